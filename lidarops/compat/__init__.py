"""Drop-in faces of other libraries, built on the lidarops core ops (minimal version of the sparse
branch: the lead merges it with the package's full compat/__init__.py, which loads each face lazily).

    import lidarops.compat.spconv as spconv
"""
from __future__ import annotations

import importlib

_FACES = ("spconv",)

__all__ = list(_FACES)


def __getattr__(name: str):
    if name in _FACES:
        module = importlib.import_module(f"{__name__}.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_FACES))
