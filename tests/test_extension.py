"""Tests of the build and loading: lidarops.extension, the lazy top-level package, build errors.

Build failures are simulated honestly: a copy of the Python sources without the compiled library
(a source checkout that was never built), the same with an unloadable ``_C`` file (a broken build),
and one whose ``_build_info.json`` names another torch (a stale build) -- each loaded in a fresh
interpreter. CUDA tensors reaching a build without CUDA kernels use real CUDA tensors where torch
has them, and FakeTensor CUDA tensors otherwise (the wrapper check only reads ``tensor.device``).
"""
from __future__ import annotations

import importlib.machinery
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

import lidarops
from lidarops import extension
from lidarops.extension import LidaropsBuildError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OPS = ("fps", "knn", "ball_query", "gather", "gather_backward")


def _run(code: str, pythonpath: str = REPO, *args) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter that imports lidarops from ``pythonpath``."""
    env = {**os.environ, "PYTHONPATH": pythonpath}
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=pythonpath, env=env,
                          capture_output=True, text=True, timeout=120)


def _minor(v: str) -> str:
    return ".".join(v.split("+")[0].split(".")[:2])


def test_build_info_describes_the_loaded_library():
    lib = extension.load()
    assert extension.load() is lib  # loaded once
    info = extension.build_info()
    assert {"torch_version", "with_cuda", "cuda_reason", "arch_list"} <= set(info)
    assert _minor(info["torch_version"]) == _minor(torch.__version__)
    assert lib.torch_version == _minor(torch.__version__)
    assert bool(lib.with_cuda) == bool(info["with_cuda"]) == extension.cuda_available()
    if info["with_cuda"]:
        assert torch.version.cuda is not None


def test_every_op_is_registered_with_its_kernels():
    extension.load()
    has = torch._C._dispatch_has_kernel_for_dispatch_key
    for op in OPS:
        name = f"lidarops::{op}"
        assert hasattr(torch.ops.lidarops, op)
        assert has(name, "CPU"), f"{name} has no CPU kernel"
        if extension.cuda_available():
            assert has(name, "CUDA"), f"{name} has no CUDA kernel although lidarops was built with CUDA"
        assert has(name, "Meta"), f"{name} has no fake (meta) kernel"
        if op != "fps":
            assert has(name, "Autograd"), f"{name} has no autograd formula"


def test_package_attributes():
    assert lidarops.__version__
    for name in ("fps", "knn", "ball_query", "gather", "validation"):
        assert name in dir(lidarops) and callable(getattr(lidarops, name))
    with pytest.raises(AttributeError, match="no_such_op"):
        lidarops.no_such_op  # noqa: B018


def test_import_is_lazy():
    """``import lidarops`` and ``import lidarops.data`` load neither the compiled library nor torch;
    the first op access loads both."""
    code = r"""
import importlib.util, sys
import lidarops
assert "lidarops._C" not in sys.modules and "torch" not in sys.modules, "import lidarops loaded _C/torch"
if importlib.util.find_spec("lidarops.data") is not None:
    import lidarops.data
    assert "lidarops._C" not in sys.modules, "import lidarops.data loaded lidarops._C"
    assert "torch" not in sys.modules, "import lidarops.data imported torch"
lidarops.knn
assert "lidarops._C" in sys.modules
import torch
assert hasattr(torch.ops.lidarops, "knn")
print("ok")
"""
    proc = _run(code)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-3000:]


_BUILD_ERRORS = r"""
import importlib, json, os, sys
root = sys.argv[1]
pkg = os.path.join(root, "lidarops")

def fresh():
    for name in [m for m in sys.modules if m == "lidarops" or m.startswith("lidarops.")]:
        del sys.modules[name]
    importlib.invalidate_caches()
    import lidarops
    from lidarops.extension import LidaropsBuildError
    return lidarops, LidaropsBuildError

failures = []

def expect(what, *needles):
    lidarops, LidaropsBuildError = fresh()
    try:
        lidarops.knn
    except LidaropsBuildError as e:
        msg = str(e)
        missing = [n for n in needles if n not in msg]
        if missing:
            failures.append(f"{what}: the message lacks {missing}: {msg}")
        else:
            print(f"{what}: ok: {msg}")
        return
    except Exception as e:
        failures.append(f"{what}: {type(e).__name__} instead of LidaropsBuildError: {e}")
        return
    failures.append(f"{what}: no error")

