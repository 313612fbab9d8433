"""Tests of lidarops/stream/ (PillarStream: steps, faults, corrupt state, overflow)."""
