"""Argument validation shared by the op wrappers.

Shape, dtype, device and size checks are free and always on. Checks that read tensor values (NaN,
infinite or too large coordinates, lengths and indices in range) cost one small kernel per tensor
and one device-to-host copy per call on CUDA; they are on by default and skipped while
``torch.compile`` traces. Turn them off in a hot loop you have already validated::

    with lidarops.validation(False):
        ...

The switch is a context variable: it holds for the thread (or asyncio task) that entered the
``with`` block and for nothing else, so a loop that turns validation off cannot turn it off in
another thread.
"""
from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Iterator, Sequence

import torch

from lidarops._checks import positive_int

# A ContextVar rather than a module global: each thread (and asyncio task) sees its own value, and a
# new thread starts with the default (checks on).
_enabled: contextvars.ContextVar[bool] = contextvars.ContextVar("lidarops_validation", default=True)

#: Most entries an op output may have (padded outputs included): a size beyond this is an argument
#: that cannot be meant (``k = 2**31``), refused before anything is allocated.
MAX_OUTPUT_ENTRIES = 2**31 - 1


@contextlib.contextmanager
def validation(enabled: bool = True) -> Iterator[None]:
    """Context manager that enables or disables the value checks of the lidarops wrappers.

    Thread-local: it affects only the thread (or asyncio task) that enters it; other threads keep
    their own setting (on unless they turned it off themselves). Shape, dtype, device and size checks
    stay on.

    Args:
        enabled (bool): ``False`` skips the value checks inside the block.
    """
    if enabled not in (True, False):  # bool, 0/1 and NumPy bools; not "no" or None
        raise ValueError(f"enabled must be a bool, got {enabled!r}")
    token = _enabled.set(bool(enabled))
    try:
        yield
    finally:
        _enabled.reset(token)


def value_checks_enabled() -> bool:
    """Whether the value checks run here: on unless this thread turned them off with
    :func:`validation` or ``torch.compile`` is tracing."""
    if torch.compiler.is_compiling():  # first: dynamo folds it and never reads the context variable
        return False
    return _enabled.get()


def describe(t) -> str:
    if not isinstance(t, torch.Tensor):
        return f"{type(t).__name__}"
    return f"shape {tuple(t.shape)}, dtype {t.dtype}, device {t.device}"


def check_tensor(t, name: str) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")


def check_cloud(t, name: str, batch: int | None = None) -> None:
    """A (B, N, 3) floating tensor."""
    check_tensor(t, name)
    if t.dim() != 3 or t.shape[-1] != 3:
        raise ValueError(f"{name} must be (B, N, 3), got {describe(t)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point (float32, float64, float16, bfloat16), got {describe(t)}")
    if batch is not None and t.shape[0] != batch:
        raise ValueError(f"{name} must have batch size {batch}, got {describe(t)}")


def check_same_device(tensors: Sequence[tuple[str, torch.Tensor]]) -> None:
    (n0, t0), *rest = tensors
    for n, t in rest:
        if t.device != t0.device:
            raise ValueError(f"{n} is on {t.device} but {n0} is on {t0.device}; move them to one device")


def check_positive_int(v, name: str) -> int:
    """An int >= 1 (ints, NumPy ints, one-element integer tensors), else ``ValueError`` naming ``name``."""
    if isinstance(v, torch.Tensor):
        if v.numel() != 1 or v.is_floating_point() or v.is_complex() or v.dtype == torch.bool:
            raise ValueError(f"{name} must be a positive int, got {describe(v)}")
        v = int(v)
    return positive_int(v, name)


def lengths_or_full(lengths, like: torch.Tensor, name: str) -> torch.Tensor:
    """``lengths`` as an int64 (B,) tensor on ``like``'s device; None means every row is full."""
    B, N = like.shape[0], like.shape[1]
    if lengths is None:
        return torch.full((B,), N, dtype=torch.int64, device=like.device)
    if not isinstance(lengths, torch.Tensor):
        try:
            lengths = torch.as_tensor(lengths, device=like.device)
        except (TypeError, ValueError, RuntimeError, OverflowError):
            raise ValueError(f"{name} must be an integer (B,) tensor with B = {B}, got {lengths!r}") from None
    if lengths.dim() != 1 or lengths.shape[0] != B:
        raise ValueError(f"{name} must be (B,) with B = {B}, got {describe(lengths)}")
    if lengths.is_floating_point() or lengths.is_complex() or lengths.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got {describe(lengths)}")
    if lengths.device != like.device:
        raise ValueError(f"{name} is on {lengths.device} but the points are on {like.device}")
    return lengths.to(torch.int64)


def check_output_size(shape: Sequence[int], asked_by: str, what: str, hint: str = "") -> None:
    """Refuse, before anything is allocated, an output of more than :data:`MAX_OUTPUT_ENTRIES` entries.

    Args:
        shape: the output shape the arguments imply.
        asked_by: the arguments that ask for it, as the user wrote them (``"k=2147483648"``).
        what: the output, e.g. ``"dist2 and idx"``.
        hint: what to do instead, appended to the message.
    """
    n = math.prod([int(s) for s in shape])  # a list: torch.compile traces no generator expressions
    if n > MAX_OUTPUT_ENTRIES:
        raise ValueError(f"{asked_by}: {what} of shape {tuple([int(s) for s in shape])} would hold {n:.3g} entries, "
                         f"more than the 2^31 - 1 a lidarops output may hold" + (f"; {hint}" if hint else ""))


