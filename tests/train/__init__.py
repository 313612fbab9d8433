"""Tests of lidarops/train/ (the training loop; DDP on two GPUs)."""
