"""The answer page of a query: one self-contained HTML file (no network, no external script, style or font)
with the query, the answer, a table of per-class counts of the shown frames (a source beside the truth
where the truth is indexed), and an inline-SVG bird's-eye view of each shown frame: the source's counted
centres (filled), the truth's (rings), the query's region, a metre grid and, when given, the frame's
points (light grey)::

    from lidarops.query.page import answer_page, points_from_index
    ids = idx.retrieve({"Car": (">=", 10)}, source="detector")
    answer_page(idx, "answer.html", kind="retrieve", query_text="Car>=10", answer=ids, frame_ids=ids,
                source="detector", points_of=points_from_index(idx, ids[:24], source="detector"))

The pictures follow the sensor's frame: x ahead is up, y left is left, one scale for every picture. The
page reads the index through two SQL statements (counts, centres), each restricted to the shown frames,
and is readable without JavaScript (a few lines of it show the metre coordinates under the mouse).
"""
from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lidarops.query.index import FrameIndex, QueryError

__all__ = ["answer_page", "points_from_index", "KINDS"]

#: the query kinds a page answers
KINDS = ("retrieve", "count", "sum", "avg")
#: one colour per class, in the index's class order (tab10 without its grey, which the points use)
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf")
MAX_POINTS = 1500   # points drawn per picture (after clipping to the picture), a few KB each
MAX_IDS = 1000      # frame ids listed in a RETRIEVAL answer
PICTURE = 340       # pixels along a picture's longer side
_MARGIN = (30, 8, 8, 20)  # left (x labels), top, right, bottom (y labels)
_REGION_MARK = '<rect x="2" y="3" width="12" height="10" class="reg"/>'
_POINT_MARK = '<circle cx="8" cy="8" r="1.5" fill="#a9a9a9"/>'
_SENSOR_MARK = '<path d="M8 3 L12 13 L4 13 Z" class="sensor"/>'


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _num(value: float) -> str:
    """A short coordinate: at most one decimal, no trailing zeros."""
    text = f"{value:.1f}"
    return text[:-2] if text.endswith(".0") else text


