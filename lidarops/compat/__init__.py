"""Drop-in faces of other libraries, built on the lidarops core ops.

Each face reproduces the argument order, shapes, dtypes, padding values and tie rules of the library
it imitates, so code written against that library can switch its import::

    from lidarops.compat.pytorch3d import knn_points, ball_query, sample_farthest_points, knn_gather
    from lidarops.compat.mmcv import furthest_point_sample, ball_query, knn, three_nn, \\
        gather_points, grouping_operation
    from lidarops.compat.torch_cluster import fps, knn, radius, knn_graph, radius_graph  # TorchScript-able
    from lidarops.compat.spconv_utils import PointToVoxel
    import lidarops.compat.spconv as spconv   # SparseConvTensor, SubMConv3d, ... (spconv 2.x)
    from lidarops.compat.pcdet import iou3d_nms_utils, roiaware_pool3d_utils   # OpenPCDet's compiled ops

==================  ==========================================================================
face                convention
==================  ==========================================================================
``pytorch3d``       padded ``(N, P, D)`` + lengths; knn pads idx 0 / dists 0; ball query pads -1 / 0
``mmcv``            ``(B, N, 3)`` or stacked + counts, int32 indices padded with valid indices
``torch_cluster``   flat ``(N, F)`` + sorted batch vector; edge index ``(2, E)`` [row = y, col = x]; scripts
``pcdet``           OpenPCDet's ``pcdet.ops`` modules; ``pcdet.install()`` serves them to OpenPCDet's code
==================  ==========================================================================

The full table, with every known deviation, is ``docs/compat.md``. Importing this package is light:
each face (and the compiled library) loads on first access.
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes

_FACES = ("pytorch3d", "mmcv", "torch_cluster", "spconv", "spconv_utils", "pcdet")

__all__ = list(_FACES)

__getattr__, __dir__ = lazy_attributes(__name__, {face: f"{__name__}.{face}" for face in _FACES}, globals())
