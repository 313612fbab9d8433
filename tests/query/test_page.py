"""lidarops.query.page.answer_page: the page is self-contained and escaped, its count table and pictures
agree with the tables the index was made from (whole frames and regions), an empty answer says so, the
points are capped; and in headless Chromium (Debian's ``chromium``, installed by .ci/run) it loads without
a console message, its coordinate readout works, and a screenshot is taken. The console check is shown to
fail on a page that throws."""
from __future__ import annotations

import os
import re
import shutil
import struct
import subprocess

import numpy as np
import pytest

duckdb = pytest.importorskip("duckdb")
pa = pytest.importorskip("pyarrow")

from helpers.query import centres_of as _centres_of  # noqa: E402
from lidarops.query import FrameIndex, QueryError  # noqa: E402
from lidarops.query.page import MAX_POINTS, answer_page, points_from_index  # noqa: E402

CLASSES = ["Car", "Pedestrian", "Cyclist"]
QUERY = 'Car>=3 & Pedestrian<=2 <script>alert("x")</script>'


def centres_of(rng, counts):
    return _centres_of(rng, counts, CLASSES, x=(-20.0, 60.0), y=(-25.0, 25.0))


@pytest.fixture
def made(tmp_path):
    """An index of two sources with centres, and the tables it was made from."""
    rng = np.random.default_rng(0)
    ids = np.arange(40) * 7 + 3  # ids are not positions
    labels = {"frame_id": ids, **{c: rng.integers(0, 6, len(ids)) for c in CLASSES}}
    detector = {"frame_id": ids[:-5], **{c: np.maximum(labels[c][:-5] + rng.integers(-1, 2, len(ids) - 5), 0)
                                          for c in CLASSES}}  # the detector lacks the last 5 frames
    lc, dc = centres_of(rng, labels), centres_of(rng, detector)
    idx = FrameIndex.create(tmp_path / "idx", labels, centres=lc)
    idx.append(detector, centres=dc, source="detector")
    return idx, {"labels": (labels, lc), "detector": (detector, dc)}


def counts_of(table, fid, region=None, centres=None):
    """{class: count} of one frame from the tables (inside region from the centres), or None if absent."""
    if fid not in set(table["frame_id"].tolist()):
        return None
    if region is None:
        i = table["frame_id"].tolist().index(fid)
        return {c: int(table[c][i]) for c in CLASSES}
    x0, y0, x1, y1 = region
    out = {c: 0 for c in CLASSES}
    for f, c, x, y in zip(centres["frame_id"], centres["class"], centres["x"], centres["y"]):
        x, y = np.float32(x), np.float32(y)  # as stored
        if f == fid and x0 <= x < x1 and y0 <= y < y1:
            out[c] += 1
    return out


def table_rows(text):
    """{frame_id: [cell, ...]} of the page's count table (the cells after the frame id)."""
    rows = {}
    for fid, body in re.findall(r'<tr id="row-(\d+)">(.*?)</tr>', text):
        cells = re.findall(r"<td[^>]*>(.*?)</td>", body)
        rows[int(fid)] = cells[1:]
    return rows


def figure_of(text, fid):
    m = re.search(rf'<figure id="frame-{fid}".*?</figure>', text, re.S)
    assert m, f"no picture of frame {fid}"
    return m.group(0)


def test_page_is_self_contained_and_escaped(made, tmp_path):
    idx, _ = made
    ids = idx.retrieve({"Car": (">=", 3)}, source="detector")
    page = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text=QUERY, answer=ids, frame_ids=ids,
                       source="detector", points_of=lambda f: np.random.default_rng(f).normal(0, 20, (3000, 4)))
    text = page.read_text(encoding="utf-8")
    for outside in ("http://", "https://", "src=", "<link", "@import", "url(", "<iframe", "<object", "<embed"):
        assert outside not in text, f"the page refers to something outside: {outside!r}"
    assert '<script>alert("x")</script>' not in text and "alert(&quot;x&quot;)" in text
    assert "&lt;script&gt;" in text and "Car&gt;=3 &amp; Pedestrian&lt;=2" in text
    assert text.count("<script>") == 1  # the page's own, a few lines
    assert len(text) < 400_000, f"{len(text)} bytes for {min(len(ids), 24)} frames"


