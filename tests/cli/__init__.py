"""Tests of the command line (lidarops/cli/), one file per command."""