def coordinate_bound(dtype: torch.dtype) -> float:
    """Largest ``|coordinate|`` the neighbourhood ops accept: 2^510 for float64 points, 2^62 for
    float32 and bfloat16 (computed in float32); for float16 (also computed in float32) every finite
    value, 65504.

    Why: a squared distance is ``(dx*dx + dy*dy) + dz*dz`` in the computation dtype. With every
    coordinate within the bound B, a difference is at most 2B, so the sum is at most 12 B^2 = 0.75 * 2^128
    (float32) or 0.75 * 2^1024 (float64): below the largest finite value, so it cannot overflow to
    infinity (which would turn a real neighbour into "no neighbour").
    """
    if dtype == torch.float64:
        return 2.0**510
    # not 2^62 for float16: compared in float16 it would round to +inf, which would let +inf through
    return min(2.0**62, torch.finfo(dtype).max)


def _bound_text(dtype: torch.dtype) -> str:
    return {torch.float64: "2^510 (about 3.4e153)", torch.float16: "65504"}.get(dtype, "2^62 (about 4.6e18)")


def _coordinate_message(t: torch.Tensor, name: str) -> str:
    if not bool(torch.isfinite(t).all()):
        return f"{name} contains NaN or infinite coordinates ({describe(t)})"
    largest = float(t.abs().amax())
    computed = "" if t.dtype in (torch.float32, torch.float64) else ", computed in float32"
    return (f"{name} has a coordinate of magnitude {largest:.3g}; coordinates must lie within "
            f"+-{_bound_text(t.dtype)} for {t.dtype}{computed}, so that squared distances cannot overflow "
            f"({describe(t)})")


def coordinate_checks(named: Sequence[tuple[str, torch.Tensor]]) -> list:
    """``(flag, message)`` pairs for :func:`run_value_checks`: each point tensor holds no NaN, no
    infinity and no coordinate beyond :func:`coordinate_bound` (one max-abs reduction per tensor)."""
    return [(t.abs().amax().le(coordinate_bound(t.dtype)).logical_not(),
             lambda t=t, name=name: _coordinate_message(t, name)) for name, t in named if t.numel()]


class DeferredChecks:
    """Value flags computed on the device and not yet read: read :attr:`flags` together with an op's own
    results (one host sync for both), then :meth:`raise_first` with the values read."""

    def __init__(self, flags: "torch.Tensor | None", messages: list):
        self.flags = flags  # int32 (k,), nonzero = bad; None: nothing to check
        self.messages = messages

    def raise_first(self, values: Sequence[int]) -> None:
        for bad, message in zip(values, self.messages):
            if bad:
                raise ValueError(message() if callable(message) else message)

    def run(self) -> None:
        """Read the flags now and raise for the first failure."""
        if self.flags is not None:
            self.raise_first(self.flags.tolist())


def deferred_value_checks(finite: Sequence[tuple[torch.Tensor, object]] = (),
                          ranged: Sequence[tuple[torch.Tensor, int, int, object]] = (),
                          extra: Sequence[tuple[torch.Tensor, object]] = (),
                          coords: Sequence[tuple[torch.Tensor, str]] = ()) -> DeferredChecks:
    """:func:`check_values`' flags without reading them (the same arguments)."""
    coords = [(t, name) for t, name in coords if t.numel()]
    first = next((c[0] for group in (coords, finite, ranged, extra) for c in group), None)
    if first is None or first.device.type == "meta":  # meta tensors carry no values to check
        return DeferredChecks(None, [])
    parts = []
    if coords:  # NaN propagates through amax, and NaN <= bound is False: one flag for NaN, inf and too large
        ok = torch.stack([t.abs().amax().le(coordinate_bound(t.dtype)) for t, _ in coords])
        parts.append(ok.logical_not().to(torch.int32))
    if finite or ranged:
        parts.append(torch.ops.lidarops.value_flags([t for t, _ in finite], [c[0] for c in ranged],
                                                    [int(c[1]) for c in ranged], [int(c[2]) for c in ranged]))
    if extra:
        parts.append(torch.stack([c.reshape(()).to(torch.int32) for c, _ in extra]))
    flags = parts[0] if len(parts) == 1 else torch.cat(parts)
    messages = ([lambda t=t, name=name: _coordinate_message(t, name) for t, name in coords]
                + [m for _, m in finite] + [c[3] for c in ranged] + [m for _, m in extra])
    return DeferredChecks(flags, messages)


def check_values(finite: Sequence[tuple[torch.Tensor, object]] = (),
                 ranged: Sequence[tuple[torch.Tensor, int, int, object]] = (),
                 extra: Sequence[tuple[torch.Tensor, object]] = (),
                 coords: Sequence[tuple[torch.Tensor, str]] = ()) -> None:
    """Value checks with one host sync; raise ValueError for the first failure.

    Args:
        coords: ``(tensor, name)``: point coordinates: no NaN, no infinity and every ``|value|`` at most
            :func:`coordinate_bound` of the tensor's dtype, so squared distances cannot overflow
            (checked first; the message names the argument and the bound).
        finite: ``(tensor, message)``: the floating tensor must hold no NaN or infinity.
        ranged: ``(tensor, lo, hi, message)``: every value of the integer tensor lies in ``[lo, hi]``.
        extra: ``(bool 0-d tensor, message)``: any other check, True = bad.
    A message may be a callable, evaluated only on failure (it may read tensors to say more).
    ``finite`` and ``ranged`` run in the registered ``value_flags`` op; ``coords`` is one max-abs
    reduction per tensor; all flags come back to the host together (:func:`deferred_value_checks`
    leaves the read to the caller).
    """
    deferred_value_checks(finite, ranged, extra, coords).run()


def run_value_checks(checks: Sequence[tuple[torch.Tensor, object]]) -> None:
    """Evaluate boolean 0-d tensors (True = bad) with one host sync and raise ValueError for the first
    failure; a message may be a callable, evaluated only then (it may read tensors to say more)."""
    check_values(extra=checks)
