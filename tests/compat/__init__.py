"""Tests of lidarops/compat/ (the pytorch3d, mmcv, torch_cluster and spconv faces)."""
