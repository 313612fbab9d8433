"""Tests of lidarops/sscater/ (the delta-convolution ops and the recycling backbone)."""
