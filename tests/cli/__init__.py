"""Tests of the command line (lidarops/cli/), one file per command; a package so that its conftest and
file names do not clash with those of tests/."""
