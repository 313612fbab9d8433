"""CounterNet's query metrics for a source of a frame index, scored against another (the labels)::

    from lidarops.query import FrameIndex
    from lidarops.query.evaluate import evaluate
    result = evaluate(FrameIndex.open("city_index"), source="detector")   # truth="labels"
    print(result.format())                       # the tables; result.as_dict() for JSON

The two sources' counts are read with one SQL statement (a full outer join on ``frame_id``); the frames
both hold are scored, in ascending frame id (the order "consecutive frames" follow), and the frames only
one of them holds are reported, never silently dropped. The metrics and their exact definitions (zero
cases, ties at the tolerance) are :mod:`lidarops.eval.counting`'s.
"""
from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from lidarops.query.index import FrameIndex, QueryError

__all__ = ["evaluate", "Evaluation"]

_SHOWN_IDS = 5  # frame ids shown per "only in" line


@dataclass
class Evaluation:
    """The metrics of ``source`` against ``truth`` over their common frames (per class in ``classes``
    order; definitions in :mod:`lidarops.eval.counting`).

    Attributes:
        frames: the number of frames both sources hold (the frames scored).
        only_source, only_truth: ids of the frames one source holds and the other does not (int64, ascending).
        tolerances: the RETRIEVAL tolerances, e.g. ``(0.1, 0.05)``.
        max_count: per class, the largest true count over the frames scored (the tolerances' base).
        allowed_error: ``{tolerance: (classes,) int}``, the largest count error within it.
        retrieval_single: ``{tolerance: (classes,) float}``; retrieval_multiple: ``{tolerance: float}``.
        counting_accuracy, mean_abs_error, mean_true, mean_pred: per class, over the frames scored.
        count: ``{"accuracy", "exact", "mean_abs_error"}`` of the COUNT queries, each ``(classes,)``.
        aggregation: SUM over all the frames scored: ``{"true", "pred", "abs_diff", "q_error"}``, each
            ``(classes,)``.
        aggregation_groups: over the random groups: ``{"mean_abs_diff", "mean_q_error", "median_q_error",
            "max_q_error"}``, each ``(classes,)``.
        groups, group_lengths: the number of random groups and their shortest and longest length as drawn
            (lengths are clipped to the frames scored); queries: COUNT queries per class; seed: the seed
            (None when a Generator was given).
    """

    source: str
    truth: str
    classes: list[str]
    frames: int
    only_source: np.ndarray
    only_truth: np.ndarray
    tolerances: tuple[float, ...]
    max_count: np.ndarray
    allowed_error: dict[float, np.ndarray]
    retrieval_single: dict[float, np.ndarray]
    retrieval_multiple: dict[float, float]
    counting_accuracy: np.ndarray
    mean_abs_error: np.ndarray
    mean_true: np.ndarray
    mean_pred: np.ndarray
    count: dict[str, np.ndarray]
    aggregation: dict[str, np.ndarray]
    aggregation_groups: dict[str, np.ndarray]
    groups: int
    group_lengths: tuple[int, int]
    queries: int
    seed: "int | None"

    # ------------------------------------------------------------------------------------------ output
    def as_dict(self) -> dict:
        """Plain Python values (JSON-ready): per-class values as ``{class: value}``."""
        def per_class(values) -> dict:
            return {c: _plain(v) for c, v in zip(self.classes, np.asarray(values).tolist())}

        return {
            "source": self.source, "truth": self.truth, "classes": list(self.classes), "frames": self.frames,
            "only_source": self.only_source.tolist(), "only_truth": self.only_truth.tolist(),
            "tolerances": list(self.tolerances), "max_count": per_class(self.max_count),
            "allowed_error": {_tol(t): per_class(v) for t, v in self.allowed_error.items()},
            "retrieval_single": {_tol(t): per_class(v) for t, v in self.retrieval_single.items()},
            "retrieval_multiple": {_tol(t): float(v) for t, v in self.retrieval_multiple.items()},
            "counting_accuracy": per_class(self.counting_accuracy), "mean_abs_error": per_class(self.mean_abs_error),
            "mean_true": per_class(self.mean_true), "mean_pred": per_class(self.mean_pred),
            "count": {k: per_class(v) for k, v in self.count.items()},
            "aggregation": {k: per_class(v) for k, v in self.aggregation.items()},
            "aggregation_groups": {k: per_class(v) for k, v in self.aggregation_groups.items()},
            "groups": self.groups, "group_lengths": list(self.group_lengths), "queries": self.queries,
            "seed": self.seed,
        }

    def tables(self) -> list[tuple[str, list[str], list[list[str]]]]:
        """The printable tables: ``(title, header, rows)``, cells as strings."""
        tols = self.tolerances
        retrieval = [[c, str(int(self.max_count[i]))]
                     + [x for t in tols for x in (f"{int(self.allowed_error[t][i])}",
                                                  _f(self.retrieval_single[t][i]))]
                     for i, c in enumerate(self.classes)]
        retrieval.append(["all (MULTIPLE)", ""] + [x for t in tols for x in ("", _f(self.retrieval_multiple[t]))])
        count = [[c, _f(self.count["accuracy"][i]), _f(self.count["exact"][i]),
                  f"{self.count['mean_abs_error'][i]:.2f}"] for i, c in enumerate(self.classes)]
        agg, grp = self.aggregation, self.aggregation_groups
        aggregation = [[c, str(int(agg["true"][i])), str(int(agg["pred"][i])), str(int(agg["abs_diff"][i])),
                        f"{agg['q_error'][i]:.3f}", f"{grp['mean_abs_diff'][i]:.2f}", f"{grp['mean_q_error'][i]:.3f}",
                        f"{grp['median_q_error'][i]:.3f}", f"{grp['max_q_error'][i]:.3f}"]
                       for i, c in enumerate(self.classes)]
        counting = [[c, _f(self.counting_accuracy[i]), f"{self.mean_abs_error[i]:.3f}", f"{self.mean_true[i]:.2f}",
                     f"{self.mean_pred[i]:.2f}"] for i, c in enumerate(self.classes)]
        lo, hi = self.group_lengths
        seed = "a Generator" if self.seed is None else str(self.seed)
        return [
            (f"RETRIEVAL accuracy of {self.source} against {self.truth} over {self.frames} frames: share of frames "
             "whose count is within the allowed error (+/- = floor(tolerance * max count))",
             ["class", "max count"] + [x for t in tols for x in (f"+/- @{_pct(t)}", f"SINGLE @{_pct(t)}")],
             retrieval),
            (f"COUNT queries: {self.queries} per class over {self.groups} groups of {lo}-{hi} consecutive frames "
             f"(seed {seed}); a query scores min(a, b) / max(a, b), a the truth's answer, b the source's",
             ["class", "accuracy", "exact", "mean |b - a| (frames)"], count),
            ("AGGREGATION (SUM): all frames, and the mean / median / max over the groups",
             ["class", "true", "pred", "|diff|", "Q-error", "groups |diff|", "mean Q", "median Q", "max Q"],
             aggregation),
            ("Per-class counting: share of frames counted exactly",
             ["class", "accuracy", "mean |error|", "mean true", "mean pred"], counting),
        ]

    def format(self) -> str:
        """The frames line and the tables, as text."""
        lines = [f"{self.source} against {self.truth}: {self.frames} common frame(s); "
                 f"{_ids(self.only_source)} only in {self.source}; {_ids(self.only_truth)} only in {self.truth}"]
        for title, header, rows in self.tables():
            lines += ["", title, _table(header, rows)]
        return "\n".join(lines)

    __str__ = format


