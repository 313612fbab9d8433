"""Lazy attributes for packages whose submodules import torch or the compiled library: ``import
lidarops.models`` stays light, and ``lidarops.models.PointPillars`` imports its module on first use."""
from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping


def lazy_attributes(package: str, table: Mapping[str, "tuple[str, str] | str"], namespace: dict
                    ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package``: ``table`` maps a name to ``(module, attribute)`` or to
    a submodule path; the value is cached in ``namespace`` (the package's globals) on first access."""

    def __getattr__(name: str) -> Any:
        target = table.get(name)
        if target is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        if isinstance(target, str):
            value = importlib.import_module(target)
        else:
            value = getattr(importlib.import_module(target[0]), target[1])
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(table))

    return __getattr__, __dir__
