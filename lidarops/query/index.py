"""The frame index: per-frame, per-class object counts (and the counted objects' BEV centres) of one or
more sources, as Parquet files, queried through DuckDB views.

Layout of an index folder::

    index.json                          classes, sources, format version
    counts/<source>/part-00000.parquet  source, frame_id (int64), sequence, timestamp, one int32 column per class
    centres/<source>/part-00000.parquet source, frame_id, class, x, y (metres, BEV), score

A source is where counts come from: ``labels`` (the ground truth), a detector used as a counter, a counting
network. Each query is one SQL statement over the view ``counts`` (``centres`` for regions), with the
class names checked against the index and every value bound as a parameter.
"""
from __future__ import annotations

import json
import math
import numbers
import os
import re
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

__all__ = ["FrameIndex", "QueryError", "OPERATORS"]

FORMAT = "lidarops-frame-index"
FORMAT_VERSION = 1
#: comparison operators of RETRIEVAL and COUNT queries
OPERATORS = ("<", "<=", "=", ">=", ">")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")  # class and source names: SQL identifiers, folder names


class QueryError(ValueError):
    """A query or index that cannot be answered: the message names the argument and what is valid."""


def _name(value: Any, what: str) -> str:
    if not isinstance(value, str) or not _NAME.match(value):
        raise QueryError(f"{what} must be a name of letters, digits and underscores (not starting with a digit), "
                         f"got {value!r}")
    return value


def _columns(table) -> dict[str, np.ndarray]:
    """A pandas DataFrame, a pyarrow Table or a mapping of column name -> array, as NumPy columns."""
    if hasattr(table, "to_pydict") and hasattr(table, "column_names"):  # pyarrow.Table
        return {name: np.asarray(table.column(name).to_numpy(zero_copy_only=False)) for name in table.column_names}
    if hasattr(table, "columns") and hasattr(table, "to_numpy"):  # pandas.DataFrame
        return {str(name): table[name].to_numpy() for name in table.columns}
    if isinstance(table, Mapping):
        return {str(k): np.asarray(v) for k, v in table.items()}
    raise QueryError(f"counts must be a pandas DataFrame, a pyarrow Table or a dict of columns, got {type(table).__name__}")


def _int_column(values: np.ndarray, what: str, minimum: int | None = None) -> np.ndarray:
    if values.dtype.kind == "b" or values.dtype.kind not in "iuf":
        raise QueryError(f"{what} must hold integers, got dtype {values.dtype}")
    if values.dtype.kind == "f":
        bad = ~(np.isfinite(values) & (values == np.round(values)))
        if bad.any():
            raise QueryError(f"{what} must hold whole numbers, got e.g. {values[bad][:3].tolist()}")
    out = values.astype(np.int64)
    if minimum is not None and out.size and out.min() < minimum:
        raise QueryError(f"{what} must be >= {minimum}, got {int(out.min())}")
    return out


def _threshold(value: Any, what: str) -> int | float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise QueryError(f"{what} must be a finite number, got {value!r}")
    return value


