#!/usr/bin/env bash
# Run the upstream libraries' own test files, unmodified, against lidarops' compat faces.
#
#   tools/upstream/run.sh [UPSTREAM_DIR [LIBRARY]]   (default: .upstream at the repository root, every library)
#
# LIBRARY, a folder of UPSTREAM_DIR (torch_cluster, torch_cluster_scripted, mmcv, pytorch3d), runs only its files.
#
# UPSTREAM_DIR holds the files listed in tools/upstream/fetch.md (not committed: they are not ours).
# tools/upstream/shims/ goes first on PYTHONPATH, so `import torch_cluster`, `import mmcv.ops` and
# `import pytorch3d.ops` load lidarops' faces. Prints one summary line per test file, then the totals.
# Not part of `make test`: the files must be fetched first. Tests that need CUDA skip on CPU machines
# (PyTorch3D's through tools/upstream/upstream_plugin.py). Python: $PYTHON, else the repository's .venv,
# else python3 (the GPU machine's).
set -u
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
UPSTREAM_DIR="$(cd "${1:-$ROOT/.upstream}" && pwd)" || { echo "no upstream folder; see tools/upstream/fetch.md"; exit 2; }
[ -d "$UPSTREAM_DIR/${2:-}" ] || { echo "no folder $UPSTREAM_DIR/${2:-}"; exit 2; }
PY="${PYTHON:-$ROOT/.venv/bin/python}"
[ -x "$PY" ] || PY="$(command -v python3 || command -v python)"
export UPSTREAM_DIR
device="cpu"
"$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null && device="cuda"
echo "upstream tests against lidarops faces (CUDA: $([ $device = cuda ] && echo yes || echo no); $UPSTREAM_DIR)"
status=0
summary=()
while IFS= read -r f; do
    dir="$(dirname "$f")"
    # each file runs from its own folder (PyTorch3D's tests folder is a package, `tests`, whose files
    # import `.common_testing`; pytest imports them as tests.test_*)
    out="$(cd "$dir" && PYTHONPATH="$ROOT/tools/upstream/shims:$ROOT/tools/upstream:$dir:$ROOT${PYTHONPATH:+:$PYTHONPATH}" \
        "$PY" -m pytest -q -p no:cacheprovider -p upstream_plugin -rfE --rootdir "$dir" "$(basename "$f")" 2>&1)"
    rc=$?
    [ $rc -ne 0 ] && [ $rc -ne 5 ] && status=1
    line="$(printf '%s\n' "$out" | grep -E '^(=+ )?[0-9]+ (passed|failed|skipped|error)|^=+ .*(passed|failed|skipped|error|no tests ran)' | tail -1 | sed 's/=//g; s/^ *//; s/ *$//')"
    [ -z "$line" ] && line="rc=$rc (no summary: collection error?)"
    printf '%s\n' "$out" | grep -E '^(FAILED|ERROR) ' | sed "s|^|    |"
    rel="${f#$UPSTREAM_DIR/}"
    summary+=("$(printf '%-62s %s' "$rel" "$line")")
done < <(find "$UPSTREAM_DIR/${2:-}" -name 'test_*.py' | sort)
echo
echo "per-file summary ($device):"
printf '  %s\n' "${summary[@]}"
exit $status
