from lidarops.compat.pytorch3d import ball_query  # noqa: F401
