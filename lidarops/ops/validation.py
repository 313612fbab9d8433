"""Argument validation shared by the op wrappers.

Shape, dtype and device checks are free. Checks that read tensor values (NaN coordinates, lengths
and indices in range) cost one small kernel per tensor (the ``value_flags`` op) and one
device-to-host copy per call on CUDA; they are on by default
and skipped while ``torch.compile`` traces. Turn them off in a hot loop you have already validated::

    with lidarops.validation(False):
        ...
"""
from __future__ import annotations

import contextlib
import operator
from typing import Iterator, Sequence

import torch

_enabled = True


@contextlib.contextmanager
def validation(enabled: bool = True) -> Iterator[None]:
    """Context manager that enables or disables the value checks of the lidarops wrappers."""
    global _enabled
    old, _enabled = _enabled, bool(enabled)
    try:
        yield
    finally:
        _enabled = old


def value_checks_enabled() -> bool:
    if not _enabled:
        return False
    return not torch.compiler.is_compiling()


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
    if isinstance(v, torch.Tensor):
        if v.numel() != 1 or v.is_floating_point() or v.is_complex() or v.dtype == torch.bool:
            raise ValueError(f"{name} must be a positive int, got {describe(v)}")
        v = int(v)
    elif isinstance(v, bool):
        raise ValueError(f"{name} must be a positive int, got {v!r}")
    else:
        try:  # int, NumPy integers, anything with __index__ (not floats)
            v = operator.index(v)
        except TypeError:
            raise ValueError(f"{name} must be a positive int, got {v!r}") from None
    if v <= 0:
        raise ValueError(f"{name} must be a positive int, got {v}")
    return v


def lengths_or_full(lengths, like: torch.Tensor, name: str) -> torch.Tensor:
    """``lengths`` as an int64 (B,) tensor on ``like``'s device; None means every row is full."""
    B, N = like.shape[0], like.shape[1]
    if lengths is None:
        return torch.full((B,), N, dtype=torch.int64, device=like.device)
    if not isinstance(lengths, torch.Tensor):
        lengths = torch.as_tensor(lengths, device=like.device)
    if lengths.dim() != 1 or lengths.shape[0] != B:
        raise ValueError(f"{name} must be (B,) with B = {B}, got {describe(lengths)}")
    if lengths.is_floating_point() or lengths.is_complex() or lengths.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got {describe(lengths)}")
    if lengths.device != like.device:
        raise ValueError(f"{name} is on {lengths.device} but the points are on {like.device}")
    return lengths.to(torch.int64)


def check_values(finite: Sequence[tuple[torch.Tensor, object]] = (),
                 ranged: Sequence[tuple[torch.Tensor, int, int, object]] = (),
                 extra: Sequence[tuple[torch.Tensor, object]] = ()) -> None:
    """Value checks with one registered op call and one host sync; raise ValueError for the first failure.

    Args:
        finite: ``(tensor, message)``: the floating tensor must hold no NaN or infinity.
        ranged: ``(tensor, lo, hi, message)``: every value of the integer tensor lies in ``[lo, hi]``.
        extra: ``(bool 0-d tensor, message)``: any other check, True = bad.
    A message may be a callable, evaluated only on failure (it may read tensors to say more).
    """
    first = next((c[0] for group in (finite, ranged, extra) for c in group), None)
    if first is None or first.device.type == "meta":  # meta tensors carry no values to check
        return
    parts = []
    if finite or ranged:
        parts.append(torch.ops.lidarops.value_flags([t for t, _ in finite], [c[0] for c in ranged],
                                                    [int(c[1]) for c in ranged], [int(c[2]) for c in ranged]))
    if extra:
        parts.append(torch.stack([c.reshape(()).to(torch.int32) for c, _ in extra]))
    flags = parts[0] if len(parts) == 1 else torch.cat(parts)
    messages = [m for _, m in finite] + [c[3] for c in ranged] + [m for _, m in extra]
    for bad, message in zip(flags.tolist(), messages):
        if bad:
            raise ValueError(message() if callable(message) else message)


def run_value_checks(checks: Sequence[tuple[torch.Tensor, object]]) -> None:
    """Evaluate boolean 0-d tensors (True = bad) with one host sync and raise ValueError for the first
    failure; a message may be a callable, evaluated only then (it may read tensors to say more)."""
    check_values(extra=checks)
