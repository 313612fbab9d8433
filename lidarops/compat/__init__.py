"""Drop-in faces of other libraries (spconv, pytorch3d, mmcv, torch_cluster), built on lidarops' ops.

Import the face you need, e.g. ``from lidarops.compat.spconv_utils import PointToVoxel``.
"""
