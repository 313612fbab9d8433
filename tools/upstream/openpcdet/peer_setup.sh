#!/usr/bin/env bash
# OpenPCDet ready to run on the GPU machine, from what the device call carries (README.md here lists it):
# .peers/openpcdet-src (git archive of its pcdet/ tools/ setup.py, with COMMIT), .peers/wheels (its pure-Python
# needs) and .peers/spconv_site.tar.xz (../shared/tools/spconv-bundle.sh). From the repository root:
#   peers=$(bash tools/upstream/openpcdet/peer_setup.sh) || exit 1; eval "$peers"
# Installs the packages into $SITE (default /tmp/site), builds OpenPCDet's ops into the source tree
# (build_ops.py; NO_OPS_BUILD=1 leaves them unbuilt, for lidarops' faces) and prints the PYTHONPATH to export
# (the only line on stdout; progress goes to stderr). What an earlier run did is skipped.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../../.."
exec 3>&1 1>&2
SITE=${SITE:-/tmp/site}
SRC=$PWD/.peers/openpcdet-src
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}

# the stamp names what was installed (file names and the bundle's size), so other peers install again
want=$(ls .peers/wheels; wc -c < .peers/spconv_site.tar.xz)
if [ "$(cat "$SITE/.openpcdet-peers" 2>/dev/null)" != "$want" ]; then
  mkdir -p "$SITE"
  tar xJf .peers/spconv_site.tar.xz -C "$SITE"
  python3 -m pip install -q --no-index --no-deps --no-cache-dir --upgrade --target "$SITE" .peers/wheels/*.whl
  # an sdist (no wheel is published), compiled here against the image's NumPy
  python3 -m pip install -q --no-index --no-deps --no-cache-dir --upgrade --no-build-isolation --target "$SITE" \
    .peers/wheels/SharedArray-*.tar.gz
  PYTHONPATH=$SITE python3 -c "import spconv.pytorch, easydict, SharedArray, av2, kornia, torchvision"
  echo "$want" > "$SITE/.openpcdet-peers"
  echo "[peer_setup] OpenPCDet's Python needs installed in $SITE"
fi
if [ -z "${NO_OPS_BUILD:-}" ]; then
  python3 tools/upstream/openpcdet/build_ops.py "$SRC" --missing
fi
echo "export PYTHONPATH=$SITE:$PWD\${PYTHONPATH:+:\$PYTHONPATH}" >&3
