"""Shared pieces of the fuzz suite: the settings decorators, hypothesis strategies for point clouds,
sparse tensors, box sets and file bytes, and the one rule every fuzz test asserts:

    an op or reader either raises a clear exception of a documented type (ValueError and its
    subclasses, FileNotFoundError, the reader's documented errors) whose message names the argument
    or the file, or returns the result of its float64 / pure-Python reference.

Known bugs that other changes are fixing get their own tests, marked with :func:`known_bug` (xfail,
not strict); the main tests leave those inputs out with ``assume`` so that they stay green. When a
fix lands, drop the mark and the ``assume``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

# Hypothesis profiles of this folder, picked by HYPOTHESIS_PROFILE (default ``ci``):
#
# - ``ci``: what ``make test`` runs: a few examples per test, derandomized (the same examples on
#   every run, so CI is not flaky), no deadline.
# - ``long``: ``make fuzz``: 2,000 examples per test, random (failures kept in ``.hypothesis/`` and
#   replayed first next time); every test runs once per device.
# - ``dev``: 200 examples, random: a quick local check while editing a test.
#
# They are applied by the ``fuzz`` decorator below to the tests of this folder only, so the other
# hypothesis tests of the suite keep their own settings. (The folder is a package: its tests import
# ``from .fuzzing import ...``; the shared helpers of the whole suite are ``helpers``.)
_COMMON = dict(deadline=None, print_blob=True,
               # the device fixture only returns a string: safe to share between examples
               suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                      HealthCheck.data_too_large, HealthCheck.filter_too_much])
settings.register_profile("fuzz-ci", max_examples=12, derandomize=True, **_COMMON)
settings.register_profile("fuzz-dev", max_examples=200, **_COMMON)
settings.register_profile("fuzz-long", max_examples=2000, **_COMMON)

PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
if PROFILE not in ("ci", "dev", "long"):
    raise ValueError(f"HYPOTHESIS_PROFILE must be ci, dev or long for tests/fuzz, got {PROFILE!r}")
_BASE = settings.get_profile("fuzz-" + PROFILE)
# FUZZ_SHARDS=n: each process runs 1/n of the profile's examples (tools/fuzz_cuda.sh runs n processes of
# one test with different --hypothesis-seed values: the long profile's 2,000 examples in parallel)
_SHARDS = int(os.environ.get("FUZZ_SHARDS", "1"))
if _SHARDS < 1:
    raise ValueError(f"FUZZ_SHARDS must be an int >= 1, got {_SHARDS}")
if _SHARDS > 1:
    _BASE = settings(_BASE, max_examples=-(-_BASE.max_examples // _SHARDS))

#: the decorator of every fuzz test: the profile's settings
fuzz = settings(_BASE)


def known_bug(reason: str):
    """A fuzz test of inputs that expose a bug being fixed elsewhere: xfail (not strict), and no
    shrinking (the failure is known; a shrink would only cost CI time). Replace by ``@fuzz`` once
    fixed."""
    def wrap(f):
        f = settings(_BASE, phases=[Phase.explicit, Phase.reuse, Phase.generate],
                     max_examples=min(_BASE.max_examples, 200))(f)
        return pytest.mark.xfail(strict=False, reason=reason)(f)
    return wrap


# ---------------------------------------------------------------------------------------------
# outcomes
# ---------------------------------------------------------------------------------------------
def outcome(fn: Callable, *args, **kwargs):
    """``(result, None)`` or ``(None, exception)``."""
    try:
        return fn(*args, **kwargs), None
    except Exception as e:  # noqa: BLE001  (the caller judges the exception)
        return None, e


def assert_clear_error(err: Optional[BaseException], types, names: Sequence[str], what: str) -> None:
    """``err`` is one of ``types`` and its message names one of ``names`` (argument or file names)."""
    assert err is not None, f"{what}: expected {_names(types)} naming one of {list(names)}, got a result"
    if not isinstance(err, types):
        raise AssertionError(f"{what}: expected {_names(types)} naming one of {list(names)}, got "
                             f"{type(err).__name__}: {err}") from err
    msg = str(err)
    assert any(n in msg for n in names), f"{what}: the {type(err).__name__} names none of {list(names)}: {msg!r}"


def assert_no_error(err: Optional[BaseException], what: str) -> None:
    if err is not None:
        raise AssertionError(f"{what}: expected a result, got {type(err).__name__}: {err}") from err


def _names(types) -> str:
    types = types if isinstance(types, tuple) else (types,)
    return " or ".join(t.__name__ for t in types)


def assert_same(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    """Equal shapes and values (NaN equal to NaN), with the first difference in the message."""
    got, want = got.detach().cpu(), want.detach().cpu()
    assert tuple(got.shape) == tuple(want.shape), f"{what}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    if got.numel() == 0:
        return
    g, w = got.double() if got.is_floating_point() else got, want.to(got.dtype).double() \
        if got.is_floating_point() else want.to(got.dtype)
    same = (g == w) | (torch.isnan(g) & torch.isnan(w)) if got.is_floating_point() else g == w
    if not bool(same.all()):
        at = tuple(torch.nonzero(~same)[0].tolist())
        raise AssertionError(f"{what}: {int((~same).sum())} of {same.numel()} entries differ; first at {at}: "
                             f"got {g[at].item()!r}, reference {w[at].item()!r}")


def assert_close(got: torch.Tensor, want: torch.Tensor, rtol: float, atol: float, what: str) -> None:
    got, want = got.detach().cpu().double(), want.detach().cpu().double()
    assert tuple(got.shape) == tuple(want.shape), f"{what}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    if got.numel() == 0:
        return
    diff = (got - want).abs()
    bad = ~(diff <= atol + rtol * want.abs()) & ~(torch.isnan(got) & torch.isnan(want))
    if bool(bad.any()):
        at = tuple(torch.nonzero(bad)[0].tolist())
        raise AssertionError(f"{what}: {int(bad.sum())} entries beyond rtol {rtol:g} / atol {atol:g}; max diff "
                             f"{diff[~torch.isnan(diff)].max().item():.3e}; first at {at}: got {got[at].item()!r}, "
                             f"reference {want[at].item()!r}")


# ---------------------------------------------------------------------------------------------
# numbers
# ---------------------------------------------------------------------------------------------
FLOAT_DTYPES = (torch.float32, torch.float64)

#: magnitude regimes of coordinates
REGIMES = ("normal", "lattice", "tiny", "huge", "nonfinite")

_F32_MAX = float(np.finfo(np.float32).max)
_TINY = [0.0, -0.0, 1e-30, -1e-30, 1e-38, 1.4e-45, -1.4e-45, 2.5e-40]
_HUGE32 = [1e15, -1e15, 4e18, 1e19, -3e19, 1e30, _F32_MAX, -_F32_MAX]
_HUGE64 = _HUGE32 + [1e160, -1e200, 1.7e308]


def scalars(regime: str, dtype: torch.dtype = torch.float32) -> st.SearchStrategy:
    """Python floats exactly representable in ``dtype`` for one magnitude regime."""
    width = 32 if dtype == torch.float32 else 64
    if regime == "normal":
        return st.floats(-60, 60, width=width)
    if regime == "lattice":  # exact ties and duplicates
        return st.integers(-3, 3).map(float)
    if regime == "tiny":
        tiny = float(np.float32(1e-20))
        return st.sampled_from(_TINY) | st.floats(-tiny, tiny, width=width)
    if regime == "huge":
        big = _HUGE32 if dtype == torch.float32 else _HUGE64
        top = _F32_MAX if dtype == torch.float32 else 1.7e308
        return st.sampled_from(big) | st.floats(-top, top, width=width) | st.floats(-60, 60, width=width)
    if regime == "nonfinite":
        return st.floats(-60, 60, width=width) | st.sampled_from([math.nan, math.inf, -math.inf])
    raise ValueError(regime)


# ---------------------------------------------------------------------------------------------
# point clouds
# ---------------------------------------------------------------------------------------------
@dataclass
class Cloud:
    """A batch of clouds: points (B, N, 3) on the CPU, ragged lengths (B,) or None, and the regime."""

    points: torch.Tensor
    lengths: Optional[torch.Tensor]
    regime: str

    @property
    def valid_lengths(self) -> bool:
        n = self.points.shape[1]
        return self.lengths is None or bool(((self.lengths >= 0) & (self.lengths <= n)).all())

    def rows(self) -> list:
        """Valid rows per cloud (the lengths, or N), clipped to [0, N]."""
        B, N = self.points.shape[:2]
        if self.lengths is None:
            return [N] * B
        return [min(max(int(v), 0), N) for v in self.lengths]

    def finite(self) -> bool:
        return bool(torch.isfinite(self.points).all())


@st.composite
def clouds(draw, batch: Optional[int] = None, dtype: Optional[torch.dtype] = None, regime: Optional[str] = None,
           max_n: int = 10, min_n: int = 0, lengths: bool = True) -> Cloud:
    """(B, N, 3) clouds: ragged lengths (sometimes out of range), duplicated points (rows drawn with
    repetition from a pool), empty clouds (B = 0 or N = 0 or a length 0), and one magnitude regime."""
    B = draw(st.integers(0, 3)) if batch is None else batch
    N = draw(st.integers(min_n, max_n))
    dtype = dtype or draw(st.sampled_from(FLOAT_DTYPES))
    regime = regime or draw(st.sampled_from(REGIMES))
    elem = scalars(regime, dtype)
    pool_n = draw(st.integers(1, max(1, N)))
    pool = draw(st.lists(st.tuples(elem, elem, elem), min_size=pool_n, max_size=pool_n))
    picks = draw(st.lists(st.integers(0, pool_n - 1), min_size=B * N, max_size=B * N))
    pts = torch.tensor([pool[i] for i in picks], dtype=torch.float64).reshape(B, N, 3).to(dtype)
    lens = None
    if lengths and draw(st.booleans()):
        bad = draw(st.integers(0, 9)) == 0  # out of range now and then
        values = st.integers(-2, N + 2) if bad else st.integers(0, N)
        lens = torch.tensor(draw(st.lists(values, min_size=B, max_size=B)), dtype=torch.int64).reshape(B)
    return Cloud(pts, lens, regime)


# ---------------------------------------------------------------------------------------------
# sparse tensors
# ---------------------------------------------------------------------------------------------
@dataclass
class Sites:
    """Sites (N, 1 + D) int32 of a sparse tensor, features (N, C) float64, its grid and batch size."""

    indices: torch.Tensor
    features: torch.Tensor
    spatial_shape: list
    batch_size: int

    def in_range(self) -> bool:
        if self.indices.shape[0] == 0:
            return True
        bound = torch.tensor([self.batch_size] + self.spatial_shape)
        return bool(((self.indices >= 0) & (self.indices < bound)).all())

    def unique(self) -> bool:
        return torch.unique(self.indices, dim=0).shape[0] == self.indices.shape[0]


@st.composite
def sparse_sites(draw, D: Optional[int] = None, channels: Optional[int] = None, max_sites: int = 14) -> Sites:
    """Random sites on a small grid: sometimes duplicated, sometimes outside the grid or the batch."""
    D = D or draw(st.sampled_from([2, 2, 3]))
    shape = [draw(st.integers(1, 6 if D == 2 else 4)) for _ in range(D)]
    B = draw(st.integers(1, 2))
    C = channels or draw(st.integers(1, 3))
    n = draw(st.integers(0, max_sites))
    strict = draw(st.integers(0, 3)) > 0  # mostly valid sites, so that the convolutions get compared
    rows = []
    for _ in range(n):
        if strict:
            rows.append([draw(st.integers(0, B - 1))] + [draw(st.integers(0, s - 1)) for s in shape])
        else:
            rows.append([draw(st.integers(-1, B))] + [draw(st.integers(-1, s)) for s in shape])
    if strict:  # unique by construction (the duplicates come from the other branch)
        rows = [list(r) for r in dict.fromkeys(tuple(r) for r in rows)]
    elif rows and draw(st.booleans()):
        rows.append(list(draw(st.sampled_from(rows))))  # an exact duplicate
    idx = torch.tensor(rows, dtype=torch.int32).reshape(len(rows), 1 + D)
    feats = torch.tensor(draw(st.lists(st.floats(-4, 4, width=32), min_size=len(rows) * C,
                                       max_size=len(rows) * C)), dtype=torch.float64).reshape(len(rows), C)
    return Sites(idx, feats, shape, B)


# ---------------------------------------------------------------------------------------------
# box sets
# ---------------------------------------------------------------------------------------------
@dataclass
class Boxes:
    boxes: torch.Tensor  # (M, 7) x, y, z, dx, dy, dz, heading
    regime: str

    def finite(self) -> bool:
        return bool(torch.isfinite(self.boxes).all())

    def nonnegative(self) -> bool:
        return bool((self.boxes[:, 3:6] >= 0).all()) if self.boxes.numel() else True

    def in_range(self) -> bool:
        """Within docs/boxes.md's input policy: centres within 1e6 m of the origin, sizes 0 or in
        [1e-6, 1e6] m, headings within 1e6 rad (NaN counts as out of range)."""
        t = self.boxes.double()
        size = t[:, 3:6]
        ok = (t[:, :3].abs() <= 1e6).all(1) & (t[:, 6].abs() <= 1e6) \
            & ((size == 0) | ((size >= 1e-6) & (size <= 1e6))).all(1)
        return bool(ok.all())


_HEADINGS = st.sampled_from([0.0, math.pi / 2, -math.pi / 2, math.pi, 2 * math.pi, 0.25, -3.0]) | st.floats(-7, 7)


@st.composite
def box_sets(draw, dtype: Optional[torch.dtype] = None, max_boxes: int = 5, regime: Optional[str] = None,
             min_boxes: int = 0) -> Boxes:
    """Boxes near each other (so that they overlap), with zero sizes, coordinates near the supported bound
    ("huge"), NaN/inf, negative sizes or one value beyond the supported range ("outside") depending on the
    regime."""
    dtype = dtype or draw(st.sampled_from(FLOAT_DTYPES))
    regime = regime or draw(st.sampled_from(["normal", "normal", "zero", "huge", "nonfinite", "negative",
                                             "outside"]))
    m = draw(st.integers(min_boxes, max_boxes))
    width = 32 if dtype == torch.float32 else 64
    centre = st.floats(-3, 3, width=width) | st.sampled_from([0.0, 0.5, 1.0])
    size = st.floats(0.125, 4, width=width) | st.sampled_from([1.0, 2.0])
    rows = []
    offset = draw(st.sampled_from([1e4, -9.99e5, 9.9e5])) if regime == "huge" else 0.0
    for _ in range(m):
        x, y, z = (draw(centre) for _ in range(3))
        dx, dy, dz = (draw(size) for _ in range(3))
        h = draw(_HEADINGS)
        if regime == "zero" and draw(st.booleans()):
            which = draw(st.integers(0, 2))
            dx, dy, dz = [0.0 if i == which else v for i, v in enumerate((dx, dy, dz))]
        rows.append([x + offset, y + offset, z, dx, dy, dz, h])
    t = torch.tensor(rows, dtype=torch.float64).reshape(m, 7)
    if m and regime == "nonfinite" and draw(st.booleans()):
        t[draw(st.integers(0, m - 1)), draw(st.integers(0, 6))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    if m and regime == "negative":
        t[draw(st.integers(0, m - 1)), draw(st.integers(3, 5))] = -draw(st.floats(0.01, 2))
    if m and regime == "outside":
        col, value = draw(st.sampled_from([(0, 3e7), (1, -1.5e6), (2, 2e6), (3, 2e6), (4, 1e-9), (5, 5e-7),
                                           (6, 1e7), (6, -1e20), (6, 1.5e6)]))
        t[draw(st.integers(0, m - 1)), col] = value
    return Boxes(t.to(dtype), regime)


# ---------------------------------------------------------------------------------------------
# file bytes
# ---------------------------------------------------------------------------------------------
def mangled(data: bytes) -> st.SearchStrategy:
    """``data`` truncated at any byte, with a few bytes flipped, with random bytes appended, or random
    bytes instead."""
    n = len(data)
    truncated = st.integers(0, n).map(lambda k: data[:k])

    @st.composite
    def flipped(draw):
        if not data:
            return data
        b = bytearray(data)
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, n - 1))
            b[i] = draw(st.integers(0, 255))
        return bytes(b)

    appended = st.binary(min_size=1, max_size=24).map(lambda extra: data + extra)
    return st.one_of(st.just(data), truncated, flipped(), appended, st.binary(max_size=96))
