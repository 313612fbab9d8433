"""OpenPCDet's compiled ops, served by lidarops (CPU and CUDA, nothing to compile).

Building ``pcdet/ops`` (CUDA extensions compiled when OpenPCDet is installed) is where most OpenPCDet
installs fail, and those ops never run on a CPU. These faces have OpenPCDet's module names, functions,
arguments and return values, on lidarops' kernels::

    from lidarops.compat.pcdet import iou3d_nms_utils, roiaware_pool3d_utils
    from lidarops.compat.pcdet import pointnet2_batch, pointnet2_stack   # the two pointnet2_utils

or, to run OpenPCDet's own code on them (before anything imports ``pcdet``)::

    import lidarops.compat.pcdet; lidarops.compat.pcdet.install()

:func:`install` puts each face in ``sys.modules`` under the OpenPCDet module it replaces. The table of
what is covered and the deliberate differences: docs/compat.md, "OpenPCDet".
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from pathlib import Path

from lidarops._lazy import lazy_attributes

_FACES = ("iou3d_nms_utils", "roiaware_pool3d_utils", "pointnet2_batch", "pointnet2_stack")

#: the OpenPCDet module each face stands in for
REPLACES = {
    "pcdet.ops.iou3d_nms.iou3d_nms_utils": "iou3d_nms_utils",
    "pcdet.ops.roiaware_pool3d.roiaware_pool3d_utils": "roiaware_pool3d_utils",
    "pcdet.ops.pointnet2.pointnet2_batch.pointnet2_utils": "pointnet2_batch",
    "pcdet.ops.pointnet2.pointnet2_stack.pointnet2_utils": "pointnet2_stack",
}

#: OpenPCDet's compiled modules that its Python files import at import time; the ones lidarops does
#: not serve get a placeholder (when OpenPCDet's own build is absent) that raises on first use
COMPILED = {
    "pcdet.ops.iou3d_nms.iou3d_nms_cuda": "served through iou3d_nms_utils",
    "pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda": "RoIAwarePool3d (Part-A2's RoI pooling)",
    "pcdet.ops.roipoint_pool3d.roipoint_pool3d_cuda": "RoIPointPool3d (PointRCNN's RoI head)",
    "pcdet.ops.pointnet2.pointnet2_batch.pointnet2_batch_cuda": "served through pointnet2_batch",
    "pcdet.ops.pointnet2.pointnet2_stack.pointnet2_stack_cuda": "the voxel query and vector pool of PV-RCNN++",
    "pcdet.ops.bev_pool.bev_pool_ext": "bev_pool (BEVFusion)",
    "pcdet.ops.ingroup_inds.ingroup_inds_cuda": "ingroup_inds (DSVT)",
}

__all__ = list(_FACES) + ["install", "REPLACES", "COMPILED"]

__getattr__, __dir__ = lazy_attributes(__name__, {face: f"{__name__}.{face}" for face in _FACES}, globals())


class _NotServed(types.ModuleType):
    """Stands in for a compiled OpenPCDet module that is neither built nor served: importing it works
    (OpenPCDet imports every op at import time), using it says what is missing."""

    def __init__(self, name: str, what: str):
        super().__init__(name)
        self._what = what

    def __getattr__(self, attr: str):
        if attr.startswith("__"):
            raise AttributeError(attr)
        raise NotImplementedError(
            f"{self.__name__}.{attr}: OpenPCDet's compiled op for {self._what} is not built, and lidarops does "
            f"not serve it (lidarops.compat.pcdet serves: {', '.join(REPLACES)}). Build OpenPCDet's ops "
            f"(python setup.py develop in OpenPCDet) to use it.")


def _spec(name: str):
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None


def install(placeholders: bool = True) -> list[str]:
    """Serve OpenPCDet's ops from lidarops: register the faces in ``sys.modules`` under the names of the
    OpenPCDet modules they replace, so ``from pcdet.ops.iou3d_nms import iou3d_nms_utils`` (and every
    OpenPCDet file that imports it) gets lidarops'. Call it before anything imports those modules.

    Args:
        placeholders (bool): also stand in for the compiled modules that OpenPCDet imports at import time
            but lidarops does not serve (:data:`COMPILED`), where OpenPCDet's own build of them is
            absent; they raise NotImplementedError, naming the op, when used. Needed to import
            ``pcdet.models`` without OpenPCDet's compiled ops.

    Also, when an OpenPCDet checkout is importable but was never installed (``pcdet/version.py`` is
    written by its ``setup.py``), registers ``pcdet.version`` with ``__version__ = "0.0.0+lidarops"`` so
    that ``import pcdet`` works.

    Returns:
        The module names registered.
    """
    registered = []
    top = _spec("pcdet")
    if top is not None and top.origin and not (Path(top.origin).parent / "version.py").exists() \
            and "pcdet.version" not in sys.modules:
        version = types.ModuleType("pcdet.version")
        version.__version__ = "0.0.0+lidarops"
        sys.modules["pcdet.version"] = version
        registered.append("pcdet.version")
    for name, face in REPLACES.items():
        sys.modules[name] = importlib.import_module(f"{__name__}.{face}")
        registered.append(name)
    if placeholders and top is not None:
        for name, what in COMPILED.items():
            if name not in sys.modules and _spec(name) is None:
                sys.modules[name] = _NotServed(name, what)
                registered.append(name)
    return registered
