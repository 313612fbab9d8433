"""Tests of lidarops/models/ (PointPillars, the BEV backbone, anchors, SSCATeR's model and calibration)."""
