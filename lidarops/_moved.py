"""Old import paths of what the model floor's re-lay moved (0.2.0): each still works for one release,
with one ``DeprecationWarning`` naming the new path (the list is CHANGELOG.md's).

Two mechanisms, both tables kept here so that a package never imports a floor above it to serve an
old name:

- :data:`MOVED_MODULES`: a module that no longer exists (``lidarops.models.detector``) imports as an
  alias whose attributes are looked up in the modules that now hold them;
- :func:`moved_attributes`: a package's ``__getattr__`` for names that moved out of it
  (``lidarops.sscater.SSCATeRPointPillars`` is ``lidarops.models.SSCATeRPointPillars``).
"""
from __future__ import annotations

import functools
import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from typing import Any, Callable, Mapping

__all__ = ["MOVED_MODULES", "MOVED_ATTRIBUTES", "moved_attributes", "install", "warn_renamed", "renamed_argument", "renamed_kwargs"]

_UNSET = object()

#: old module -> the modules that now hold its public names, searched in order
MOVED_MODULES: dict[str, tuple[str, ...]] = {
    "lidarops.models.detector": ("lidarops.models.pointpillars", "lidarops.models.pillar_vfe",
                                 "lidarops.models.map_to_bev", "lidarops.models.anchor_head",
                                 "lidarops.models.losses", "lidarops.models.postprocess", "lidarops.checkpoint"),
    "lidarops.models.boxes": ("lidarops.models.anchors",),
    "lidarops.models.graph": ("lidarops.models.cuda_graph",),
    "lidarops.models.cli": ("lidarops.cli.train", "lidarops.cli.detect", "lidarops.cli.eval", "lidarops.cli.errors"),
    "lidarops.stream.pillars": ("lidarops.ops.pillars",),
    "lidarops.stream.stream": ("lidarops.stream.pillar_stream",),
    "lidarops.sscater.pointpillars": ("lidarops.models.sscater_pointpillars",),
    "lidarops.sscater.models": ("lidarops.models.sscater_calibration",),
    "lidarops.sscater.cli": ("lidarops.cli.stream",),
    "lidarops.data.cli": ("lidarops.cli.data",),
    "lidarops.tour": ("lidarops.cli.tour",),
}

#: (package, name) -> the module that now holds the name, for names that left a package
MOVED_ATTRIBUTES: dict[tuple[str, str], str] = {
    ("lidarops.sscater", "SSCATeRPointPillars"): "lidarops.models.sscater_pointpillars",
    ("lidarops.models", "load_config"): "lidarops.config",
}


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """One ``DeprecationWarning``: ``old`` is now ``new`` (removed in the release after next)."""
    warnings.warn(f"{old} is deprecated: use {new} (the old name goes in lidarops 0.3; see CHANGELOG.md)",
                  DeprecationWarning, stacklevel=stacklevel)


def renamed_kwargs(**renames: str) -> Callable:
    """Decorator: keyword arguments by their old names (``point_range=``) reach the function under their new
    ones (``point_cloud_range=``) with one deprecation warning; the function's own signature is the new one."""

    def wrap(fn: Callable) -> Callable:
        where = fn.__qualname__

        @functools.wraps(fn)
        def call(*args: Any, **kwargs: Any) -> Any:
            for old, new in renames.items():
                if old in kwargs:
                    if new in kwargs:
                        raise TypeError(f"{where}: give {new}= only ({old}= is its deprecated name)")
                    warn_renamed(f"{where}'s argument {old}=", f"{new}=")
                    kwargs[new] = kwargs.pop(old)
            return fn(*args, **kwargs)

        return call

    return wrap


def renamed_argument(where: str, new: str, new_value: Any, old: str, old_value: Any, default: Any = _UNSET) -> Any:
    """The value of argument ``new`` of ``where``, taking the deprecated keyword ``old`` (with a warning)
    when only it was given; ``TypeError`` when both were, or (without ``default``) neither."""
    if old_value is not _UNSET:
        if new_value is not _UNSET:
            raise TypeError(f"{where}: give {new}= only ({old}= is its deprecated name)")
        warn_renamed(f"{where}'s argument {old}=", f"{new}=", stacklevel=4)
        return old_value
    if new_value is _UNSET:
        if default is _UNSET:
            raise TypeError(f"{where}: missing argument {new}")
        return default
    return new_value


UNSET = _UNSET  # the default of a renamed argument's parameters, to tell "not given" from None


def moved_attributes(package: str, table: "Mapping[str, str | tuple[str, str]] | None" = None,
                     fallback: Callable[[str], Any] | None = None) -> Callable[[str], Any]:
    """A module ``__getattr__`` serving the names that moved out of ``package`` or were renamed (``table``
    maps an old name to its new module, or to ``(module, new name)``; :data:`MOVED_ATTRIBUTES` is consulted
    too), with a deprecation warning; other names go to ``fallback`` (e.g. the package's lazy attributes) or
    raise ``AttributeError``."""
    table = dict(table or {})
    table.update({name: module for (pkg, name), module in MOVED_ATTRIBUTES.items() if pkg == package})

    def __getattr__(name: str) -> Any:
        target = table.get(name)
        if target is None:
            if fallback is not None:
                return fallback(name)
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, new = (target, name) if isinstance(target, str) else target
        warn_renamed(f"{package}.{name}", f"{module}.{new}")
        return getattr(importlib.import_module(module), new)

    return __getattr__


class _AliasModule(types.ModuleType):
    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        for target in MOVED_MODULES[self.__name__]:
            module = importlib.import_module(target)
            if hasattr(module, name):
                return getattr(module, name)
        raise AttributeError(f"module {self.__name__!r} (moved to {', '.join(MOVED_MODULES[self.__name__])}) "
                             f"has no attribute {name!r}")


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED_MODULES:
            return importlib.machinery.ModuleSpec(fullname, self)
        return None

    def create_module(self, spec):
        return _AliasModule(spec.name)

    def exec_module(self, module) -> None:
        targets = MOVED_MODULES[module.__name__]
        warn_renamed(module.__name__, " / ".join(targets), stacklevel=4)


def install() -> None:
    """Serve the old module paths (called once by ``import lidarops``); the real modules' files come first."""
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.append(_Finder())