def test_counts_and_pictures_match_the_tables(made, tmp_path):
    idx, tables = made
    det, lab = tables["detector"][0], tables["labels"][0]
    ids = [int(f) for f in det["frame_id"] if det["Car"][list(det["frame_id"]).index(f)] >= 2]
    shown_ids = ids + [int(lab["frame_id"][-1])]  # one frame the detector does not hold
    page = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text="Car>=2", answer=ids,
                       frame_ids=shown_ids, source="detector", truth="labels", max_frames=30)
    text = page.read_text()
    assert f"{len(ids)} frame(s)" in text and ", ".join(map(str, ids[:10])) in text
    shown = shown_ids[:30]
    rows = table_rows(text)
    assert list(rows) == shown
    for fid in shown:
        d, t = counts_of(det, fid), counts_of(lab, fid)
        want = [str(v) for c in CLASSES for v in ("&ndash;" if d is None else d[c], t[c])]
        assert rows[fid] == want, fid
    assert text.count('<svg class="bev"') == len(shown)
    for fid in shown[:8]:  # the markers are the stored centres: filled per detector object, rings per label
        fig = figure_of(text, fid)
        for i, c in enumerate(CLASSES):
            d, t = counts_of(det, fid), counts_of(lab, fid)
            assert len(re.findall(rf'class="s{i}"', fig)) == (0 if d is None else d[c])
            assert len(re.findall(rf'class="ring t{i}"', fig)) == t[c]


def test_at_most_max_frames_and_no_truth(made, tmp_path):
    idx, tables = made
    ids = idx.retrieve({})
    text = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text="all", answer=ids, frame_ids=ids,
                       max_frames=5, truth=None).read_text()
    assert text.count('<svg class="bev"') == 5 and list(table_rows(text)) == ids[:5]
    assert "5 of 40 frame(s) shown" in text and 'class="ring' not in text
    lab = tables["labels"][0]
    assert table_rows(text)[ids[0]] == [str(counts_of(lab, ids[0])[c]) for c in CLASSES]
    text = answer_page(idx, tmp_path / "b.html", kind="sum", query_text="sum Car", answer=7, frame_ids=ids,
                       max_frames=0, truth="counter").read_text()  # a truth the index lacks: a note, no column
    assert '<svg class="bev"' not in text and "No frames to show." in text and "is not in this index" in text


def test_region_counts_inside_it(made, tmp_path):
    idx, tables = made
    region = (0.0, -7.5, 30.0, 7.5)
    ids = idx.retrieve({"Car": (">=", 1)}, source="detector", region=region)
    assert ids
    text = answer_page(idx, tmp_path / "a.html", kind="count", query_text="Car>=1 in region", answer=len(ids),
                       frame_ids=ids, source="detector", region=region).read_text()
    rows = table_rows(text)
    for fid in ids[:24]:
        d = counts_of(tables["detector"][0], fid, region, tables["detector"][1])
        t = counts_of(tables["labels"][0], fid, region, tables["labels"][1])
        assert rows[fid] == [str(v) for c in CLASSES for v in (d[c], t[c])], fid
        assert d["Car"] >= 1
    assert text.count('class="reg"><title>') == min(len(ids), 24)  # the region drawn on every picture
    assert "inside the region" in text


def test_empty_answers_say_so(made, tmp_path):
    idx, _ = made
    text = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text="Car>99", answer=[]).read_text()
    assert "No frame meets the query." in text and '<svg class="bev"' not in text and "No frames to show." in text
    text = answer_page(idx, tmp_path / "b.html", kind="avg", query_text="avg Car over 9000:9001", answer=None).read_text()
    assert "No frames to aggregate over." in text
    text = answer_page(idx, tmp_path / "c.html", kind="count", query_text="Car>99", answer=0).read_text()
    assert '<span class="answer">0</span> frame(s)' in text


def test_points_are_capped_and_clipped(made, tmp_path):
    idx, _ = made
    ids = idx.retrieve({})[:24]
    many = np.random.default_rng(0).uniform(-80, 80, (120_000, 4)).astype(np.float32)
    text = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text="all", answer=ids, frame_ids=ids,
                       points_of=lambda f: many if f != ids[1] else None).read_text()
    paths = re.findall(r'<path class="pts" d="([^"]*)"', text)
    assert len(paths) == 23  # frame ids[1] has no points: centres only
    assert all(0 < p.count("h0") <= MAX_POINTS for p in paths)
    assert 'class="pts"' not in figure_of(text, ids[1])
    assert len(text) < 600_000, f"{len(text)} bytes for 24 frames of {len(many)} points"
    with pytest.raises(QueryError, match=r"points_of\(3\) must return an array \(N, >= 2\)"):
        answer_page(idx, tmp_path / "b.html", kind="retrieve", query_text="q", answer=[3], frame_ids=[3],
                    points_of=lambda f: np.zeros(5))


