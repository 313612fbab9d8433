"""Build OpenPCDet's compiled ops in place, only the ones asked for (its setup.py builds all of them).

    python tools/upstream/openpcdet/build_ops.py .peers/OpenPCDet [OP ...] [--missing]    (default: all of them)

Compiles each op's sources (the lists of OpenPCDet's setup.py) with ``torch.utils.cpp_extension.load``
(ninja; ``TORCH_CUDA_ARCH_LIST`` picks the GPU) and puts the library where OpenPCDet imports it
(``pcdet/ops/<op>/<name>.so``). Writes ``pcdet/version.py`` as its setup.py does (the commit from git, or
from a ``COMMIT`` file beside ``pcdet/`` in a copy made with ``git archive``). ``--missing``: only the ops whose
library is not there yet (``peer_setup.sh`` runs it so, to skip what an earlier call built). Needs CUDA.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

OPS = {  # OpenPCDet's setup.py: module -> (extension name, sources)
    "iou3d_nms": ("pcdet/ops/iou3d_nms", "iou3d_nms_cuda",
                  ["src/iou3d_cpu.cpp", "src/iou3d_nms_api.cpp", "src/iou3d_nms.cpp", "src/iou3d_nms_kernel.cu"]),
    "roiaware_pool3d": ("pcdet/ops/roiaware_pool3d", "roiaware_pool3d_cuda",
                        ["src/roiaware_pool3d.cpp", "src/roiaware_pool3d_kernel.cu"]),
    "pointnet2_batch": ("pcdet/ops/pointnet2/pointnet2_batch", "pointnet2_batch_cuda",
                        ["src/pointnet2_api.cpp", "src/ball_query.cpp", "src/ball_query_gpu.cu", "src/group_points.cpp",
                         "src/group_points_gpu.cu", "src/interpolate.cpp", "src/interpolate_gpu.cu", "src/sampling.cpp",
                         "src/sampling_gpu.cu"]),
    "pointnet2_stack": ("pcdet/ops/pointnet2/pointnet2_stack", "pointnet2_stack_cuda",
                        ["src/pointnet2_api.cpp", "src/ball_query.cpp", "src/ball_query_gpu.cu", "src/group_points.cpp",
                         "src/group_points_gpu.cu", "src/sampling.cpp", "src/sampling_gpu.cu", "src/interpolate.cpp",
                         "src/interpolate_gpu.cu", "src/voxel_query.cpp", "src/voxel_query_gpu.cu", "src/vector_pool.cpp",
                         "src/vector_pool_gpu.cu"]),
    "roipoint_pool3d": ("pcdet/ops/roipoint_pool3d", "roipoint_pool3d_cuda",
                        ["src/roipoint_pool3d.cpp", "src/roipoint_pool3d_kernel.cu"]),
    "bev_pool": ("pcdet/ops/bev_pool", "bev_pool_ext", ["src/bev_pool.cpp", "src/bev_pool_cuda.cu"]),
    # imported unguarded by pcdet.models (DSVT): `import pcdet.models` fails without it
    "ingroup_inds": ("pcdet/ops/ingroup_inds", "ingroup_inds_cuda", ["src/ingroup_inds.cpp", "src/ingroup_inds_kernel.cu"]),
}


def build(src: Path, name: str) -> str:
    from torch.utils.cpp_extension import load

    folder, ext, sources = OPS[name]
    t0 = time.time()
    out = Path(tempfile.mkdtemp(prefix=f"pcdet_{ext}_"))
    load(name=ext, sources=[str(src / folder / s) for s in sources], build_directory=str(out), verbose=False)
    shutil.copy(out / f"{ext}.so", src / folder / f"{ext}.so")
    return f"built {folder}/{ext}.so in {time.time() - t0:.0f} s"


def commit_of(src: Path) -> str:
    """OpenPCDet's commit: from ``src/COMMIT`` (a ``git archive`` copy records it there), else from ``src``'s own git;
    "" when neither says."""
    if (src / "COMMIT").is_file():
        return (src / "COMMIT").read_text().strip()
    if (src / ".git").exists():  # not git's answer for a tree inside another checkout (.peers/ in lidarops')
        out = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True)
        return out.stdout.strip() if out.returncode == 0 else ""
    return ""


def main(argv: list[str]) -> int:
    missing = "--missing" in argv
    argv = [a for a in argv if a != "--missing"]
    if not argv:
        print(__doc__)
        return 2
    src = Path(argv[0]).resolve()
    names = argv[1:] or list(OPS)
    unknown = [n for n in names if n not in OPS]
    if unknown:
        raise SystemExit(f"unknown ops {unknown}; known: {list(OPS)}")
    if missing:
        names = [n for n in names if not (src / OPS[n][0] / f"{OPS[n][1]}.so").is_file()]

    version = "0.6.0+" + (commit_of(src) or "0000000")[:7]
    (src / "pcdet/version.py").write_text(f'__version__ = "{version}"\n')
    t0 = time.time()
    if names:
        with ProcessPoolExecutor(len(names)) as pool:  # each op compiles with its own ninja, side by side
            for line in pool.map(build, [src] * len(names), names):
                print(line)
    print(f"{len(names)} ops built in {time.time() - t0:.0f} s" if names else "every op built already")
    print(f"OpenPCDet {version} at {src}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
