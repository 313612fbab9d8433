"""Models built on lidarops' ops: :mod:`lidarops.models.pointpillars` (pillar feature net, the dense and
sparse PointPillars backbone)."""