def answer_page(index: FrameIndex, path: "str | os.PathLike", *, kind: str, query_text: str, answer: Any,
                frame_ids: Sequence[int] = (), source: str = "labels", truth: str | None = "labels",
                max_frames: int = 24, points_of: Callable[[int], Any] | None = None,
                region: Sequence[float] | None = None, truth_answer: Any = None) -> Path:
    """Writes the answer page of one query and returns its path.

    Args:
        index: the index the query ran on.
        path: the HTML file to write (its folder is made).
        kind: ``retrieve``, ``count``, ``sum`` or ``avg``.
        query_text: the query as the user wrote it (shown escaped).
        answer: the answer: a list of frame ids (``retrieve``), an int (``count``, ``sum``), a float or
            None (``avg`` over no frames).
        frame_ids: the frames to show (e.g. the retrieved ones); the first ``max_frames`` are shown.
        source: whose counts and centres the query used.
        truth: the source put beside it (rings, a second column), when the index holds it and it is not
            ``source``; None for none.
        max_frames: frames shown at most (table rows and pictures).
        points_of: optional ``points_of(frame_id) -> array (N, >= 2)`` (x, y first, metres) or None; its
            points are drawn subsampled (:data:`MAX_POINTS`), e.g. :func:`points_from_index`.
        region: the query's ``(x0, y0, x1, y1)`` in metres: drawn, and the table then counts the objects
            inside it (as the query did).
        truth_answer: optional, the truth's answer to the same query, shown beside ``answer``.

    Raises:
        QueryError: an unknown kind or source, a bad region or frame list, a region with a source that
            has no centres.
    """
    if kind not in KINDS:
        raise QueryError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if source not in index.sources:
        raise QueryError(f"unknown source {source!r}; the index's sources: {', '.join(index.sources)}")
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 0:
        raise QueryError(f"max_frames must be an integer >= 0, got {max_frames!r}")
    if points_of is not None and not callable(points_of):
        raise QueryError(f"points_of must be a callable frame_id -> points or None, got {type(points_of).__name__}")
    try:
        all_ids = [int(f) for f in frame_ids]
    except (TypeError, ValueError):
        raise QueryError(f"frame_ids must be integers, got {frame_ids!r}") from None
    all_ids = list(dict.fromkeys(all_ids))
    shown = all_ids[:max_frames]
    answer = _checked_answer(kind, answer, "answer")
    truth_answer = None if truth_answer is None else _checked_answer(kind, truth_answer, "truth_answer")
    notes = []
    if truth is not None and (truth == source or truth not in index.sources):
        if truth != source:
            notes.append(f"the truth {truth!r} is not in this index: {source}'s counts are shown alone")
        truth = None
    if region is not None:
        region = _region(region)
        with_centres = {s for s, e in index.meta["sources"].items() if e.get("centres")}
        if source not in with_centres:
            raise QueryError(f"source {source!r} has no object centres: a region needs them")
        if truth is not None and truth not in with_centres:
            notes.append(f"{truth} has no object centres, so no counts inside the region: {source}'s are shown alone")
            truth = None
    sources = [source] + ([truth] if truth else [])
    notes += [f"{s} has no stored object centres: its objects are counted, not drawn" for s in sources
              if not index.meta["sources"][s].get("centres")]
    classes = index.classes
    counts = _counts(index, sources, shown, classes, region)
    centres = _centres(index, sources, shown)
    points = {}
    if points_of is not None:
        for fid in shown:
            p = points_of(fid)
            if p is not None:
                p = np.asarray(p, dtype=np.float64)
                if p.ndim != 2 or p.shape[1] < 2:
                    raise QueryError(f"points_of({fid}) must return an array (N, >= 2) or None, got shape {p.shape}")
                points[fid] = p[:, :2]
    extent = _extent(centres, region)
    colour = {c: PALETTE[i % len(PALETTE)] for i, c in enumerate(classes)}
    body = [
        _header(index, kind, query_text, source, truth, region, len(all_ids), len(shown), notes),
        _answer(kind, answer, source, truth, truth_answer),
        _legend(classes, colour, source, truth, region is not None, bool(points), _grid_step(extent)),
        _table(shown, classes, counts, source, truth, region is not None),
        _pictures(shown, classes, colour, counts, centres, points, extent, source, truth, region),
    ]
    page = _document(query_text, classes, colour, "\n".join(body))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
    return path


def points_from_index(index: FrameIndex, frame_ids: Sequence[int], source: str = "labels"
                      ) -> Callable[[int], np.ndarray | None] | None:
    """A ``points_of`` for :func:`answer_page` reading each frame's scan from the ``path`` column of the
    index's counts (KITTI ``.bin``: float32 ``(N, 4)``), or None where no shown frame has a path (e.g.
    simulated frames, or an index written before the column existed).

    A relative path is taken from the current folder, else from the index's folder; a missing file gives
    no points (the picture shows the centres alone); a file whose size is not a whole number of float32
    ``(x, y, z, intensity)`` rows raises ``QueryError`` naming it.
    """
    ids = [int(f) for f in frame_ids]
    if not ids or "path" not in index.sql("SELECT * FROM counts LIMIT 0").columns:
        return None
    rows = index.sql("SELECT frame_id, any_value(path) AS path FROM counts WHERE source = ? AND path IS NOT NULL "
                     "AND list_contains(?::BIGINT[], frame_id) GROUP BY frame_id", [source, ids])
    paths = {int(f): str(p) for f, p in zip(rows["frame_id"], rows["path"])}
    if not paths:
        return None
    root = Path(index.root)

    def points_of(frame_id: int) -> np.ndarray | None:
        name = paths.get(int(frame_id))
        if name is None:
            return None
        file = Path(name)
        if not file.is_file() and not file.is_absolute():
            file = root / name
        if not file.is_file():
            return None
        raw = np.fromfile(file, dtype=np.float32)
        if raw.size % 4:
            raise QueryError(f"{file}: {raw.size} float32 values, not (N, 4) rows of x, y, z, intensity")
        return raw.reshape(-1, 4)

    return points_of