def test_points_from_index_reads_bin_paths(tmp_path):
    rng = np.random.default_rng(0)
    scans = {}
    for fid in (1, 2):
        scans[fid] = rng.normal(0, 10, (500, 4)).astype(np.float32)
        scans[fid].tofile(tmp_path / f"{fid:06d}.bin")
    (tmp_path / "000004.bin").write_bytes(b"\0" * 10)  # not (N, 4) float32
    counts = {"frame_id": [1, 2, 3, 4], "Car": [1, 0, 2, 0],
              "path": [str(tmp_path / "000001.bin"), "000002.bin", None, str(tmp_path / "000004.bin")]}
    try:
        idx = FrameIndex.create(tmp_path / "idx", counts)
    except QueryError as e:
        pytest.skip(f"this index has no path column yet: {e}")
    (tmp_path / "idx" / "000002.bin").write_bytes(scans[2].tobytes())  # a relative path: from the index's folder
    points_of = points_from_index(idx, [1, 2, 3, 4])
    np.testing.assert_array_equal(points_of(1), scans[1])
    np.testing.assert_array_equal(points_of(2), scans[2])
    assert points_of(3) is None and points_of(9) is None
    with pytest.raises(QueryError, match="000004.bin: 2 float32 values"):
        points_of(4)
    assert points_from_index(idx, [3]) is None and points_from_index(idx, []) is None
    page = answer_page(idx, tmp_path / "a.html", kind="sum", query_text="sum Car", answer=3, frame_ids=[1, 2, 3],
                       points_of=points_of)
    assert page.read_text().count('<path class="pts"') == 2


def test_bad_arguments_are_named(made, tmp_path):
    idx, _ = made
    out = tmp_path / "a.html"
    with pytest.raises(QueryError, match="kind must be one of retrieve, count, sum, avg"):
        answer_page(idx, out, kind="median", query_text="q", answer=1)
    with pytest.raises(QueryError, match="unknown source 'counter'"):
        answer_page(idx, out, kind="sum", query_text="q", answer=1, source="counter")
    with pytest.raises(QueryError, match="max_frames must be an integer >= 0"):
        answer_page(idx, out, kind="sum", query_text="q", answer=1, max_frames=-1)
    with pytest.raises(QueryError, match="region must be finite with x0 < x1"):
        answer_page(idx, out, kind="sum", query_text="q", answer=1, region=(5, 0, 1, 1))
    with pytest.raises(QueryError, match="answer of a retrieve must be a list of frame ids"):
        answer_page(idx, out, kind="retrieve", query_text="q", answer=3)
    with pytest.raises(QueryError, match="answer of a sum must be a number or None"):
        answer_page(idx, out, kind="sum", query_text="q", answer=[1, 2])
    assert not out.exists()


def test_numpy_answers_and_sources_without_centres(tmp_path):
    counts = {"frame_id": np.array([5, 6, 7]), "Car": np.array([2, 0, 1]), "Pedestrian": np.array([0, 3, 1])}
    idx = FrameIndex.create(tmp_path / "idx", counts)  # no centres
    ids = np.array(idx.retrieve({"Car": (">=", 1)}))
    text = answer_page(idx, tmp_path / "a.html", kind="retrieve", query_text="Car>=1", answer=ids, frame_ids=ids,
                       truth_answer=ids).read_text()
    assert "2 frame(s)" in text and "labels has no stored object centres" in text and "<circle" not in text.split(
        '<section id="frames">')[1]
    assert table_rows(text) == {5: ["2", "0"], 7: ["1", "1"]}
    text = answer_page(idx, tmp_path / "b.html", kind="avg", query_text="avg Car", answer=np.float64(1.0),
                       frame_ids=[5, 6, 7]).read_text()
    assert '<span class="answer">1</span> per frame' in text
    with pytest.raises(QueryError, match="source 'labels' has no object centres: a region needs them"):
        answer_page(idx, tmp_path / "c.html", kind="avg", query_text="q", answer=1.0, region=(0, 0, 1, 1))


# ---------------------------------------------------------------------------------------------- Chromium
def chromium() -> str:
    found = shutil.which("chromium") or ("/usr/bin/chromium" if os.access("/usr/bin/chromium", os.X_OK) else None)
    if found is None:
        pytest.skip("no Chromium (Debian's chromium package; .ci/run installs it when it can): the answer page "
                    "is not tried in a browser")
    return found


