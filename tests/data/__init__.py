"""Tests of lidarops/data/ (the simulator, formats, detection items, the native ray caster)."""