# ---------------------------------------------------------------------------------------------- reading
def _checked_answer(kind, answer, what):
    """A retrieve answer as a list of ints; any other as the number (or None) it is."""
    if kind == "retrieve":
        try:
            return [int(a) for a in ([] if answer is None else answer)]
        except (TypeError, ValueError):
            raise QueryError(f"{what} of a retrieve must be a list of frame ids, got {answer!r}") from None
    if answer is not None and (isinstance(answer, (str, bytes)) or not np.isscalar(answer) and np.ndim(answer)):
        raise QueryError(f"{what} of a {kind} must be a number or None, got {answer!r}")
    return answer


def _region(region) -> tuple[float, float, float, float]:
    try:
        x0, y0, x1, y1 = (float(v) for v in region)
    except (TypeError, ValueError):
        raise QueryError(f"region must be (x0, y0, x1, y1) in metres, got {region!r}") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)) or not (x0 < x1 and y0 < y1):
        raise QueryError(f"region must be finite with x0 < x1 and y0 < y1, got {tuple(region)}")
    return x0, y0, x1, y1


def _counts(index, sources, shown, classes, region) -> dict[tuple[str, int], dict[str, int]]:
    """{(source, frame_id): {class: count}} of the shown frames: one statement, inside ``region`` if given."""
    if not shown:
        return {}
    if region is None:
        picked = ", ".join(f'coalesce("{c}", 0) AS "{c}"' for c in classes)  # a source may lack a class
        rows = index.sql(f"SELECT source, frame_id, {picked} FROM counts WHERE list_contains(?::VARCHAR[], source) "
                         "AND list_contains(?::BIGINT[], frame_id)", [sources, shown])
    else:
        x0, y0, x1, y1 = region
        counted = ", ".join(f'count(c.class) FILTER (WHERE c.class = ?) AS "{c}"' for c in classes)
        rows = index.sql(f"SELECT k.source, k.frame_id, {counted} FROM counts k LEFT JOIN centres c ON "
                         "c.source = k.source AND c.frame_id = k.frame_id AND c.x >= ? AND c.x < ? AND c.y >= ? "
                         "AND c.y < ? WHERE list_contains(?::VARCHAR[], k.source) AND list_contains(?::BIGINT[], "
                         "k.frame_id) GROUP BY k.source, k.frame_id", list(classes) + [x0, x1, y0, y1, sources, shown])
    return {(str(r["source"]), int(r["frame_id"])): {c: int(r[c]) for c in classes} for r in rows.to_dict("records")}


def _centres(index, sources, shown) -> dict[tuple[str, int], list[tuple[str, float, float, float | None]]]:
    """{(source, frame_id): [(class, x, y, score), ...]} of the shown frames, one statement."""
    out: dict = {}
    if not shown:
        return out
    rows = index.sql("SELECT source, frame_id, class, x, y, score FROM centres WHERE list_contains(?::VARCHAR[], "
                     "source) AND list_contains(?::BIGINT[], frame_id) ORDER BY frame_id, source, class, x, y",
                     [sources, shown])
    for s, f, c, x, y, score in rows.itertuples(index=False):
        score = None if score is None or not math.isfinite(score) else float(score)
        out.setdefault((str(s), int(f)), []).append((str(c), float(x), float(y), score))
    return out


