"""Loads the compiled library ``lidarops._C`` and explains, in one error, why ops are missing.

Importing ``lidarops._C`` runs the C++ ``TORCH_LIBRARY`` registrations, after which the ops live
under ``torch.ops.lidarops``. The Python side then registers fake (meta) kernels for
``torch.compile`` and the autograd formulas.
"""
from __future__ import annotations

import importlib
import json
import os
import threading

import torch

__all__ = ["load", "cuda_available", "check_device", "build_info", "LidaropsBuildError"]

_lock = threading.RLock()
_lib = None
_HERE = os.path.dirname(os.path.abspath(__file__))
# One <package>/_registrations.py per package of wrappers: its ops' fake (meta) kernels and Python
# autograd formulas.
_REGISTRATION_MODULES = (
    "lidarops.ops._registrations",
    "lidarops.data._registrations",
    "lidarops.eval._registrations",
    "lidarops.sparse._registrations",
    "lidarops.stream._registrations",
    "lidarops.sscater._registrations",
)


class LidaropsBuildError(RuntimeError):
    """The compiled part of lidarops is missing, stale, or lacks the kernels asked for."""


def build_info() -> dict:
    """How ``lidarops._C`` was built: torch version, CUDA or not, arch list (from ``_build_info.json``)."""
    try:
        with open(os.path.join(_HERE, "_build_info.json")) as f:
            return json.load(f)
    except OSError:
        return {}


def _torch_minor(version: str) -> str:
    return ".".join(version.split("+")[0].split(".")[:2])


def load():
    """Import ``lidarops._C`` once and register the Python-side kernels; returns the module."""
    global _lib
    if _lib is not None:
        return _lib
    with _lock:
        if _lib is not None:
            return _lib
        info = build_info()
        built_with = info.get("torch_version")
        if built_with and _torch_minor(built_with) != _torch_minor(torch.__version__):
            raise LidaropsBuildError(
                f"lidarops was built against torch {built_with} but torch {torch.__version__} is imported; "
                "rebuild it: pip install --no-build-isolation -e . (or make build)")
        try:
            _C = importlib.import_module("lidarops._C")  # runs the op registrations
        except ImportError as e:
            not_built = isinstance(e, ModuleNotFoundError) and e.name == "lidarops._C"
            hint = "lidarops' compiled ops are not built" if not_built else f"lidarops._C failed to load ({e})"
            raise LidaropsBuildError(
                f"{hint}. Build them with `make build` or `pip install --no-build-isolation -e .` "
                f"from the repository root (torch {torch.__version__}).") from e
        if not hasattr(torch.ops.lidarops, "fps"):
            raise LidaropsBuildError("lidarops._C loaded but registered no ops; rebuild the extension")
        # Set before the registration modules are imported: they import wrappers that call load().
        _lib = _C
        for module in _REGISTRATION_MODULES:
            importlib.import_module(module)
        return _lib


def cuda_available() -> bool:
    """True when the library was built with its CUDA kernels."""
    return bool(load().with_cuda)


def check_device(t: torch.Tensor, name: str) -> None:
    """Raise one clear error when a CUDA tensor reaches a build without CUDA kernels."""
    if t.device.type == "cuda" and not cuda_available():
        info = build_info()
        raise LidaropsBuildError(
            f"{name} is a CUDA tensor but lidarops was built without CUDA kernels "
            f"({info.get('cuda_reason', 'CPU-only build')}). Rebuild on a machine with nvcc and a CUDA build "
            "of torch, or with FORCE_CUDA=1.")
    if t.device.type not in ("cpu", "cuda", "meta"):
        raise ValueError(f"{name} is on device {t.device}; lidarops ops run on cpu and cuda")
