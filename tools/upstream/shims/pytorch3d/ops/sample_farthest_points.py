from lidarops.compat.pytorch3d import sample_farthest_points  # noqa: F401