# ---------------------------------------------------------------------------------------------- geometry
def _extent(centres, region) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) in metres, shared by every picture: the sensor, the centres and the
    region, with a margin, rounded out to 5 m and never much narrower than tall (nor the other way)."""
    xs, ys = [0.0, 20.0], [-10.0, 10.0]  # the sensor and a little in front of it
    for rows in centres.values():
        xs += [r[1] for r in rows]
        ys += [r[2] for r in rows]
    if region is not None:
        xs += [region[0], region[2]]
        ys += [region[1], region[3]]
    x0, x1 = math.floor((min(xs) - 4) / 5) * 5, math.ceil((max(xs) + 4) / 5) * 5
    y0, y1 = math.floor((min(ys) - 4) / 5) * 5, math.ceil((max(ys) + 4) / 5) * 5
    span = max(x1 - x0, y1 - y0)  # widen the short side to at least 0.6 of the long one, centred
    if x1 - x0 < 0.6 * span:
        grow = math.ceil((0.6 * span - (x1 - x0)) / 10) * 5
        x0, x1 = x0 - grow, x1 + grow
    if y1 - y0 < 0.6 * span:
        grow = math.ceil((0.6 * span - (y1 - y0)) / 10) * 5
        y0, y1 = y0 - grow, y1 + grow
    return float(x0), float(x1), float(y0), float(y1)


def _grid_step(extent) -> int:
    span = max(extent[1] - extent[0], extent[3] - extent[2])
    for step in (5, 10, 20, 25, 50, 100, 200, 500):
        if span / step <= 8:
            return step
    return 1000


# ---------------------------------------------------------------------------------------------- HTML
def _document(query_text: str, classes, colour, body: str) -> str:
    styles = "\n".join(f".s{i}{{fill:{colour[c]}}} .t{i}{{stroke:{colour[c]}}}" for i, c in enumerate(classes))
    return f"""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>lidarops query: {_e(query_text)}</title>
