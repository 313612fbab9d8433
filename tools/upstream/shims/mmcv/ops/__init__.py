from lidarops.compat.mmcv import (  # noqa: F401
    ball_query,
    furthest_point_sample,
    furthest_point_sample_with_dist,
    gather_points,
    grouping_operation,
    knn,
    three_nn,
)
