"""The frame index: per-frame, per-class object counts (and the counted objects' BEV centres) of one or
more sources, as Parquet files, queried through DuckDB views.

Layout of an index folder::

    index.json                          classes, sources, format version
    counts/<source>/part-00000.parquet  source, frame_id (int64), sequence, timestamp, path, model (the member of a
                                        model selection that counted the frame), one int32 column per class
                                        (part-r001-00000.parquet: written by torchrun rank 1)
    centres/<source>/part-00000.parquet source, frame_id, class, x, y (metres, BEV), score
    index.duckdb                        a cache of the parts as DuckDB tables, remade on open when they change

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
from collections import abc
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

__all__ = ["FrameIndex", "QueryError", "OPERATORS"]

FORMAT = "lidarops-frame-index"
FORMAT_VERSION = 1
#: comparison operators of RETRIEVAL and COUNT queries
OPERATORS = ("<", "<=", "=", ">=", ">")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")  # class and source names: SQL identifiers, folder names
#: the columns of a counts table that are not classes
_META_COLUMNS = ("frame_id", "sequence", "timestamp", "path", "source", "model")
_WRITER = re.compile(r"^[a-z0-9]*$")


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


STORE_FILE = "index.duckdb"  # the parts as DuckDB tables, made by FrameIndex.open (see FrameIndex._store)
STORE_PARTS = "parts_v1"  # its table of the parts it holds; another name (version) makes open rebuild it


def _float32_ceil(value: float) -> float:
    """The least float32 >= ``value`` (infinite past float32's range), as a Python float."""
    with np.errstate(over="ignore"):
        f = np.float32(value)
        if float(f) < value:
            f = np.nextafter(f, np.float32(np.inf))
    return float(f)


def _literal(path: Path) -> str:
    """A path as a quoted SQL string (where DuckDB takes no parameter: views, ATTACH)."""
    return "'" + str(path).replace("'", "''") + "'"


class FrameIds(abc.Sequence):
    """The frame ids a RETRIEVAL answers, ascending: a read-only sequence of ints over a NumPy int64 array.

    It behaves as the list of those ids (``len``, indexing, slicing, iteration, ``in``, ``==`` with a list)
    without building one, since a Python list of millions of ids costs more than the query itself.
    ``np.asarray(ids)`` is the array (no copy), ``ids.tolist()`` the list (e.g. for JSON).
    """

    __slots__ = ("_ids",)
    __hash__ = None  # compares by value, as a list does

    def __init__(self, ids) -> None:
        self._ids = np.asarray(ids, np.int64).reshape(-1)
        self._ids.flags.writeable = False

    def __len__(self) -> int:
        return int(self._ids.shape[0])

    def __getitem__(self, i):
        if isinstance(i, slice):
            return FrameIds(self._ids[i])
        return int(self._ids[i])

    def __iter__(self):
        return iter(self._ids.tolist())

    def __contains__(self, value) -> bool:
        return isinstance(value, numbers.Real) and bool((self._ids == value).any())

    def __eq__(self, other) -> bool:
        if isinstance(other, FrameIds):
            return bool(np.array_equal(self._ids, other._ids))
        if isinstance(other, list):
            return len(other) == len(self) and self._ids.tolist() == other
        return NotImplemented

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        if copy:
            return np.array(self._ids, dtype=dtype)
        if dtype is None or np.dtype(dtype) == self._ids.dtype:
            return self._ids
        if copy is False:
            raise ValueError(f"frame ids are int64: no {np.dtype(dtype)} array of them without a copy")
        return self._ids.astype(dtype)

    def tolist(self) -> list[int]:
        return self._ids.tolist()

    def __repr__(self) -> str:
        shown = ", ".join(str(v) for v in self._ids[:10].tolist())
        return f"FrameIds([{shown}{', ...' if len(self) > 10 else ''}], {len(self)} frames)"


class FrameIndex:
    """An index folder, open for queries (see the module docstring for its layout).

    Open one with :meth:`open`, make one with :meth:`create`, add frames or sources with :meth:`append`.
    """

    #: an index whose Parquet parts hold at least this many bytes is queried from ``index.duckdb``: DuckDB
    #: tables made from the parts, rebuilt by :meth:`open` when they changed; a smaller one reads its parts
    STORE_MIN_BYTES = 4 << 20

    def __init__(self, root: Path, meta: dict):
        import duckdb

        self.root = root
        self.meta = meta
        # in memory: only the views counts and centres, over index.duckdb (attached read-only) and Parquet
        self.con = duckdb.connect()
        self._views(refresh=True)

    # ---------------------------------------------------------------- making and opening
    @classmethod
    def create(cls, root: "str | os.PathLike", counts=None, centres=None, source: str = "labels",
               classes: Sequence[str] | None = None) -> "FrameIndex":
        """A new index at ``root`` (refused if one is there) holding ``counts`` of ``source``.

        Args:
            counts: a table (pandas DataFrame, pyarrow Table or dict of columns) with ``frame_id`` (integers,
                unique), optional ``sequence`` (str), ``timestamp`` (float, seconds) and ``path`` (str, where
                the frame's points are), and one column of non-negative integer counts per class; or None for
                an index without frames yet (``classes`` then required).
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
        cols = _columns(counts) if counts is not None else None
        if classes is None:
            if cols is None:
                raise QueryError("an index without counts needs its classes: FrameIndex.create(root, classes=[...])")
            classes = [c for c in cols if c not in _META_COLUMNS]
        classes = [_name(c, "a class name") for c in classes]
        if not classes:
            raise QueryError("counts has no class column (one integer column per class besides frame_id)")
        if len(set(classes)) != len(classes):
            raise QueryError(f"classes must be distinct, got {classes}")
        root.mkdir(parents=True, exist_ok=True)
        meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "classes": list(classes), "sources": {}}
        index = cls.__new__(cls)
        index.root, index.meta = root, meta
        if cols is not None:
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

    def add_source(self, source: str, centres: bool = True) -> None:
        """Declares ``source`` (with or without object centres) before any of its frames: what a build run
        by several processes does once, on rank 0, so that no other process rewrites ``index.json``."""
        entry = self.meta["sources"].setdefault(_name(source, "source"), {"centres": bool(centres)})
        if entry.get("centres") != bool(centres):
            raise QueryError(f"source {source!r} is already declared {'with' if entry.get('centres') else 'without'} "
                             "object centres")
        self._save_meta()

    def frame_count(self, source: str = "labels") -> int:
        """How many frames ``source`` holds."""
        self._frame_source(source, None, None)  # checks the name
        return int(self.con.execute("SELECT count(*) FROM counts WHERE source = ?", [source]).fetchone()[0])

    def held_frames(self, source: str) -> np.ndarray:
        """The frame ids ``source`` holds (int64, ascending; empty for a source not in the index)."""
        if source not in self.meta["sources"] or not any((self.root / "counts" / source).glob("*.parquet")):
            return np.zeros(0, np.int64)
        rows = self.con.execute("SELECT frame_id FROM counts WHERE source = ? ORDER BY frame_id", [source]).fetchnumpy()
        return np.asarray(rows["frame_id"], np.int64)

    # ---------------------------------------------------------------- queries
    @property
    def classes(self) -> list[str]:
        return list(self.meta["classes"])

    @property
    def sources(self) -> list[str]:
        return sorted(self.meta["sources"])

    def retrieve(self, where: Mapping[str, tuple], frames=None, source: str = "labels",
                 region: Sequence[float] | None = None) -> FrameIds:
        """RETRIEVAL: the ids (ascending) of the frames whose counts meet every condition, as
        :class:`FrameIds` (a sequence of ints that equals the list of those ids; ``np.asarray(ids)`` is
        the int64 array, ``ids.tolist()`` the list).

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
        # a relation through Arrow, quicker than fetchnumpy for millions of ids (DuckDB 2: to_arrow_table,
        # 1.x: arrow); on a cursor, since DuckDB 2 runs none while the connection holds an unfinished result
        cursor = self.con.cursor()
        try:
            answer = cursor.sql(f"{sql} SELECT frame_id FROM f WHERE {where_sql}", params=base + params)
            table = answer.to_arrow_table() if hasattr(answer, "to_arrow_table") else answer.arrow()
        finally:
            cursor.close()
        ids = np.asarray(table.column(0).to_numpy(), np.int64)
        # no ORDER BY: index.duckdb's rows are in frame order and a filter keeps it (DuckDB preserves
        # insertion order), so an answer from it comes sorted; a check costs less than DuckDB's sort
        if ids.size > 1 and not (ids[1:] > ids[:-1]).all():
            ids = np.sort(ids)
        return FrameIds(ids)

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

    def compare(self, kind: str, *args, **kwargs) -> dict[str, Any]:
        """One query's answer from every source of the index, ``{source: answer}``, labels first: e.g.
        ``idx.compare("count", "Car", ">=", 5, region=(0, -10, 40, 10))``.

        Args:
            kind: ``"retrieve"``, ``"count"``, ``"sum"`` or ``"avg"``; the other arguments are that
                method's, without ``source``.
        """
        if kind not in ("retrieve", "count", "sum", "avg"):
            raise QueryError(f"kind must be one of retrieve, count, sum, avg, got {kind!r}")
        if "source" in kwargs:
            raise QueryError("compare asks every source: leave source out")
        order = sorted(self.sources, key=lambda s: (s != "labels", s))
        return {source: getattr(self, kind)(*args, source=source, **kwargs) for source in order}

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
        # x and y are float32: compared with the least float32 >= each bound, the answer is that of the exact
        # comparison, and DuckDB compares the column as stored (no cast per row, row groups skipped by their range)
        x0, y0, x1, y1 = (_float32_ceil(v) for v in (x0, y0, x1, y1))
        counted = ", ".join(f'count(*) FILTER (WHERE class = \'{c}\') AS "{c}"' for c in self.meta["classes"])
        picked = ", ".join(f'coalesce(r."{c}", 0) AS "{c}"' for c in self.meta["classes"])
        sql = (f"WITH r AS (SELECT frame_id, {counted} FROM centres WHERE source = ? AND x >= ?::FLOAT AND "
               f"x < ?::FLOAT AND y >= ?::FLOAT AND y < ?::FLOAT GROUP BY frame_id), "
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
        return " AND frame_id IN (SELECT unnest(?::BIGINT[]))", [ids]  # a hash semi-join (list_contains scans per row)

    def _views(self, refresh: bool = False) -> None:
        """(Re)makes the views ``counts`` and ``centres``: the tables of ``index.duckdb`` for the parts it was
        made from, and the Parquet parts it lacks (appended since). ``refresh`` (open) first rebuilds an
        ``index.duckdb`` that lacks parts or is out of date; an index under ``STORE_MIN_BYTES``, or in a folder
        that cannot be written, reads all its parts."""
        parts = {}
        for kind in ("counts", "centres"):
            files = sorted((self.root / kind).glob("*/*.parquet"))
            if kind == "centres":  # a part's centres count once its counts landed (a kill in between leaves them)
                files = [f for f in files if (self.root / "counts" / f.parent.name / f.name).is_file()]
            parts[kind] = files
        stored = self._store(parts, refresh)
        for kind, files in parts.items():
            selects = [f"SELECT * FROM store.{kind}"] if any(f in stored for f in files) else []
            tail = [f for f in files if f not in stored]
            if tail:  # a view cannot take parameters: the paths go in as quoted literals
                selects.append(f"SELECT * FROM read_parquet([{', '.join(map(_literal, tail))}], union_by_name=true)")
            if selects:
                self.con.execute(f"CREATE OR REPLACE VIEW {kind} AS {' UNION ALL BY NAME '.join(selects)}")
            elif kind == "counts":
                classes = ", ".join(f'NULL::INTEGER AS "{c}"' for c in self.meta["classes"])
                self.con.execute("CREATE OR REPLACE VIEW counts AS SELECT NULL::VARCHAR AS source, NULL::BIGINT AS "
                                 "frame_id, NULL::VARCHAR AS sequence, NULL::DOUBLE AS timestamp, NULL::VARCHAR AS "
                                 f"path, NULL::VARCHAR AS model, {classes} WHERE FALSE")
            else:
                self.con.execute("CREATE OR REPLACE VIEW centres AS SELECT NULL::VARCHAR AS source, NULL::BIGINT AS "
                                 "frame_id, NULL::VARCHAR AS class, NULL::FLOAT AS x, NULL::FLOAT AS y, "
                                 "NULL::FLOAT AS score WHERE FALSE")

    def _store(self, parts: dict[str, list[Path]], refresh: bool) -> set[Path]:
        """Attaches ``index.duckdb`` (read-only, as ``store``) when it is up to date for the parts it holds,
        rebuilding it first with ``refresh`` when it is not or lacks some; returns the parts it holds."""
        import duckdb

        self.con.execute("DETACH DATABASE IF EXISTS store")
        files = [f for kind in ("counts", "centres") for f in parts[kind]]
        try:  # a part is the same part while its size and modification time are
            stamps = {f: (st.st_size, st.st_mtime_ns) for f in files for st in [f.stat()]}
        except OSError:  # a part removed meanwhile: read the parts
            return set()
        if sum(size for size, _ in stamps.values()) < self.STORE_MIN_BYTES:
            return set()
        path = self.root / STORE_FILE
        held = self._attach_store(path)
        if refresh and held != {f.relative_to(self.root).as_posix(): s for f, s in stamps.items()}:
            self.con.execute("DETACH DATABASE IF EXISTS store")
            tmp = self.root / f".{STORE_FILE}.{os.getpid()}.tmp"
            try:
                self._build_store(tmp, parts, stamps)
                os.replace(tmp, path)  # readers holding the old file keep reading it
            except (OSError, duckdb.Error):  # a read-only folder, a full disk: the parts are read directly
                return set()
            finally:
                for leftover in (tmp, tmp.with_name(tmp.name + ".wal")):
                    leftover.unlink(missing_ok=True)
            held = self._attach_store(path)
        current = {f.relative_to(self.root).as_posix(): (f, s) for f, s in stamps.items()}
        if held is None or any(name not in current or current[name][1] != s for name, s in held.items()):
            self.con.execute("DETACH DATABASE IF EXISTS store")
            return set()
        return {current[name][0] for name in held}

    def _attach_store(self, path: Path) -> dict[str, tuple[int, int]] | None:
        """The parts ``index.duckdb`` holds, ``{relative path: (bytes, mtime_ns)}``, attached as ``store``; None
        if there is none or it is unreadable (of another version, or another DuckDB's)."""
        import duckdb

        if not path.is_file():
            return None
        try:
            self.con.execute(f"ATTACH {_literal(path)} AS store (READ_ONLY)")
            rows = self.con.execute(f"SELECT part, bytes, mtime_ns FROM store.{STORE_PARTS}").fetchall()
        except duckdb.Error:
            self.con.execute("DETACH DATABASE IF EXISTS store")
            return None
        return {part: (int(size), int(mtime)) for part, size, mtime in rows}

    def _build_store(self, path: Path, parts: dict[str, list[Path]], stamps: dict[Path, tuple[int, int]]) -> None:
        """Writes ``index.duckdb`` at ``path``: each kind's parts as one table, and the parts' stamps. Counts are
        in (source, frame_id) order: DuckDB's row-group statistics skip other sources and frames outside a
        range, and retrieve's ids come out ascending."""
        import duckdb

        con = duckdb.connect(str(path))
        try:
            for kind, files in parts.items():
                if files:
                    listed = ", ".join(map(_literal, files))
                    # centres in 8 m stripes of x, by y within: a region reads the row groups it overlaps
                    order = "source, frame_id" if kind == "counts" else "source, floor(x / 8), y"
                    con.execute(f"CREATE TABLE {kind} AS SELECT * FROM read_parquet([{listed}], union_by_name=true) "
                                f"ORDER BY {order}")
            con.execute(f"CREATE TABLE {STORE_PARTS} (part VARCHAR, bytes BIGINT, mtime_ns BIGINT)")
            con.executemany(f"INSERT INTO {STORE_PARTS} VALUES (?, ?, ?)",
                            [[f.relative_to(self.root).as_posix(), *s] for f, s in stamps.items()])
        finally:
            con.close()

    def _save_meta(self) -> None:
        tmp = self.root / "index.json.tmp"
        tmp.write_text(json.dumps(self.meta, indent=1) + "\n")
        os.replace(tmp, self.root / "index.json")

    def _write(self, cols: dict[str, np.ndarray], centres, source: str, writer: str = "",
               check_held: bool = True) -> None:
        """Writes one part of ``source`` (counts, and centres when given). ``writer`` tags the part's name so
        that processes building one index side by side never pick the same name; ``check_held=False`` is
        for a builder that has already left out the frames the source holds."""
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
        unknown = [c for c in cols if c not in _META_COLUMNS and c not in classes]
        if unknown:
            raise QueryError(f"counts has columns of classes the index does not hold: {unknown}; its classes: "
                             f"{', '.join(classes)}")
        existing = self.meta["sources"].get(source)
        if check_held and existing and hasattr(self, "con"):
            held = self.con.execute("SELECT frame_id FROM counts WHERE source = ? AND frame_id IN (SELECT unnest(?::BIGINT[])) "
                                    "ORDER BY frame_id LIMIT 5", [source, frame_id.tolist()]).fetchall()
            if held:
                raise QueryError(f"source {source!r} already holds frames {[int(r[0]) for r in held]}: an index holds "
                                 "each frame once per source")
        table = {"source": pa.array([source] * n, pa.string()), "frame_id": pa.array(frame_id, pa.int64()),
                 "sequence": pa.array([None if v is None else str(v) for v in cols["sequence"]], pa.string())
                 if "sequence" in cols else pa.nulls(n, pa.string()),
                 "timestamp": pa.array(np.asarray(cols["timestamp"], np.float64), from_pandas=True) if "timestamp" in cols
                 else pa.nulls(n, pa.float64()),
                 "path": pa.array([None if v is None else str(v) for v in cols["path"]], pa.string())
                 if "path" in cols else pa.nulls(n, pa.string()),
                 # the member of a model selection that counted the frame (SelectedCounter); null otherwise
                 "model": pa.array([None if v is None else str(v) for v in cols["model"]], pa.string())
                 if "model" in cols else pa.nulls(n, pa.string())}
        for c in classes:
            values = _int_column(cols[c], f"counts' column {c}", minimum=0).reshape(-1) if c in cols \
                else np.zeros(n, np.int64)
            if values.shape[0] != n:
                raise QueryError(f"counts' column {c} has {values.shape[0]} rows, frame_id has {n}")
            table[c] = pa.array(values.astype(np.int32), pa.int32())
        if not _WRITER.match(writer):
            raise QueryError(f"writer must be lowercase letters and digits, got {writer!r}")
        prefix = f"part-{writer}-" if writer else "part-"
        taken = [p.name[len(prefix):-len(".parquet")] for p in (self.root / "counts" / source).glob(f"{prefix}*.parquet")]
        part = 1 + max((int(t) for t in taken if t.isdigit()), default=-1)
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
        for kind, data in (("centres", centre_table), ("counts", table)):
            if data is None:
                continue
            folder = self.root / kind / source
            folder.mkdir(parents=True, exist_ok=True)
            tmp = folder / f".{prefix}{part:05d}.parquet.tmp"
            pq.write_table(pa.table(data), tmp)
            # centres first, counts last: a part's frames count as held once their counts are there
            os.replace(tmp, folder / f"{prefix}{part:05d}.parquet")  # a reader never sees half a part
        entry = self.meta["sources"].setdefault(source, {"centres": has_centres})
        entry["centres"] = has_centres
