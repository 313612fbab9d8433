"""Tests of lidarops/eval/ (the KITTI evaluation)."""
