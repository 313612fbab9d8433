"""Tests of lidarops/ops/ (neighbours, boxes, voxelize, pillars, value checks, every registered op's bounds)."""
