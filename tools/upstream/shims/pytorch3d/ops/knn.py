from lidarops.compat.pytorch3d import _KNN, knn_gather, knn_points  # noqa: F401
