"""Install what lidarops needs into the running interpreter, only what is missing.

Run by `make` with the interpreter it chose; prints make's "environment" line. Offline (the GPU
machine) nothing is downloaded when everything required is already there; optional packages that
cannot be installed are reported and the tests that need them skip.
"""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys

TORCH = "torch==2.13.0"  # the CPU wheel on the development machines; never pulled when torch exists
# torch ships the pybind11 headers the build needs; the pybind11 and wheel packages are for pip installs
REQUIRED = {"numpy": "numpy", "pytest": "pytest", "setuptools": "setuptools>=64", "yaml": "pyyaml"}
OPTIONAL = {"pybind11": "pybind11", "wheel": "wheel", "scipy": "scipy", "hypothesis": "hypothesis", "tqdm": "tqdm", "matplotlib": "matplotlib",
            "h5py": "h5py", "pandas": "pandas", "fpsample": "fpsample", "shapely": "shapely",
            "onnxscript": "onnxscript", "onnxruntime": "onnxruntime", "xdist": "pytest-xdist",
            "duckdb": "duckdb", "pyarrow": "pyarrow", "skimage": "scikit-image"}


def missing(mods: dict) -> list[str]:
    return [spec for mod, spec in mods.items() if importlib.util.find_spec(mod) is None]


def ninja_missing() -> bool:
    return shutil.which("ninja") is None and importlib.util.find_spec("ninja") is None


def pip(*specs: str, quick: bool = False) -> bool:
    """pip install; ``quick`` gives up at once when no package index answers (offline machines)."""
    if not specs:
        return True
    print(f"[make] environment: pip install {' '.join(specs)}", flush=True)
    extra = ["--retries", "0", "--timeout", "5"] if quick else []
    # -qq: errors only (pip warns about every configured find-links folder a package is not in)
    return subprocess.call([sys.executable, "-m", "pip", "install", "-qq", *extra, *specs]) == 0


def main() -> int:
    if importlib.util.find_spec("torch") is None and not pip(TORCH):
        print(f"[make] environment: could not install {TORCH}", file=sys.stderr)
        return 1
    if ninja_missing() and not pip("ninja"):
        print("[make] environment: could not install ninja", file=sys.stderr)
        return 1
    if not pip(*missing(REQUIRED)):
        print("[make] environment: could not install required packages: " + ", ".join(missing(REQUIRED)),
              file=sys.stderr)
        return 1
    opt = missing(OPTIONAL)
    if opt and not pip(*opt, quick=True):
        still = missing(OPTIONAL)
        if still:
            print("[make] environment: optional packages unavailable (their tests skip): " + ", ".join(still))
    import torch
    cuda = f"CUDA {torch.version.cuda}" if torch.version.cuda else "CPU-only torch"
    gpu = f", {torch.cuda.device_count()} GPU(s) visible" if torch.version.cuda and torch.cuda.is_available() else ""
    exe = os.path.relpath(sys.executable) if not os.path.relpath(sys.executable).startswith("..") else sys.executable
    print(f"[make] environment: {exe} (Python {sys.version.split()[0]}), torch {torch.__version__} ({cuda}{gpu})",
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