def evaluate(index: "FrameIndex | str | os.PathLike", source: str = "detector", truth: str = "labels",
             classes: Sequence[str] | None = None, seed: "int | np.random.Generator" = 0,
             tolerances: Sequence[float] = (0.10, 0.05), groups: int = 500, queries: int = 1000,
             group_frames: tuple[int, int] = (100, 500)) -> Evaluation:
    """Scores ``source``'s counts against ``truth``'s with CounterNet's query metrics.

    Args:
        index: a :class:`FrameIndex` or the path of one.
        source: the source scored (``detector``, a counting network, ...).
        truth: the source taken as the truth (default ``labels``).
        classes: the classes scored (default: all the index's); RETRIEVAL-MULTIPLE asks for all of them.
        seed: seeds the random COUNT queries and groups (an int >= 0, or a ``numpy.random.Generator``). The
            queries are drawn over the truth's counts of every class of the index, so a class's queries do not
            depend on which classes are scored.
        tolerances: RETRIEVAL tolerances in [0, 1] (default 10 % and 5 %).
        groups: random groups of consecutive frames (default 500), for COUNT and AGGREGATION.
        queries: COUNT queries per class (default 1,000).
        group_frames: ``(fewest, most)`` frames of a group (default 100–500; clipped to the frames scored).

    Returns:
        an :class:`Evaluation` (``.format()`` prints its tables, ``.as_dict()`` for JSON).

    Raises:
        QueryError: an unknown source or class, bad arguments (each named), or no frame both sources hold.
    """
    from lidarops.eval import counting

    if not isinstance(index, FrameIndex):
        if not isinstance(index, (str, os.PathLike)):
            raise QueryError(f"index must be a FrameIndex or the path of one, got {type(index).__name__}")
        index = FrameIndex.open(index)
    for name, value in (("source", source), ("truth", truth)):
        if value not in index.sources:
            raise QueryError(f"unknown {name} {value!r}; the index's sources: {', '.join(index.sources) or 'none'}")
    every = index.classes
    if classes is None:
        classes = list(every)
    else:
        if isinstance(classes, str) or not isinstance(classes, Sequence):
            raise QueryError(f"classes must be a list of class names, got {classes!r}")
        classes = list(classes)
        for c in classes:
            if c not in every:
                raise QueryError(f"unknown class {c!r}; the index's classes: {', '.join(every)}")
        if not classes or len(set(classes)) != len(classes):
            raise QueryError(f"classes must name at least one class, each once, got {classes}")
    if isinstance(tolerances, (str, bytes)) or not isinstance(tolerances, Sequence) or not tolerances:
        raise QueryError(f"tolerances must be a list of numbers in [0, 1], got {tolerances!r}")
    tols = []
    for t in tolerances:
        if isinstance(t, (bool, np.bool_)) or not isinstance(t, numbers.Real) or not math.isfinite(float(t)) \
                or not 0 <= float(t) <= 1:
            raise QueryError(f"tolerances must be numbers in [0, 1], got {t!r} in {tolerances!r}")
        tols.append(float(t))
    if len(set(tols)) != len(tols):
        raise QueryError(f"tolerances must differ, got {list(tolerances)}")
    try:  # the counting module's checks name the argument; here they are the query's errors
        counting.random_groups(1, groups, group_frames, 0)  # checks groups and group_frames, naming them
        if isinstance(queries, (bool, np.bool_)) or not isinstance(queries, numbers.Integral) or queries < 1:
            raise ValueError(f"queries must be a positive int, got {queries!r}")
        if not isinstance(seed, np.random.Generator) and (isinstance(seed, (bool, np.bool_)) or not isinstance(
                seed, numbers.Integral) or seed < 0):
            raise ValueError(f"seed must be an int >= 0 or a numpy.random.Generator, got {seed!r}")
    except ValueError as e:
        raise QueryError(str(e)) from None

    pick = ", ".join(f'coalesce(s."{c}", 0) AS "s_{c}", coalesce(t."{c}", 0) AS "t_{c}"' for c in every)
    table = index.sql(
        "SELECT coalesce(s.frame_id, t.frame_id) AS frame_id, s.frame_id IS NOT NULL AS in_source, "
        f"t.frame_id IS NOT NULL AS in_truth, {pick} "
        "FROM (SELECT * FROM counts WHERE source = ?) AS s "
        "FULL OUTER JOIN (SELECT * FROM counts WHERE source = ?) AS t ON s.frame_id = t.frame_id "
        "ORDER BY frame_id", [source, truth])
    frame_id = table["frame_id"].to_numpy(np.int64)
    in_source, in_truth = table["in_source"].to_numpy(bool), table["in_truth"].to_numpy(bool)
    both = in_source & in_truth
    only_source, only_truth = frame_id[in_source & ~in_truth], frame_id[in_truth & ~in_source]
    if not both.any():
        raise QueryError(f"sources {source!r} ({int(in_source.sum())} frames) and {truth!r} ({int(in_truth.sum())} "
                         "frames) share no frame id: nothing to score")
    pred_all = np.stack([table[f"s_{c}"].to_numpy(np.int64)[both] for c in every], 1)
    true_all = np.stack([table[f"t_{c}"].to_numpy(np.int64)[both] for c in every], 1)
    cols = [every.index(c) for c in classes]
    pred, true = pred_all[:, cols], true_all[:, cols]

    # one draw over every class of the index: a class's queries do not depend on the classes scored
    qs = counting.random_count_queries(true_all, queries, groups, group_frames, seed)
    count = counting.count_query_accuracy(pred_all, true_all, qs)
    whole = counting.aggregation_errors(pred, true)
    grouped = counting.aggregation_errors(pred, true, (qs.starts, qs.lengths))
    return Evaluation(
        source=source, truth=truth, classes=classes, frames=int(both.sum()), only_source=only_source,
        only_truth=only_truth, tolerances=tuple(tols), max_count=true.max(0),
        allowed_error={t: counting.allowed_error(true, t) for t in tols},
        retrieval_single={t: counting.retrieval_single_accuracy(pred, true, t) for t in tols},
        retrieval_multiple={t: counting.retrieval_multiple_accuracy(pred, true, t) for t in tols},
        counting_accuracy=counting.counting_accuracy(pred, true),
        mean_abs_error=counting.mean_absolute_error(pred, true),
        mean_true=true.mean(0), mean_pred=pred.mean(0),
        count={k: count[k][cols] for k in ("accuracy", "exact", "mean_abs_error")},
        aggregation={k: v[0] for k, v in whole.items()},
        aggregation_groups={"mean_abs_diff": grouped["abs_diff"].mean(0), "mean_q_error": grouped["q_error"].mean(0),
                            "median_q_error": np.median(grouped["q_error"], 0),
                            "max_q_error": grouped["q_error"].max(0)},
        groups=len(qs.starts), group_lengths=(int(qs.lengths.min()), int(qs.lengths.max())), queries=len(qs),
        seed=None if isinstance(seed, np.random.Generator) else int(seed))


# ------------------------------------------------------------------------------------------------- helpers
def _plain(v: Any) -> Any:
    return int(v) if isinstance(v, (int, np.integer)) else float(v)


def _tol(t: float) -> str:
    return repr(float(t))


def _pct(t: float) -> str:
    return f"{t * 100:g}%"


def _f(v: float) -> str:
    return f"{float(v):.3f}"


def _ids(ids: np.ndarray) -> str:
    if len(ids) == 0:
        return "0 frames"
    shown = ", ".join(str(int(i)) for i in ids[:_SHOWN_IDS]) + (", ..." if len(ids) > _SHOWN_IDS else "")
    return f"{len(ids)} frame(s) (ids {shown})"


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    fmt = "  ".join(["{:<%d}" % widths[0]] + ["{:>%d}" % w for w in widths[1:]])
    lines = [fmt.format(*header).rstrip(), "  ".join("-" * w for w in widths)]
    return "\n".join(lines + [fmt.format(*r).rstrip() for r in rows])