<style>
body {{ font: 14px/1.4 system-ui, sans-serif; margin: 1.5em; color: #222; background: #fff; }}
h1 {{ font-size: 1.4em; margin: 0 0 .3em; }} h2 {{ font-size: 1.1em; margin: 1.2em 0 .4em; }}
code {{ background: #f3f3f3; padding: 0 .3em; border-radius: 3px; }}
.facts {{ color: #555; margin: .2em 0; }} .note {{ color: #8a5a00; }}
.answer {{ font-size: 1.25em; }} .ids {{ font-family: monospace; font-size: .85em; word-break: break-word; }}
table {{ border-collapse: collapse; font-variant-numeric: tabular-nums; }}
th, td {{ border: 1px solid #ddd; padding: 2px 8px; text-align: right; }} th {{ background: #f6f6f6; }}
td.diff {{ background: #fde8e8; }} td.fid {{ text-align: left; }}
.frames {{ display: flex; flex-wrap: wrap; gap: 12px; }}
figure {{ margin: 0; border: 1px solid #ddd; padding: 6px; }}
figcaption {{ font-size: 12px; color: #333; }} .xy {{ font-size: 12px; color: #777; min-height: 1.2em; }}
svg.bev {{ display: block; background: #fcfcfc; }}
.grid {{ stroke: #e4e4e4; stroke-width: 1; }} .axis {{ stroke: #bbb; stroke-width: 1; }}
.lab {{ font-size: 9px; fill: #888; }} .pts {{ stroke: #a9a9a9; stroke-width: 1.4; stroke-linecap: round; fill: none; }}
.reg {{ fill: rgba(255, 200, 0, .08); stroke: #c89600; stroke-width: 1.5; stroke-dasharray: 5 3; }}
.ring {{ fill: none; stroke-width: 1.5; }} .out {{ opacity: .35; }} .sensor {{ fill: #444; }}
.legend span {{ margin-right: 1.2em; white-space: nowrap; }} .legend svg {{ vertical-align: middle; }}
{styles}
</style>
</head>
<body>
{body}
<script>
// the metre coordinates under the mouse, in each picture's caption
document.querySelectorAll("svg.bev").forEach(function (svg) {{
  var out = svg.parentNode.querySelector(".xy");
  if (!out) return;
  svg.addEventListener("mousemove", function (e) {{
    var r = svg.getBoundingClientRect(), k = svg.viewBox.baseVal.width / r.width, d = svg.dataset;
    var px = (e.clientX - r.left) * k - Number(d.left), py = (e.clientY - r.top) * k - Number(d.top);
    var x = Number(d.xmax) - py * Number(d.mpp), y = Number(d.ymax) - px * Number(d.mpp);
    out.textContent = "x " + x.toFixed(1) + " m, y " + y.toFixed(1) + " m";
  }});
  svg.addEventListener("mouseleave", function () {{ out.textContent = ""; }});
}});
</script>
</body>
</html>
"""


def _header(index, kind, query_text, source, truth, region, total, shown, notes) -> str:
    facts = [f"index <code>{_e(index.root)}</code>", f"kind <b>{_e(kind)}</b>", f"source <b>{_e(source)}</b>"]
    if truth:
        facts.append(f"beside the truth <b>{_e(truth)}</b>")
    if region is not None:
        x0, y0, x1, y1 = (_num(v) for v in region)
        facts.append(f"region x &isin; [{x0}, {x1}) m, y &isin; [{y0}, {y1}) m")
    facts.append(f"{shown} of {total} frame(s) shown")
    out = [f"<h1>Query: <code>{_e(query_text)}</code></h1>", f'<p class="facts">{" &middot; ".join(facts)}</p>']
    out += [f'<p class="note">{_e(n)}</p>' for n in notes]
    return "\n".join(out)


def _answer_text(kind, answer) -> str:
    if kind == "retrieve":
        ids = [int(a) for a in answer or []]
        if not ids:
            return '<span class="answer">No frame meets the query.</span>'
        listed = ", ".join(str(i) for i in ids[:MAX_IDS])
        if len(ids) > MAX_IDS:
            listed += f", &hellip; and {len(ids) - MAX_IDS} more"
        return f'<span class="answer">{len(ids)} frame(s)</span><div class="ids">{listed}</div>'
    if answer is None:
        return '<span class="answer">No frames to aggregate over.</span>'
    if kind == "avg":
        return f'<span class="answer">{_e(f"{float(answer):.4g}")}</span> per frame'
    return f'<span class="answer">{_e(int(answer))}</span>' + (" frame(s)" if kind == "count" else "")


def _answer(kind, answer, source, truth, truth_answer) -> str:
    out = ['<section id="answer"><h2>Answer</h2>', f"<p>{_e(source)}: {_answer_text(kind, answer)}</p>"]
    if truth_answer is not None:
        out.append(f"<p>{_e(truth or 'truth')}: {_answer_text(kind, truth_answer)}</p>")
    out.append("</section>")
    return "\n".join(out)


def _legend(classes, colour, source, truth, region, points, step) -> str:
    def swatch(inner: str) -> str:
        return f'<svg width="16" height="16" viewBox="0 0 16 16" aria-hidden="true">{inner}</svg>'

    items = []
    for i, c in enumerate(classes):
        mark = f'<circle cx="8" cy="8" r="3.5" class="s{i}"/>'
        if truth:
            mark += f'<circle cx="8" cy="8" r="6" class="ring t{i}"/>'
        items.append(f"<span>{swatch(mark)} {_e(c)}</span>")
    keys = [f"filled: {_e(source)}"] + ([f"ring: {_e(truth)}"] if truth else [])
    keys += [f"grid: every {step} m", "hover a marker for its place"]
    if region:
        items.append(f"<span>{swatch(_REGION_MARK)} region (faded: outside it)</span>")
    if points:
        items.append(f"<span>{swatch(_POINT_MARK)} points</span>")
    items.append(f"<span>{swatch(_SENSOR_MARK)} sensor (x ahead: up, y left: left)</span>")
    return (f'<section id="legend" class="legend"><h2>Legend</h2><p>{"".join(items)}</p>'
            f'<p class="facts">{" &middot; ".join(keys)}</p></section>')


def _table(shown, classes, counts, source, truth, region) -> str:
    if not shown:
        return '<section id="counts"><h2>Per-class counts</h2><p>No frames to show.</p></section>'
    cols = [source] + ([truth] if truth else [])
    if truth:  # a class's columns: the source, the truth
        head = '<tr><th rowspan="2">frame</th>' + "".join(f'<th colspan="2">{_e(c)}</th>' for c in classes)
        head += "</tr><tr>" + "".join(f"<th>{_e(s)}</th>" for _ in classes for s in cols) + "</tr>"
    else:
        head = "<tr><th>frame</th>" + "".join(f"<th>{_e(c)}</th>" for c in classes) + "</tr>"
    rows = []
    for fid in shown:
        cells = [f'<td class="fid"><a href="#frame-{fid}">{fid}</a></td>']
        for c in classes:
            got = [counts.get((s, fid), {}).get(c) for s in cols]
            diff = truth is not None and None not in got and got[0] != got[1]
            for v in got:
                cells.append(f'<td{" class=diff" if diff else ""}>{"&ndash;" if v is None else v}</td>')
        rows.append(f'<tr id="row-{fid}">{"".join(cells)}</tr>')
    caption = f"Objects per class{' inside the region' if region else ''} in each shown frame"
    if truth:
        caption += f" ({_e(source)} beside {_e(truth)}; shaded: they differ)"
    caption += ". &ndash;: the source does not hold the frame."
    return (f'<section id="counts"><h2>Per-class counts</h2><table><thead>{head}</thead>'
            f'<tbody>{"".join(rows)}</tbody></table><p class="facts">{caption}</p></section>')


def _pictures(shown, classes, colour, counts, centres, points, extent, source, truth, region) -> str:
    if not shown:
        return '<section id="frames"><h2>Bird&rsquo;s-eye views</h2><p>No frames to show.</p></section>'
    figures = "".join(_picture(fid, classes, counts, centres, points.get(fid), extent, source, truth, region)
                      for fid in shown)
    return f'<section id="frames"><h2>Bird&rsquo;s-eye views</h2><div class="frames">{figures}</div></section>'


def _picture(fid, classes, counts, centres, pts, extent, source, truth, region) -> str:
    x_min, x_max, y_min, y_max = extent
    mpp = max(x_max - x_min, y_max - y_min) / PICTURE  # metres per pixel
    left, top, right, bottom = _MARGIN
    w, h = (y_max - y_min) / mpp, (x_max - x_min) / mpp

    def px(y):  # y left -> left on the picture
        return left + (y_max - y) / mpp

    def py(x):  # x ahead -> up
        return top + (x_max - x) / mpp

    parts = []
    step = _grid_step(extent)
    for gx in range(math.ceil(x_min / step) * step, math.floor(x_max / step) * step + 1, step):
        parts.append(f'<line x1="{_num(left)}" y1="{_num(py(gx))}" x2="{_num(left + w)}" y2="{_num(py(gx))}" '
                     f'class="{"axis" if gx == 0 else "grid"}"/><text x="{left - 3}" y="{_num(py(gx) + 3)}" '
                     f'class="lab" text-anchor="end">{gx}</text>')
    for gy in range(math.ceil(y_min / step) * step, math.floor(y_max / step) * step + 1, step):
        parts.append(f'<line x1="{_num(px(gy))}" y1="{top}" x2="{_num(px(gy))}" y2="{_num(top + h)}" '
                     f'class="{"axis" if gy == 0 else "grid"}"/><text x="{_num(px(gy))}" y="{_num(top + h + 12)}" '
                     f'class="lab" text-anchor="middle">{gy}</text>')
    if pts is not None and len(pts):
        parts.append(_points_path(pts, extent, px, py, fid))
    if region is not None:
        x0, y0, x1, y1 = region
        rx0, rx1 = px(min(max(y1, y_min), y_max)), px(min(max(y0, y_min), y_max))
        ry0, ry1 = py(min(max(x1, x_min), x_max)), py(min(max(x0, x_min), x_max))
        tip = f"region x [{_num(x0)}, {_num(x1)}) m, y [{_num(y0)}, {_num(y1)}) m"
        parts.append(f'<rect x="{_num(rx0)}" y="{_num(ry0)}" width="{_num(rx1 - rx0)}" height="{_num(ry1 - ry0)}" '
                     f'class="reg"><title>{tip}</title></rect>')
    sx, sy = px(0.0), py(0.0)
    parts.append(f'<path d="M{_num(sx)} {_num(sy - 6)} L{_num(sx + 4)} {_num(sy + 4)} L{_num(sx - 4)} '
                 f'{_num(sy + 4)} Z" class="sensor"><title>sensor</title></path>')
    index_of = {c: i for i, c in enumerate(classes)}
    for s, ring in ((truth, True), (source, False)):  # rings under the filled markers
        if s is None:
            continue
        for c, x, y, score in centres.get((s, fid), []):
            inside = region is None or (region[0] <= x < region[2] and region[1] <= y < region[3])
            i = index_of.get(c, 0)
            cls = f"ring t{i}" if ring else f"s{i}"
            cls += "" if inside else " out"
            tip = f"{s}: {c} at x {x:.1f} m, y {y:.1f} m" + ("" if score is None or ring else f", score {score:.2f}")
            parts.append(f'<circle cx="{_num(px(y))}" cy="{_num(py(x))}" '
                         f'r="{5.5 if ring else 3.2}" class="{cls}"><title>{_e(tip)}</title></circle>')
    width, height = left + w + right, top + h + bottom
    svg = (f'<svg class="bev" width="{_num(width)}" height="{_num(height)}" '
           f'viewBox="0 0 {_num(width)} {_num(height)}" data-left="{left}" data-top="{top}" data-mpp="{mpp:.6g}" '
           f'data-xmax="{_num(x_max)}" data-ymax="{_num(y_max)}" role="img" aria-label="frame {fid}, bird&rsquo;s-eye '
           f'view">{"".join(parts)}</svg>')
    got, want = counts.get((source, fid), {}), counts.get((truth, fid), {})
    summary = ", ".join(f"{_e(c)} {got.get(c, '&ndash;')}"
                        + (f" ({_e(truth)} {want.get(c, '&ndash;')})" if truth else "") for c in classes)
    if region is not None:
        summary += " inside the region"
    return (f'<figure id="frame-{fid}" style="width:{_num(width)}px"><figcaption><b>frame {fid}</b>: {summary}'
            f'</figcaption>{svg}<div class="xy"></div></figure>')


def _points_path(pts: np.ndarray, extent, px, py, fid: int) -> str:
    """The points as one SVG path of short strokes on whole pixels, clipped to the picture, at most
    :data:`MAX_POINTS` of them (a subsample fixed by the frame id)."""
    x_min, x_max, y_min, y_max = extent
    pts = pts[np.isfinite(pts).all(1)]
    keep = (pts[:, 0] >= x_min) & (pts[:, 0] <= x_max) & (pts[:, 1] >= y_min) & (pts[:, 1] <= y_max)
    pts = pts[keep]
    xy = np.stack([np.round(px(pts[:, 1])), np.round(py(pts[:, 0]))], 1).astype(np.int64)
    xy = np.unique(xy, axis=0)  # one dot per pixel
    if len(xy) > MAX_POINTS:
        xy = xy[np.sort(np.random.default_rng(abs(fid)).choice(len(xy), MAX_POINTS, replace=False))]
    if not len(xy):
        return ""
    steps = np.diff(xy, axis=0)
    d = [f"M{xy[0, 0]} {xy[0, 1]}h0"] + [f"m{dx} {dy}h0" for dx, dy in steps.tolist()]  # round caps: a dot each
    return f'<path class="pts" d="{"".join(d)}"/>'