class FrameIndex:
    """An index folder, open for queries (see the module docstring for its layout).

    Open one with :meth:`open`, make one with :meth:`create`, add frames or sources with :meth:`append`.
    """

    def __init__(self, root: Path, meta: dict):
        import duckdb

        self.root = root
        self.meta = meta
        self.con = duckdb.connect()
        self._views()

    # ---------------------------------------------------------------- making and opening
    @classmethod
    def create(cls, root: "str | os.PathLike", counts, centres=None, source: str = "labels",
               classes: Sequence[str] | None = None) -> "FrameIndex":
        """A new index at ``root`` (refused if one is there) holding ``counts`` of ``source``.

        Args:
            counts: a table (pandas DataFrame, pyarrow Table or dict of columns) with ``frame_id`` (integers,
                unique), optional ``sequence`` (str) and ``timestamp`` (float, seconds), and one column of
                non-negative integer counts per class.
            centres: optional table of the counted objects: ``frame_id``, ``class``, ``x``, ``y`` (BEV metres)
                and optional ``score``; needed for queries restricted to a region.
            source: the source's name (``labels``, ``detector``, ...).
            classes: the index's classes (default: the class columns of ``counts``); a source may leave a
                class out (its counts are then 0).
        """
        root = Path(root)
        if (root / "index.json").exists():
            raise QueryError(f"{root} already holds an index (index.json): open it with FrameIndex.open, or add "
                             "frames with append")
        cols = _columns(counts)
        if classes is None:
            classes = [c for c in cols if c not in ("frame_id", "sequence", "timestamp", "source")]
        classes = [_name(c, "a class name") for c in classes]
        if not classes:
            raise QueryError("counts has no class column (one integer column per class besides frame_id)")
        if len(set(classes)) != len(classes):
            raise QueryError(f"classes must be distinct, got {classes}")
        root.mkdir(parents=True, exist_ok=True)
        meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "classes": list(classes), "sources": {}}
        index = cls.__new__(cls)
        index.root, index.meta = root, meta
        index._write(cols, centres, _name(source, "source"))
        index._save_meta()
        return cls.open(root)

    @classmethod
    def open(cls, root: "str | os.PathLike") -> "FrameIndex":
        """The index at ``root`` (``QueryError`` if there is none or it is of another format)."""
        root = Path(root)
        path = root / "index.json"
        if not path.is_file():
            raise QueryError(f"no frame index at {root} (no index.json): build one with FrameIndex.create")
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise QueryError(f"{path}: not a readable index description ({e})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise QueryError(f"{path}: not a lidarops frame index")
        if int(meta.get("format_version", 0)) > FORMAT_VERSION:
            raise QueryError(f"{path} has format version {meta['format_version']}, newer than this lidarops reads "
                             f"({FORMAT_VERSION}): upgrade lidarops")
        return cls(root, meta)

    def append(self, counts, centres=None, source: str = "labels") -> None:
        """Adds frames to a source, or a new source. Frames the source already holds are refused (naming
        them): an index holds each frame once per source."""
        self._write(_columns(counts), centres, _name(source, "source"))
        self._save_meta()
        self._views()

    # ---------------------------------------------------------------- queries
    @property
    def classes(self) -> list[str]:
        return list(self.meta["classes"])

    @property
    def sources(self) -> list[str]:
        return sorted(self.meta["sources"])

    def retrieve(self, where: Mapping[str, tuple], frames=None, source: str = "labels",
                 region: Sequence[float] | None = None) -> list[int]:
        """RETRIEVAL: the ids (ascending) of the frames whose counts meet every condition.

        Args:
            where: ``{class: (operator, value)}``, e.g. ``{"Car": (">=", 5), "Pedestrian": ("<=", 2)}``;
                operators ``<, <=, =, >=, >``. An empty mapping selects every frame.
            frames: ``range`` or list of frame ids to search (default: all).
            source: whose counts.
            region: ``(x0, y0, x1, y1)`` metres: count only objects with ``x0 <= x < x1`` and
                ``y0 <= y < y1`` (needs the source's centres).
        """
        if not isinstance(where, Mapping):
            raise QueryError(f"where must be a mapping of class -> (operator, value), got {type(where).__name__}")
        conds, params = [], []
        for cls_name, cond in where.items():
            column = self._class(cls_name)
            if not isinstance(cond, (tuple, list)) or len(cond) != 2:
                raise QueryError(f"the condition on {cls_name} must be (operator, value), got {cond!r}")
            op = self._operator(cond[0])
            conds.append(f"{column} {op} ?")
            params.append(_threshold(cond[1], f"the value compared with {cls_name}"))
        sql, base = self._frame_source(source, frames, region)
        where_sql = " AND ".join(conds) if conds else "TRUE"
        rows = self.con.execute(f"{sql} SELECT frame_id FROM f WHERE {where_sql} ORDER BY frame_id",
                                base + params).fetchall()
        return [int(r[0]) for r in rows]

    def count(self, cls_name: str, op: str, value, frames=None, source: str = "labels",
              region: Sequence[float] | None = None) -> int:
        """COUNT: how many frames have ``count(cls_name) op value``."""
        column, op = self._class(cls_name), self._operator(op)
        value = _threshold(value, f"the value compared with {cls_name}")
        sql, base = self._frame_source(source, frames, region)
        return int(self.con.execute(f"{sql} SELECT count(*) FROM f WHERE {column} {op} ?", base + [value]).fetchone()[0])

    def sum(self, cls_name: str, frames=None, source: str = "labels", region: Sequence[float] | None = None) -> int:
        """AGGREGATION: the total number of ``cls_name`` objects over the frames (0 for no frames)."""
        column = self._class(cls_name)
        sql, base = self._frame_source(source, frames, region)
        return int(self.con.execute(f"{sql} SELECT coalesce(sum({column}), 0) FROM f", base).fetchone()[0])

    def avg(self, cls_name: str, frames=None, source: str = "labels",
            region: Sequence[float] | None = None) -> float | None:
        """AGGREGATION: the mean number of ``cls_name`` objects per frame (None for no frames)."""
        column = self._class(cls_name)
        sql, base = self._frame_source(source, frames, region)
        value = self.con.execute(f"{sql} SELECT avg({column}) FROM f", base).fetchone()[0]
        return None if value is None else float(value)

    def sql(self, query: str, params: Sequence[Any] = ()):
        """Any SQL over the views ``counts`` and ``centres`` (a pandas DataFrame)."""
        return self.con.execute(query, list(params)).df()

    # ---------------------------------------------------------------- internals
    def _class(self, cls_name: Any) -> str:
        if cls_name not in self.meta["classes"]:
            raise QueryError(f"unknown class {cls_name!r}; the index's classes: {', '.join(self.meta['classes'])}")
        return f'"{cls_name}"'

    @staticmethod
    def _operator(op: Any) -> str:
        if op not in OPERATORS:
            raise QueryError(f"unknown operator {op!r}; valid: {', '.join(OPERATORS)}")
        return op

    def _frame_source(self, source: str, frames, region) -> tuple[str, list]:
        """A ``WITH f AS (...)`` clause: one row per frame of ``source`` (within ``frames``), one column per
        class (counted within ``region`` when given), and its parameters."""
        if source not in self.meta["sources"]:
            raise QueryError(f"unknown source {source!r}; the index's sources: {', '.join(self.sources) or 'none'}")
        filt, params = self._frames_filter(frames)
        if region is None:
            return f"WITH f AS (SELECT * FROM counts WHERE source = ?{filt})", [source] + params
        if not self.meta["sources"][source].get("centres"):
            raise QueryError(f"source {source!r} has no object centres: a region query needs them (create or "
                             "append the source with centres=...)")
        if not isinstance(region, (tuple, list)) or len(region) != 4:
            raise QueryError(f"region must be (x0, y0, x1, y1) in metres, got {region!r}")
        x0, y0, x1, y1 = (float(_threshold(v, "region")) for v in region)
        if not (x0 < x1 and y0 < y1):
            raise QueryError(f"region must have x0 < x1 and y0 < y1, got {tuple(region)}")
        counted = ", ".join(f'count(*) FILTER (WHERE class = \'{c}\') AS "{c}"' for c in self.meta["classes"])
        picked = ", ".join(f'coalesce(r."{c}", 0) AS "{c}"' for c in self.meta["classes"])
        sql = (f"WITH r AS (SELECT frame_id, {counted} FROM centres WHERE source = ? AND x >= ? AND x < ? "
               f"AND y >= ? AND y < ? GROUP BY frame_id), "
               f"f AS (SELECT k.frame_id, {picked} FROM counts k LEFT JOIN r ON k.frame_id = r.frame_id "
               f"WHERE k.source = ?{filt.replace('frame_id', 'k.frame_id')})")
        return sql, [source, x0, x1, y0, y1, source] + params

    @staticmethod
    def _frames_filter(frames) -> tuple[str, list]:
        if frames is None:
            return "", []
        if isinstance(frames, range):
            if frames.step != 1:
                raise QueryError(f"frames must be a range of step 1 or a list of ids, got {frames!r}")
            return " AND frame_id >= ? AND frame_id < ?", [frames.start, frames.stop]
        if isinstance(frames, (str, bytes)) or not isinstance(frames, Iterable):
            raise QueryError(f"frames must be a range or a list of frame ids, got {type(frames).__name__}")
        frames = list(frames)
        ids = _int_column(np.asarray(frames).reshape(-1), "frames").tolist() if frames else []
        return " AND list_contains(?::BIGINT[], frame_id)", [ids]

    def _views(self) -> None:
        for kind in ("counts", "centres"):
            files = sorted((self.root / kind).glob("*/*.parquet"))
            if files:  # a view cannot take parameters: the paths go in as quoted literals
                listed = ", ".join("'" + str(f).replace("'", "''") + "'" for f in files)
                self.con.execute(f"CREATE OR REPLACE VIEW {kind} AS SELECT * FROM read_parquet([{listed}], "
                                 "union_by_name=true)")
            elif kind == "centres":
                self.con.execute("CREATE OR REPLACE VIEW centres AS SELECT NULL::VARCHAR AS source, NULL::BIGINT AS "
                                 "frame_id, NULL::VARCHAR AS class, NULL::FLOAT AS x, NULL::FLOAT AS y, "
                                 "NULL::FLOAT AS score WHERE FALSE")

    def _save_meta(self) -> None:
        tmp = self.root / "index.json.tmp"
        tmp.write_text(json.dumps(self.meta, indent=1) + "\n")
        os.replace(tmp, self.root / "index.json")

    def _write(self, cols: dict[str, np.ndarray], centres, source: str) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        classes = self.meta["classes"]
        if "frame_id" not in cols:
            raise QueryError(f"counts needs a frame_id column, got columns {sorted(cols)}")
        frame_id = _int_column(cols["frame_id"], "counts' frame_id").reshape(-1)
        n = frame_id.shape[0]
        values, times = np.unique(frame_id, return_counts=True)
        if (times > 1).any():
            raise QueryError(f"counts' frame_id holds duplicates, e.g. {values[times > 1][:5].tolist()}")
        unknown = [c for c in cols if c not in ("frame_id", "sequence", "timestamp", "source") and c not in classes]
        if unknown:
            raise QueryError(f"counts has columns of classes the index does not hold: {unknown}; its classes: "
                             f"{', '.join(classes)}")
        existing = self.meta["sources"].get(source)
        if existing and hasattr(self, "con"):
            held = self.con.execute("SELECT frame_id FROM counts WHERE source = ? AND list_contains(?, frame_id) "
                                    "ORDER BY frame_id LIMIT 5", [source, frame_id.tolist()]).fetchall()
            if held:
                raise QueryError(f"source {source!r} already holds frames {[int(r[0]) for r in held]}: an index holds "
                                 "each frame once per source")
        table = {"source": pa.array([source] * n, pa.string()), "frame_id": pa.array(frame_id, pa.int64()),
                 "sequence": pa.array([None if v is None else str(v) for v in cols["sequence"]], pa.string())
                 if "sequence" in cols else pa.nulls(n, pa.string()),
                 "timestamp": pa.array(np.asarray(cols["timestamp"], np.float64)) if "timestamp" in cols
                 else pa.nulls(n, pa.float64())}
        for c in classes:
            values = _int_column(cols[c], f"counts' column {c}", minimum=0).reshape(-1) if c in cols \
                else np.zeros(n, np.int64)
            if values.shape[0] != n:
                raise QueryError(f"counts' column {c} has {values.shape[0]} rows, frame_id has {n}")
            table[c] = pa.array(values.astype(np.int32), pa.int32())
        part = len(list((self.root / "counts" / source).glob("*.parquet"))) if (self.root / "counts" / source).is_dir() else 0
        has_centres = bool(existing and existing.get("centres"))
        centre_table = None
        if centres is not None:
            cc = _columns(centres)
            missing = [k for k in ("frame_id", "class", "x", "y") if k not in cc]
            if missing:
                raise QueryError(f"centres needs the columns frame_id, class, x, y; missing {missing}")
            cid = _int_column(cc["frame_id"], "centres' frame_id").reshape(-1)
            if not np.isin(cid, frame_id).all():
                raise QueryError(f"centres name frames that counts does not hold, e.g. {cid[~np.isin(cid, frame_id)][:5].tolist()}")
            names = [str(v) for v in cc["class"]]
            bad = sorted(set(names) - set(classes))
            if bad:
                raise QueryError(f"centres hold classes the index does not: {bad}; its classes: {', '.join(classes)}")
            xy = np.stack([np.asarray(cc["x"], np.float64), np.asarray(cc["y"], np.float64)], 1) if len(cid) else np.zeros((0, 2))
            if not np.isfinite(xy).all():
                raise QueryError("centres' x and y must be finite")
            centre_table = {"source": pa.array([source] * len(cid), pa.string()), "frame_id": pa.array(cid, pa.int64()),
                            "class": pa.array(names, pa.string()), "x": pa.array(xy[:, 0].astype(np.float32)),
                            "y": pa.array(xy[:, 1].astype(np.float32)),
                            "score": pa.array(np.asarray(cc["score"], np.float32)) if "score" in cc
                            else pa.nulls(len(cid), pa.float32())}
            has_centres = True
        elif existing and existing.get("centres"):
            raise QueryError(f"source {source!r} has object centres: append its new frames with centres too")
        for kind, data in (("counts", table), ("centres", centre_table)):
            if data is None:
                continue
            folder = self.root / kind / source
            folder.mkdir(parents=True, exist_ok=True)
            tmp = folder / f".part-{part:05d}.parquet.tmp"
            pq.write_table(pa.table(data), tmp)
            os.replace(tmp, folder / f"part-{part:05d}.parquet")  # a reader never sees half a part
        entry = self.meta["sources"].setdefault(source, {"frames": 0, "parts": 0, "centres": False})
        entry["frames"] += n
        entry["parts"] = part + 1
        entry["centres"] = has_centres
