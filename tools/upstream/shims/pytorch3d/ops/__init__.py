from lidarops.compat.pytorch3d import ball_query, knn_gather, knn_points, sample_farthest_points  # noqa: F401
