"""Regression tests of hardened inputs: each fails if its guard is removed."""