def open_in_chromium(page, tmp_path, name="page"):
    """Loads ``page`` in headless Chromium (timers run for 2 s of virtual time), screenshots it, and returns
    (the console messages, the screenshot's path)."""
    shot = tmp_path / f"{name}.png"
    args = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={tmp_path / (name + '-profile')}", "--enable-logging=stderr", "--v=0",
            "--virtual-time-budget=2000", f"--screenshot={shot}", "--window-size=1280,2000", page.resolve().as_uri()]
    try:
        run = subprocess.run(args, capture_output=True, text=True, timeout=90, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        pytest.fail("headless Chromium did not finish within 90 s")
    assert run.returncode == 0, f"chromium exited {run.returncode}:\n{run.stderr[-3000:]}"
    # every console message (log, warning, error, uncaught exception) is logged as ...:CONSOLE:<line>] "...";
    # the level is not in the line, and the page logs nothing, so any message counts
    console = [m.group(1) for m in re.finditer(r":CONSOLE(?::\d+|\(\d+\))\] (.*)", run.stderr)]
    return console, shot


def png_size_and_colours(path):
    """(width, height) from the PNG header, and the number of distinct colours (None without a decoder)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    width, height = struct.unpack(">II", data[16:24])
    try:
        from PIL import Image

        colours = Image.open(path).convert("RGB").getcolors(maxcolors=1 << 24)
        return (width, height), len(colours)
    except ImportError:
        pass
    try:
        import matplotlib.image

        pixels = matplotlib.image.imread(path)[..., :3].reshape(-1, 3)
        return (width, height), len(np.unique(pixels, axis=0))
    except ImportError:
        return (width, height), None


@pytest.mark.slow
def test_page_loads_in_chromium_without_console_messages(made, tmp_path):
    idx, _ = made
    ids = idx.retrieve({"Car": (">=", 2)}, source="detector")
    region = (0.0, -10.0, 40.0, 10.0)
    page = answer_page(idx, tmp_path / "answer.html", kind="retrieve", query_text=QUERY, answer=ids, frame_ids=ids,
                       source="detector", region=region,
                       points_of=lambda f: np.random.default_rng(f).normal((15, 0), (15, 10), (4000, 2)))
    console, shot = open_in_chromium(page, tmp_path)
    assert console == [], f"the page logged to the console: {console}"
    (width, height), colours = png_size_and_colours(shot)
    assert (width, height) == (1280, 2000)
    if colours is None:  # no PNG decoder here: a blank page compresses to a few KB
        assert shot.stat().st_size > 50_000, f"the screenshot looks blank ({shot.stat().st_size} bytes)"
    else:
        assert colours > 20, f"the screenshot looks blank ({colours} colours)"
    # the coordinate readout, against the drawing: a mouse move over the sensor's mark reads x 0, y 0, and one
    # over the first object's marker reads the place its title names (within a pixel: mouse events land on
    # whole pixels), else the probe throws
    probe = """<script>
var svg = document.querySelector("svg.bev"), k = svg.viewBox.baseVal.width / svg.getBoundingClientRect().width;
var tol = Number(svg.dataset.mpp) / k * 1.5 + 0.06;
var sensor = svg.querySelector(".sensor").getBoundingClientRect();  // a triangle, its base 4 units below the sensor
var marker = svg.querySelector("circle[class^=s]"), place = / at x (-?[0-9.]+) m, y (-?[0-9.]+) m/.exec(marker.textContent);
var m = marker.getBoundingClientRect();
[[(sensor.left + sensor.right) / 2, sensor.bottom - 4 / k, 0, 0],
 [(m.left + m.right) / 2, (m.top + m.bottom) / 2, Number(place[1]), Number(place[2])]].forEach(function (p) {
  svg.dispatchEvent(new MouseEvent("mousemove", {clientX: p[0], clientY: p[1]}));
  var said = svg.parentNode.querySelector(".xy").textContent, r = /^x (-?[0-9.]+) m, y (-?[0-9.]+) m$/.exec(said);
  if (!r || Math.abs(r[1] - p[2]) > tol || Math.abs(r[2] - p[3]) > tol) throw new Error("readout at " + p + ": " + said);
});
</script></body>"""
    probed = tmp_path / "probed.html"
    probed.write_text(page.read_text().replace("</body>", probe), encoding="utf-8")
    console, _ = open_in_chromium(probed, tmp_path, "probed")
    assert console == [], f"the coordinate readout failed: {console}"


@pytest.mark.slow
def test_console_check_finds_an_error(tmp_path):
    page = tmp_path / "throws.html"
    page.write_text('<!doctype html><html><body><p>x</p><script>throw new Error("x")</script></body></html>')
    console, shot = open_in_chromium(page, tmp_path)
    assert any("Uncaught Error: x" in line for line in console), console
    assert shot.is_file()
