"""File checks of :mod:`lidarops.data` (NumPy only, no torch), and the ground floor's argument checks.

Every error is a ``ValueError`` (``FileNotFoundError`` for a missing file) that names the argument or
the file and says what was expected, so a bad value is refused where it enters, not turned into a NaN,
a truncated number, a hang or an exception from deep inside NumPy.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lidarops._checks import flag, integer, real  # noqa: F401  (the data floor's callers import them from here)

__all__ = ["real", "integer", "flag", "require_file", "read_text", "record_count", "finite_rows", "read_float32_records",
           "read_npz"]


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def require_file(path, what: str) -> Path:
    """``path`` as a Path to an existing regular file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}" + (" (a directory)" if path.is_dir() else ""))
    return path


def read_text(path: Path, what: str) -> str:
    """A text file decoded as UTF-8, a leading byte-order mark dropped (editors on Windows write one; left in,
    it would become part of the first field); binary junk is a ValueError that names the file and the byte."""
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a {what} text file (byte {e.start} is {data[e.start:e.start + 1]!r}, "
                         "not UTF-8 text)") from None


def record_count(path: Path, record_bytes: int, layout: str) -> int:
    """Number of fixed-size records in a binary file, from its size in bytes: a size that is not a
    whole number of records (a truncated or foreign file) is a ValueError."""
    size = path.stat().st_size
    if size % record_bytes:
        raise ValueError(f"{path}: {size} bytes is not a whole number of records of {record_bytes} bytes ({layout}); "
                         f"the file is truncated or not in this format ({size // record_bytes} whole records, "
                         f"{size % record_bytes} bytes left over)")
    return size // record_bytes


def finite_rows(values: np.ndarray, path: Path, what: str) -> None:
    """ValueError naming the file and the first record that holds a NaN or an infinity."""
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.flatnonzero(bad.reshape(values.shape[0], -1).any(axis=1))[0])
        raise ValueError(f"{path}: {what} {row} holds a NaN or infinite value ({values[row].tolist()}); "
                         f"{int(bad.reshape(values.shape[0], -1).any(axis=1).sum())} such record(s) in the file")


def read_float32_records(path: Path, columns: int, layout: str, what: str) -> np.ndarray:
    """float32[n, columns] from a headerless binary file (KITTI, nuScenes scans): the size must be a
    whole number of records and every value finite (errors name the file and the first bad record)."""
    n = record_count(path, 4 * columns, layout)
    values = np.fromfile(path, dtype=np.float32)
    if values.size != columns * n:
        raise ValueError(f"{path}: read {values.size} floats but the file size says {columns * n}; "
                         "it changed while being read")
    values = values.reshape(n, columns)
    finite_rows(values, path, what)
    return values


def read_npz(path: Path, fields, what: str) -> dict:
    """The named arrays of a NumPy ``.npz`` archive, read whole (no pickles); ``what`` with its article
    (``"an object set"``).

    A damaged archive fails inside ``zipfile``/``zlib``/NumPy with a dozen exception types depending on
    the byte hit (BadZipFile, EOFError, zlib.error, a bad CRC, a bad ``.npy`` header, NotImplementedError
    for an unknown zip version, RuntimeError for an "encrypted" member...); each becomes a
    ValueError that names the file, and so does a missing array.
    """
    import tokenize
    import zipfile
    import zlib

    try:
        with np.load(path, allow_pickle=False) as z:
            missing = sorted(set(fields) - set(z.files))
            if missing:
                raise ValueError(f"{path}: not {what} (missing {missing})")
            return {name: z[name] for name in fields}
    except ValueError as e:
        if str(path) in str(e):
            raise
        raise ValueError(f"{path}: not a readable .npz archive, so not {what} ({e})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, IndexError, TypeError, SyntaxError,
            tokenize.TokenError, MemoryError, OverflowError, RecursionError, UnicodeDecodeError,
            NotImplementedError, RuntimeError) as e:  # zipfile: an unknown version or method, an "encrypted" flag
        raise ValueError(f"{path}: not a readable .npz archive, so not {what} ({type(e).__name__}: {e})") from None