# 1. never built: no _C, no _build_info.json
expect("not built", "not built", "pip install --no-build-isolation -e .")
# 2. broken build: a _C file that cannot be loaded
with open(os.path.join(pkg, "_C" + sys.argv[2]), "w") as f:
    f.write("not an ELF file")
expect("broken", "failed to load", "pip install --no-build-isolation -e .")
# 3. stale build: built against another torch
with open(os.path.join(pkg, "_build_info.json"), "w") as f:
    json.dump({"torch_version": "2.4.0", "with_cuda": False}, f)
expect("stale", "built against torch 2.4.0", "rebuild")
print("\n".join(failures) if failures else "all ok")
"""


def test_build_errors_are_one_clear_error(tmp_path):
    src = os.path.join(REPO, "lidarops")
    shutil.copytree(src, tmp_path / "lidarops",
                    ignore=shutil.ignore_patterns("_C*", "_build_info.json", "__pycache__", "*.so", "*.pyd"))
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    proc = _run(_BUILD_ERRORS, str(tmp_path), tmp_path, suffix)
    assert proc.returncode == 0 and "all ok" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-1000:]


def test_version_mismatch_in_process(monkeypatch):
    """The same check in this process: load() refuses a library built for another torch."""
    monkeypatch.setattr(extension, "_lib", None)
    monkeypatch.setattr(extension, "build_info", lambda: {"torch_version": "1.13.1+cu117"})
    with pytest.raises(LidaropsBuildError, match="1.13.1"):
        extension.load()


def _cuda_tensors_on_a_build_without_cuda(monkeypatch):
    """Yields (context, device) in which 'cuda' tensors reach lidarops built without CUDA kernels."""
    import contextlib

    if torch.cuda.is_available():
        if extension.cuda_available():
            # a CUDA build: pretend its CUDA kernels are missing (the wrapper asks cuda_available())
            monkeypatch.setattr(extension, "cuda_available", lambda: False)
        return contextlib.nullcontext()
    from torch._subclasses.fake_tensor import FakeTensorMode

    return FakeTensorMode()


def test_cuda_tensor_on_a_cpu_only_build(monkeypatch):
    ctx = _cuda_tensors_on_a_build_without_cuda(monkeypatch)
    with ctx:
        p = torch.zeros(2, 10, 3, device="cuda")
        x = torch.zeros(2, 10, 4, device="cuda")
        idx = torch.zeros(2, 3, dtype=torch.long, device="cuda")
        calls = {
            "fps": lambda: lidarops.fps(p, 4),
            "knn": lambda: lidarops.knn(p, p, 4),
            "ball_query": lambda: lidarops.ball_query(p, p, 1.0, 4),
            "gather": lambda: lidarops.gather(x, idx),
        }
        for name, call in calls.items():
            with pytest.raises(LidaropsBuildError) as err:
                call()
            msg = str(err.value)
            assert "CUDA" in msg and "without CUDA kernels" in msg and "FORCE_CUDA" in msg, f"{name}: {msg}"


def test_check_device_accepts_cpu_and_meta():
    extension.check_device(torch.zeros(1), "x")
    extension.check_device(torch.zeros(1, device="meta"), "x")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_gpu_machine_has_cuda_kernels():
    """On a machine where torch sees a GPU, the build must include the CUDA kernels (setup.py builds
    them when a toolkit is present); set LIDAROPS_NO_CUDA_EXPECTED=1 to allow a CPU-only build."""
    if os.environ.get("LIDAROPS_NO_CUDA_EXPECTED") == "1":
        pytest.skip("CPU-only build expected")
    assert extension.cuda_available(), f"lidarops was built without CUDA kernels: {extension.build_info()}"


def test_build_info_json_is_valid():
    path = os.path.join(REPO, "lidarops", "_build_info.json")
    with open(path) as f:
        info = json.load(f)
    assert info == extension.build_info()
