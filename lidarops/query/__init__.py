"""Point-cloud queries over a fleet's frames (CounterNet's query side): an index of per-frame, per-class
object counts and object centres, as Parquet files with DuckDB views over them, and RETRIEVAL / COUNT /
AGGREGATION queries, each one SQL statement::

    from lidarops.query import FrameIndex
    idx = FrameIndex.create("fleet_index", counts)              # counts: frame_id + one column per class
    idx.retrieve({"Car": (">=", 5), "Pedestrian": ("<=", 2)})   # frame ids
    idx.count("Car", ">=", 5), idx.sum("Car"), idx.avg("Car")
    evaluate(idx, source="detector")                             # CounterNet's metrics against the labels

docs/query.md says what exists and what is to come. ``import lidarops.query`` is light: DuckDB and
pyarrow are imported on first use.
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes

_LAZY = {"FrameIndex": ("lidarops.query.index", "FrameIndex"), "QueryError": ("lidarops.query.index", "QueryError"),
         "OPERATORS": ("lidarops.query.index", "OPERATORS"), "FrameIds": ("lidarops.query.index", "FrameIds"),
         "build_index": ("lidarops.query.build", "build_index"), "evaluate": ("lidarops.query.evaluate", "evaluate"),
         "Evaluation": ("lidarops.query.evaluate", "Evaluation"), "answer_page": ("lidarops.query.page", "answer_page")}

__all__ = list(_LAZY)

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, globals())
