"""Argument checks shared by every floor: numbers, ints and flags, each refused with a ``ValueError``
that names the argument and says what was expected (a bad value is refused where it enters, not turned
into a NaN, a truncated number or a hang deeper down). NumPy only; tensors are checked in
:mod:`lidarops.ops.validation`.
"""
from __future__ import annotations

import math
import numbers
import operator

import numpy as np

__all__ = ["real", "integer", "positive_int", "flag"]


def _range_text(lo, hi, lo_open: bool, hi_open: bool) -> str:
    if lo is None and hi is None:
        return ""
    if hi is None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if lo is None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def real(value, name: str, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         hi_open: bool = False, unit: str = "") -> float:
    """A finite real number in the given range, as a float.

    Python and NumPy ints and floats pass; bools, strings, complex numbers, NaN and infinities do not.
    """
    expected = f"{name} must be a finite number{_range_text(lo, hi, lo_open, hi_open)}{unit}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{expected}, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) \
            or (hi is not None and (v >= hi if hi_open else v > hi)):
        raise ValueError(f"{expected}, got {v!r}")
    return v


def integer(value, name: str, lo: int | None = None, hi: int | None = None) -> int:
    """An int in ``[lo, hi]``: Python and NumPy integers; not bools, floats (1.7 would be truncated) or
    strings."""
    expected = f"{name} must be an int{_range_text(lo, hi, False, False)}"
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{expected}, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{expected}, got {value!r}") from None
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{expected}, got {v}")
    return v


def flag(value, name: str) -> bool:
    """A bool (or a NumPy bool)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def positive_int(value, name: str) -> int:
    """An int >= 1: Python and NumPy integers (anything with ``__index__``); not bools or floats. Tensors are
    :func:`lidarops.ops.validation.check_positive_int`'s."""
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    try:  # int, NumPy integers, anything with __index__ (not floats)
        value = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be a positive int, got {value!r}") from None
    if value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value}")
    return value
