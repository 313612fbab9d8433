"""The property-based fuzz suite (fuzzing.py: settings, strategies and the one rule every fuzz test asserts)."""
