"""Shim: ``pytorch3d.ops`` with lidarops' face for the neighbour ops.

Modules of ``pytorch3d.ops`` that are not here come from the fetched upstream copy,
``$UPSTREAM_DIR/pytorch3d/pytorch3d/ops`` (appended to this package's search path, so a module here
wins over upstream's of the same name): ``utils.py`` (``masked_gather``) runs unchanged.
"""
import importlib.util
import os
import sys

from lidarops.compat.pytorch3d import ball_query, knn_gather, knn_points, sample_farthest_points  # noqa: F401

from .sample_points_from_meshes import sample_points_from_meshes  # noqa: F401

_fetched = os.path.join(os.environ.get("UPSTREAM_DIR", ""), "pytorch3d", "pytorch3d", "ops")
if os.path.isdir(_fetched):
    __path__.append(_fetched)  # noqa: F821 (a package's __path__)


def _upstream_module(name: str):
    """Upstream's ``pytorch3d/ops/<name>.py`` from the fetched copy, unchanged, under the name
    ``pytorch3d.ops._upstream_<name>`` (the module of that name here is the face's)."""
    path = os.path.join(_fetched, name + ".py")
    if not os.path.isfile(path):
        raise ImportError(f"{path} is missing: fetch it as tools/upstream/fetch.md says")
    spec = importlib.util.spec_from_file_location(f"{__name__}._upstream_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
