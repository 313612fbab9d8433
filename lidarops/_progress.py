"""Progress bars, optional: tqdm when it is installed and wanted, else a stand-in that does nothing
(lidarops runs without tqdm; the long jobs also print plain lines)."""
from __future__ import annotations

from typing import Any, Iterable

__all__ = ["tqdm_class", "progress_bar", "progress", "NoBar"]


def tqdm_class(enabled: bool = True, auto: bool = False):
    """tqdm's class (``tqdm.auto``'s with ``auto``), or None when disabled or not installed."""
    if not enabled:
        return None
    try:
        if auto:
            from tqdm.auto import tqdm
        else:
            from tqdm import tqdm
    except ImportError:  # tqdm is optional
        return None
    return tqdm


class NoBar:
    """What :func:`progress_bar` returns without tqdm: a bar that shows nothing."""

    n = 0

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_postfix_str(self, *args: Any, **kwargs: Any) -> None:
        pass

    def write(self, *args: Any, **kwargs: Any) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(total: int, desc: str, enabled: bool = True, unit: str = "frame", **kwargs: Any):
    """A tqdm bar over ``total`` items, or a :class:`NoBar`."""
    tqdm = tqdm_class(enabled)
    return NoBar() if tqdm is None else tqdm(total=total, desc=desc, unit=unit, **kwargs)


def progress(iterable: Iterable, total: int, desc: str, enabled: bool = True, unit: str = "frame") -> Iterable:
    """``iterable`` wrapped in a tqdm bar, or as it is."""
    tqdm = tqdm_class(enabled)
    return iterable if tqdm is None else tqdm(iterable, total=total, desc=desc, unit=unit)
