"""``sample_farthest_points`` is lidarops' face; ``sample_farthest_points_naive``, the tests' reference,
is upstream's own, from the fetched ``pytorch3d/ops/sample_farthest_points.py`` (its other function calls
compiled PyTorch3D and is not used)."""
from lidarops.compat.pytorch3d import sample_farthest_points  # noqa: F401

from . import _upstream_module

sample_farthest_points_naive = _upstream_module("sample_farthest_points").sample_farthest_points_naive
