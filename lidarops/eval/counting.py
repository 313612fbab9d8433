"""Query metrics of counting: how well per-frame, per-class object counts of a source (a detector used
as a counter, a counting network) answer RETRIEVAL, COUNT and AGGREGATION queries, scored against the
true counts (the labels). CounterNet's query types (Zhang et al., MM'25, "Querying autonomous-vehicle
point clouds with CounterNet", arXiv:2507.19209); the precise definitions below, their zero cases and
their ties, are lidarops' (docs/query.md, "Evaluation", says which parts come from where).

Pure NumPy. Inputs are counts: ``pred`` and ``true`` of the same shape ``(frames,)`` (one class) or
``(frames, classes)``, frames in the order of the drive (ascending frame id); integer dtypes, or floats
holding whole numbers; each count in ``[0, 2**31 - 1]`` (the index's int32 columns). A per-class metric
returns an array ``(classes,)`` for 2-D inputs and a float for 1-D inputs.

Definitions (``p``, ``t``: a frame's predicted and true count of a class; ``F`` frames):

- **allowed error** of a class at tolerance ``tau``: ``floor(tau * max_f t_f)``, the tolerance times the
  class's largest true count over the evaluated frames, computed exactly (``tau`` is taken as the decimal
  it prints as, ``0.1`` is 1/10: no float rounding moves a tie). A class absent from every frame has
  allowed error 0.
- **within tolerance**: ``|p - t| <= allowed error``; an error equal to the allowed error is within.
- **RETRIEVAL-SINGLE accuracy** of a class: the share of frames whose count of the class is within
  tolerance (a frame a single-class retrieval query would judge on a count near enough the truth).
- **RETRIEVAL-MULTIPLE accuracy**: the share of frames whose counts of every given class are all within
  tolerance at once.
- **counting accuracy** of a class: the share of frames whose count is exactly right (RETRIEVAL-SINGLE at
  tolerance 0); beside it, the **mean absolute error** ``mean_f |p - t|``.
- **COUNT queries**: ``how many frames of a group have count(class) op v``. Groups are runs of
  consecutive frames (:func:`random_groups`); per class, each random query picks a group, an operator of
  ``<, <=, =, >=, >`` and a value ``v``, the true count of a random frame of that group
  (:func:`random_count_queries`). With ``a`` the true answer and ``b`` the predicted one, a query scores
  ``min(a, b) / max(a, b)``, and 1 when both are 0 (so 0 when exactly one is 0); the **COUNT accuracy**
  of a class is the mean score over its queries, beside the share answered exactly and the mean
  ``|b - a|`` in frames.
- **AGGREGATION** (the SUM of a class over a group of frames; an AVG over the same frames differs by the
  factor 1/frames): the **absolute difference** ``|Σp - Σt|`` and the **Q-error**
  ``max(Σp / Σt, Σt / Σp)`` (:func:`q_error`: a sum of 0 is taken as 1, so 0 against 0 scores 1, 0
  against 5 scores 5, and 0 against 1 scores 1, which the absolute difference beside it shows).

Random groups and queries depend only on the number of frames, the true counts and the seed, never on the
predictions: two sources scored with one seed face the same queries.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Sequence, Union

import numpy as np

from lidarops._checks import integer, positive_int

__all__ = ["OPERATORS", "MAX_COUNT", "CountQueries", "q_error", "allowed_error", "within_tolerance",
           "retrieval_single_accuracy", "retrieval_multiple_accuracy", "counting_accuracy",
           "mean_absolute_error", "random_groups", "random_count_queries", "count_query_answers",
           "count_query_accuracy", "aggregation_errors"]

#: the comparison operators of COUNT queries (the indices of :attr:`CountQueries.op`)
OPERATORS = ("<", "<=", "=", ">=", ">")
#: the largest count accepted (the index's int32 columns): sums over 2**32 frames stay within int64
MAX_COUNT = 2 ** 31 - 1
#: the largest sum :func:`q_error` takes
_MAX_SUM = 2 ** 62
#: COUNT queries are scored in chunks of at most this many (query, frame) pairs
_CHUNK = 1 << 22

Seed = Union[int, np.random.Generator]


# ---------------------------------------------------------------------------------------------------------
# argument checks
# ---------------------------------------------------------------------------------------------------------
def _counts(value: Any, name: str, ndims: Sequence[int] = (1, 2), maximum: int = MAX_COUNT) -> np.ndarray:
    """``value`` as int64 counts in ``[0, maximum]``, or a ValueError naming ``name``, its shape and dtype."""
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as e:  # ragged nested lists
        raise ValueError(f"{name} must be an array of counts, got {type(value).__name__} ({e})") from None
    what = f"{name} (shape {tuple(arr.shape)}, dtype {arr.dtype})"
    if arr.ndim not in ndims:
        shapes = " or ".join({0: "()", 1: "(frames,)", 2: "(frames, classes)"}[d] for d in ndims)
        raise ValueError(f"{name} must have shape {shapes}, got shape {tuple(arr.shape)}")
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{what} must hold integer counts (an integer dtype, or floats of whole numbers)")
    if arr.size == 0:
        return arr.astype(np.int64)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.any():
            raise ValueError(f"{what} must be finite, got {arr[bad][0]!r}")
        bad = arr != np.floor(arr)
        if bad.any():
            raise ValueError(f"{what} must hold whole numbers (counts), got {arr[bad][0]!r}")
    lo, hi = arr.min(), arr.max()
    if lo < 0:
        raise ValueError(f"{what} must hold counts >= 0, got {lo.item()!r}")
    if hi > maximum:
        limit = "2**31 - 1" if maximum == MAX_COUNT else "2**62"
        raise ValueError(f"{what} must hold counts <= {maximum} ({limit}), got {hi.item()!r}")
    return arr.astype(np.int64)


def _pair(pred: Any, true: Any, frames: bool = True) -> tuple[np.ndarray, np.ndarray, bool]:
    """``pred`` and ``true`` as int64 ``(frames, classes)`` arrays of one shape, and whether they were 1-D.
    ``frames``: refuse inputs without frames or classes (an accuracy over nothing is undefined)."""
    p, t = _counts(pred, "pred"), _counts(true, "true")
    if p.shape != t.shape:
        raise ValueError(f"pred and true must have the same shape, got pred {tuple(p.shape)} and true "
                         f"{tuple(t.shape)}")
    one_d = p.ndim == 1
    if one_d:
        p, t = p[:, None], t[:, None]
    if frames and p.shape[0] == 0:
        raise ValueError(f"pred and true hold no frames (shape {tuple(p.shape[:1] if one_d else p.shape)}): "
                         "a share of frames over none is undefined")
    if p.shape[1] == 0:
        raise ValueError(f"pred and true hold no class (shape {tuple(p.shape)}): give at least one column")
    return p, t, one_d


def _per_class(values: np.ndarray, one_d: bool):
    return float(values[0]) if one_d else values


def _tolerance(value: Any, name: str = "tolerance") -> Fraction:
    """A tolerance in [0, 1] as an exact fraction: the decimal a float prints as (0.1 -> 1/10)."""
    if isinstance(value, Fraction):
        frac = value
    elif isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) \
            or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number in [0, 1], got {value!r}")
    elif isinstance(value, numbers.Integral):
        frac = Fraction(int(value))
    elif isinstance(value, (float, np.floating)):
        frac = Fraction(str(value))  # the shortest decimal that prints as the float (NumPy's too)
    else:
        frac = Fraction(str(float(value)))
    if not 0 <= frac <= 1:
        raise ValueError(f"{name} must be a finite number in [0, 1], got {value!r}")
    return frac


def _rng(seed: Seed) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(integer(seed, "seed", lo=0))


def _group_frames(group_frames: Any) -> tuple[int, int]:
    if not isinstance(group_frames, (tuple, list)) or len(group_frames) != 2:
        raise ValueError(f"group_frames must be (fewest, most) frames of a group, got {group_frames!r}")
    lo = positive_int(group_frames[0], "group_frames[0] (the fewest frames of a group)")
    hi = positive_int(group_frames[1], "group_frames[1] (the most frames of a group)")
    if lo > hi:
        raise ValueError(f"group_frames must have fewest <= most, got {tuple(group_frames)}")
    return lo, hi


# ---------------------------------------------------------------------------------------------------------
# per-frame metrics
# ---------------------------------------------------------------------------------------------------------
def q_error(pred: Any, true: Any) -> "np.ndarray | float":
    """Q-error of counts (sums of objects), element by element: ``max(p / t, t / p)`` with a count of 0
    taken as 1.

    So 0 against 0 is 1 (a perfect answer), 0 against ``n >= 1`` is ``n``, and 0 against 1 is 1 (read the
    absolute difference beside it). Always finite and ``>= 1``; 1 exactly when both counts are equal or
    both are in {0, 1}.

    Args:
        pred, true: counts or sums of counts of one shape, ``()``, ``(n,)`` or ``(n, classes)`` (integers,
            or floats of whole numbers, in ``[0, 2**62]``); empty arrays give an empty result.

    Returns:
        float64 array of the inputs' shape (a float for 0-d inputs).
    """
    p, t = _counts(pred, "pred", (0, 1, 2), _MAX_SUM), _counts(true, "true", (0, 1, 2), _MAX_SUM)
    if p.shape != t.shape:
        raise ValueError(f"pred and true must have the same shape, got pred {tuple(p.shape)} and true "
                         f"{tuple(t.shape)}")
    out = _q_error(p, t)
    return float(out) if out.ndim == 0 else out


def _q_error(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    p, t = np.maximum(p, 1).astype(np.float64), np.maximum(t, 1).astype(np.float64)
    return np.maximum(p, t) / np.minimum(p, t)


def allowed_error(true: Any, tolerance: Any) -> "np.ndarray | int":
    """The largest absolute count error within ``tolerance``, per class: ``floor(tolerance * max_f true)``.

    Computed exactly: ``tolerance`` is the decimal it prints as (0.1 is 1/10, 0.29 is 29/100, so 0.29 of a
    largest count of 100 allows 29, where float arithmetic gives 28.999999999999996). A class absent from
    every frame allows 0.

    Args:
        true: true counts ``(frames,)`` or ``(frames, classes)``, at least one frame.
        tolerance: a number in [0, 1] (or a ``fractions.Fraction``).

    Returns:
        int64 array ``(classes,)`` (an int for 1-D ``true``).
    """
    t = _counts(true, "true")
    one_d = t.ndim == 1
    t = t[:, None] if one_d else t
    if t.shape[0] == 0:
        raise ValueError(f"true holds no frames (shape {tuple(t.shape[:1] if one_d else t.shape)}): the largest "
                         "count of a class is undefined")
    frac = _tolerance(tolerance)
    # Python ints: exact, whatever the tolerance's digits
    allowed = np.array([(frac.numerator * int(m)) // frac.denominator for m in t.max(0)], np.int64)
    return int(allowed[0]) if one_d else allowed


def within_tolerance(pred: Any, true: Any, tolerance: Any) -> np.ndarray:
    """Whether each count is within tolerance: ``|pred - true| <= allowed_error(true, tolerance)`` (an error
    equal to the allowed error is within), the allowed error taken per class over all the given frames.

    Returns:
        bool array of the inputs' shape ``(frames,)`` or ``(frames, classes)``.
    """
    p, t, one_d = _pair(pred, true)
    allowed = np.atleast_1d(allowed_error(t, tolerance))
    ok = np.abs(p - t) <= allowed[None, :]
    return ok[:, 0] if one_d else ok


def retrieval_single_accuracy(pred: Any, true: Any, tolerance: Any) -> "np.ndarray | float":
    """RETRIEVAL-SINGLE accuracy per class: the share of frames whose count of the class is within
    tolerance (:func:`within_tolerance`). In [0, 1].

    Args:
        pred, true: counts ``(frames,)`` or ``(frames, classes)``, at least one frame (else ValueError).
        tolerance: in [0, 1]; the allowed error is ``floor(tolerance * largest true count of the class)``.

    Returns:
        float64 array ``(classes,)`` (a float for 1-D inputs).
    """
    p, t, one_d = _pair(pred, true)
    return _per_class(within_tolerance(p, t, tolerance).mean(0), one_d)


def retrieval_multiple_accuracy(pred: Any, true: Any, tolerance: Any) -> float:
    """RETRIEVAL-MULTIPLE accuracy: the share of frames whose counts of every given class are within
    tolerance at once (for one class, the RETRIEVAL-SINGLE accuracy). In [0, 1], and at most the smallest
    RETRIEVAL-SINGLE accuracy of the classes.

    Args:
        pred, true: counts ``(frames, classes)`` (or ``(frames,)``), at least one frame.
        tolerance: in [0, 1], applied per class as in :func:`allowed_error`.
    """
    p, t, _ = _pair(pred, true)
    return float(within_tolerance(p, t, tolerance).all(1).mean())


def counting_accuracy(pred: Any, true: Any) -> "np.ndarray | float":
    """Per-class counting accuracy: the share of frames whose count of the class is exactly right
    (RETRIEVAL-SINGLE accuracy at tolerance 0). In [0, 1]; a class absent from every frame and never
    predicted scores 1.

    Returns:
        float64 array ``(classes,)`` (a float for 1-D inputs); a ValueError for inputs without frames.
    """
    p, t, one_d = _pair(pred, true)
    return _per_class((p == t).mean(0), one_d)


def mean_absolute_error(pred: Any, true: Any) -> "np.ndarray | float":
    """Per-class mean absolute count error ``mean_f |pred - true|`` (objects per frame), ``>= 0``.

    Returns:
        float64 array ``(classes,)`` (a float for 1-D inputs); a ValueError for inputs without frames.
    """
    p, t, one_d = _pair(pred, true)
    return _per_class(np.abs(p - t).mean(0), one_d)


# ---------------------------------------------------------------------------------------------------------
# COUNT queries
# ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CountQueries:
    """COUNT queries over groups of consecutive frames, ``Q`` per class: query ``q`` of class ``c`` asks how
    many frames ``f`` of group ``group[c, q]`` (frames ``starts[g] <= f < starts[g] + lengths[g]``, by
    position in the frame order) have ``count[f, c] OPERATORS[op[c, q]] value[c, q]``.

    Attributes:
        starts, lengths: int64 ``(G,)``: each group's first frame (position) and number of frames (>= 1).
        group, op, value: int64 ``(classes, Q)``: each query's group index, operator index into
            :data:`OPERATORS` and value (a count, >= 0).
    """

    starts: np.ndarray
    lengths: np.ndarray
    group: np.ndarray
    op: np.ndarray
    value: np.ndarray

    def __post_init__(self):
        for name in ("starts", "lengths", "group", "op", "value"):
            arr = np.asarray(getattr(self, name))
            if arr.dtype.kind not in "iu":
                raise ValueError(f"queries.{name} must hold integers, got dtype {arr.dtype}")
            object.__setattr__(self, name, arr.astype(np.int64))
        if self.starts.ndim != 1 or self.starts.shape != self.lengths.shape or self.starts.size == 0:
            raise ValueError(f"queries.starts and queries.lengths must be (G,) with G >= 1, got "
                             f"{tuple(self.starts.shape)} and {tuple(self.lengths.shape)}")
        if self.group.ndim != 2 or self.op.shape != self.group.shape or self.value.shape != self.group.shape:
            raise ValueError(f"queries.group, queries.op and queries.value must be (classes, Q) of one shape, got "
                             f"{tuple(self.group.shape)}, {tuple(self.op.shape)} and {tuple(self.value.shape)}")
        if (self.starts < 0).any() or (self.lengths < 1).any():
            raise ValueError("queries.starts must be >= 0 and queries.lengths >= 1")
        if self.group.size and ((self.group < 0).any() or (self.group >= len(self.starts)).any()):
            raise ValueError(f"queries.group must index the {len(self.starts)} groups")
        if self.op.size and ((self.op < 0).any() or (self.op >= len(OPERATORS)).any()):
            raise ValueError(f"queries.op must index OPERATORS {OPERATORS}")
        if self.value.size and (self.value < 0).any():
            raise ValueError("queries.value must be >= 0")

    @property
    def classes(self) -> int:
        return self.group.shape[0]

    def __len__(self) -> int:
        """Queries per class."""
        return self.group.shape[1]

    def describe(self, c: int, q: int) -> str:
        """Query ``q`` of class column ``c`` in words, e.g. ``'frames 100-349: count >= 3'``."""
        g = int(self.group[c, q])
        first = int(self.starts[g])
        return f"frames {first}-{first + int(self.lengths[g]) - 1}: count {OPERATORS[int(self.op[c, q])]} " \
               f"{int(self.value[c, q])}"


def random_groups(n_frames: int, groups: int = 500, group_frames: tuple[int, int] = (100, 500),
                  seed: Seed = 0) -> tuple[np.ndarray, np.ndarray]:
    """``groups`` random runs of consecutive frames: each length uniform among the integers
    ``[fewest, most]`` of ``group_frames``, clipped to ``n_frames`` (an index of fewer frames than
    ``fewest`` makes every group the whole drive), then the first frame uniform among the positions where
    the run fits.

    Args:
        n_frames: frames to draw from (>= 1).
        groups: how many groups (>= 1).
        group_frames: ``(fewest, most)`` frames of a group, ``1 <= fewest <= most``.
        seed: an int >= 0, or a ``numpy.random.Generator`` (which is advanced).

    Returns:
        ``(starts, lengths)``: int64 ``(groups,)``, with ``starts + lengths <= n_frames``.
    """
    n = positive_int(n_frames, "n_frames")
    g = positive_int(groups, "groups")
    lo, hi = _group_frames(group_frames)
    rng = _rng(seed)
    lengths = rng.integers(min(lo, n), min(hi, n) + 1, size=g, dtype=np.int64)
    starts = rng.integers(0, n - lengths + 1, dtype=np.int64)
    return starts, lengths


def random_count_queries(true: Any, queries: int = 1000, groups: int = 500,
                         group_frames: tuple[int, int] = (100, 500), seed: Seed = 0) -> CountQueries:
    """Random COUNT queries over ``true`` counts: :func:`random_groups`, then per class (in column order)
    ``queries`` queries, each drawing a group (uniform among the groups), an operator (uniform among
    :data:`OPERATORS`) and a frame of that group (uniform), whose true count is the query's value.

    The draws depend only on ``true``'s shape and values and on ``seed``: one seed, one set of queries, for
    every source scored against the same truth.

    Args:
        true: true counts ``(frames,)`` or ``(frames, classes)``, at least one frame.
        queries: queries per class (>= 1).
        groups, group_frames: as :func:`random_groups`.
        seed: an int >= 0, or a ``numpy.random.Generator`` (which is advanced).
    """
    t = _counts(true, "true")
    t = t[:, None] if t.ndim == 1 else t
    if t.shape[0] == 0 or t.shape[1] == 0:
        raise ValueError(f"true must hold at least one frame and one class, got shape {tuple(t.shape)}")
    q = positive_int(queries, "queries")
    rng = _rng(seed)
    starts, lengths = random_groups(t.shape[0], groups, group_frames, rng)
    group, op, value = (np.empty((t.shape[1], q), np.int64) for _ in range(3))
    for c in range(t.shape[1]):
        group[c] = rng.integers(0, len(starts), size=q)
        op[c] = rng.integers(0, len(OPERATORS), size=q)
        frame = starts[group[c]] + rng.integers(0, lengths[group[c]])
        value[c] = t[frame, c]
    return CountQueries(starts, lengths, group, op, value)


def _check_queries(queries: Any, frames: int, classes: int) -> CountQueries:
    if not isinstance(queries, CountQueries):
        raise ValueError(f"queries must be a CountQueries or a number of queries, got {type(queries).__name__}")
    if queries.classes != classes:
        raise ValueError(f"queries are for {queries.classes} class(es), the counts have {classes}")
    end = int((queries.starts + queries.lengths).max())
    if end > frames:
        raise ValueError(f"queries reach frame position {end - 1}, the counts have {frames} frame(s)")
    return queries


def count_query_answers(counts: Any, queries: CountQueries) -> np.ndarray:
    """The answers of ``queries`` over ``counts``: how many frames of each query's group meet its condition.

    Args:
        counts: ``(frames,)`` or ``(frames, classes)`` counts.
        queries: :class:`CountQueries` of as many classes, within the frames.

    Returns:
        int64 ``(classes, Q)`` (``(Q,)`` for 1-D counts).
    """
    x = _counts(counts, "counts")
    one_d = x.ndim == 1
    x = x[:, None] if one_d else x
    qs = _check_queries(queries, x.shape[0], x.shape[1])
    out = np.zeros(qs.group.shape, np.int64)
    width = int(qs.lengths.max())
    offsets = np.arange(width)
    step = max(1, _CHUNK // width)
    for c in range(qs.classes):
        for a in range(0, len(qs), step):
            g = qs.group[c, a:a + step]
            inside = offsets[None, :] < qs.lengths[g][:, None]
            rows = np.where(inside, qs.starts[g][:, None] + offsets[None, :], 0)
            d = x[rows, c] - qs.value[c, a:a + step][:, None]
            op = qs.op[c, a:a + step][:, None]
            hit = np.select([op == 0, op == 1, op == 2, op == 3], [d < 0, d <= 0, d == 0, d >= 0], d > 0)
            out[c, a:a + step] = (hit & inside).sum(1)
    return out[0] if one_d else out


def count_query_accuracy(pred: Any, true: Any, queries: "int | CountQueries" = 1000, groups: int = 500,
                         group_frames: tuple[int, int] = (100, 500), seed: Seed = 0) -> dict:
    """COUNT accuracy per class: each query scores ``min(a, b) / max(a, b)`` (1 when both answers are 0, 0
    when exactly one is), ``a`` the query's answer over ``true`` and ``b`` over ``pred``; the accuracy is
    the mean score over the class's queries.

    Args:
        pred, true: counts ``(frames,)`` or ``(frames, classes)``, at least one frame.
        queries: queries per class, drawn by :func:`random_count_queries` from ``true`` with ``groups``,
            ``group_frames`` and ``seed``; or a :class:`CountQueries` to score (the other three unused).

    Returns:
        ``{"accuracy": mean score, "exact": share of queries answered exactly, "mean_abs_error": mean
        |b - a| in frames}``, each float64 ``(classes,)`` (floats for 1-D inputs), and ``"queries"``: the
        :class:`CountQueries` scored.
    """
    p, t, one_d = _pair(pred, true)
    if not isinstance(queries, CountQueries):
        queries = random_count_queries(t, positive_int(queries, "queries"), groups, group_frames, seed)
    qs = _check_queries(queries, t.shape[0], t.shape[1])
    a, b = count_query_answers(t, qs), count_query_answers(p, qs)
    hi = np.maximum(a, b)
    score = np.where(hi == 0, 1.0, np.minimum(a, b) / np.maximum(hi, 1))
    return {"accuracy": _per_class(score.mean(1), one_d), "exact": _per_class((a == b).mean(1), one_d),
            "mean_abs_error": _per_class(np.abs(a - b).mean(1), one_d), "queries": qs}


# ---------------------------------------------------------------------------------------------------------
# AGGREGATION
# ---------------------------------------------------------------------------------------------------------
def aggregation_errors(pred: Any, true: Any, groups: "tuple[Any, Any] | None" = None) -> dict:
    """AGGREGATION (SUM) errors per group and class: the sums ``Σt`` and ``Σp`` over each group's frames,
    their absolute difference ``|Σp - Σt|`` and their :func:`q_error`.

    A sum over no frames is 0 (so inputs without frames, taken as one group, give difference 0 and
    Q-error 1).

    Args:
        pred, true: counts ``(frames,)`` or ``(frames, classes)``.
        groups: ``(starts, lengths)`` of runs of consecutive frames (positions), e.g. from
            :func:`random_groups`; default one group of all the frames.

    Returns:
        ``{"true": Σt, "pred": Σp, "abs_diff": |Σp - Σt|}`` int64 and ``{"q_error": ...}`` float64, each
        ``(groups, classes)`` (``(groups,)`` for 1-D inputs).
    """
    p, t, one_d = _pair(pred, true, frames=False)
    n = p.shape[0]
    if groups is None:
        starts, lengths = np.zeros(1, np.int64), np.full(1, n, np.int64)
    else:
        if not isinstance(groups, (tuple, list)) or len(groups) != 2:
            raise ValueError(f"groups must be (starts, lengths), got {type(groups).__name__}")
        starts, lengths = (np.asarray(v) for v in groups)
        if starts.dtype.kind not in "iu" or lengths.dtype.kind not in "iu" or starts.ndim != 1 \
                or starts.shape != lengths.shape:
            raise ValueError(f"groups must be (starts, lengths), two integer arrays (G,), got shapes "
                             f"{tuple(starts.shape)} and {tuple(lengths.shape)}, dtypes {starts.dtype} and "
                             f"{lengths.dtype}")
        starts, lengths = starts.astype(np.int64), lengths.astype(np.int64)
        if starts.size and ((starts < 0).any() or (lengths < 0).any() or (starts + lengths > n).any()):
            raise ValueError(f"groups must lie within the {n} frame(s): starts >= 0, lengths >= 0, "
                             "starts + lengths <= frames")
    zero = np.zeros((1, p.shape[1]), np.int64)
    cp, ct = np.concatenate([zero, np.cumsum(p, 0)]), np.concatenate([zero, np.cumsum(t, 0)])
    sp, st = cp[starts + lengths] - cp[starts], ct[starts + lengths] - ct[starts]
    out = {"true": st, "pred": sp, "abs_diff": np.abs(sp - st), "q_error": _q_error(sp, st)}
    return {k: v[:, 0] for k, v in out.items()} if one_d else out


# ---------------------------------------------------------------------------------------------------------
# the trainer's evaluator of a counting network
# ---------------------------------------------------------------------------------------------------------
class CountingEvaluator:
    """``evaluator(predictions, frames) -> (metrics, text)`` for :func:`lidarops.train.fit` and a counting
    network (:class:`lidarops.models.counternet.CounterNet`): per-class counting accuracy (in %), mean absolute
    error and RETRIEVAL-SINGLE accuracy at 10 % (in %), and their means over the classes.

    ``predictions[i]`` holds ``counts`` (C,) and ``true_counts`` (C,) (``CounterNet.postprocess`` puts the
    batch's labelled counts beside its own); ``frames`` are not read.
    """

    def __init__(self, class_names: Sequence[str]) -> None:
        if isinstance(class_names, str) or not class_names or not all(isinstance(n, str) for n in class_names):
            raise ValueError(f"class_names must be a non-empty list of names, got {class_names!r}")
        self.class_names = tuple(class_names)

    def __call__(self, predictions: Sequence[Any], frames: Sequence[Any]) -> tuple[dict[str, float], str]:
        if not predictions:
            raise ValueError("predictions is empty: no frame to evaluate")
        for i, p in enumerate(predictions):
            if "counts" not in p or "true_counts" not in p:
                raise ValueError(f"predictions[{i}] needs 'counts' and 'true_counts' (keys {sorted(p)}): the "
                                 "model's postprocess must see the batch's gt_boxes")
        pred = np.stack([np.asarray(p["counts"]).reshape(-1) for p in predictions]).astype(np.int64)
        true = np.stack([np.asarray(p["true_counts"]).reshape(-1) for p in predictions]).astype(np.int64)
        if pred.shape[1] != len(self.class_names) or true.shape != pred.shape:
            raise ValueError(f"counts must hold one entry per class ({len(self.class_names)}), got predicted "
                             f"{pred.shape[1:]} and true {true.shape[1:]}")
        acc = np.atleast_1d(counting_accuracy(pred, true)) * 100
        mae = np.atleast_1d(mean_absolute_error(pred, true))
        r10 = np.atleast_1d(retrieval_single_accuracy(pred, true, 0.1)) * 100
        metrics: dict[str, float] = {"counting_accuracy": float(acc.mean()), "count_mae": float(mae.mean()),
                                     "retrieval_single_10": float(r10.mean())}
        lines = [f"{'class':<12} {'exact %':>8} {'MAE':>7} {'R-single@10% %':>15} {'true/frame':>10}"]
        for k, name in enumerate(self.class_names):
            metrics[f"counting_accuracy_{name}"] = float(acc[k])
            metrics[f"count_mae_{name}"] = float(mae[k])
            lines.append(f"{name:<12} {acc[k]:8.1f} {mae[k]:7.2f} {r10[k]:15.1f} {true[:, k].mean():10.2f}")
        lines.append(f"{'mean':<12} {acc.mean():8.1f} {mae.mean():7.2f} {r10.mean():15.1f}   ({len(pred)} frames)")
        return metrics, "\n".join(lines)
