"""Filling an index from frames (lidarops.query.build) and the ``lidarops index`` / ``lidarops query``
commands: counts equal the frames' labels; a build killed midway (SIGKILL) and run again holds every frame
once; two torchrun ranks make one index; unreadable scans and missing labels are named, or skipped and
listed, never a silent hole."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

from lidarops.cli import main  # noqa: E402
from lidarops.data.formats.kitti import KittiCalib, write_calib  # noqa: E402
from lidarops.query import FrameIndex  # noqa: E402
from lidarops.query.build import BuildReport, FrameError, LabelsSource, build_index  # noqa: E402
from lidarops.query.index import QueryError  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CLASSES = ("Car", "Pedestrian", "Cyclist")


class FakeFrame:
    class_names = ("Car", "Pedestrian", "Cyclist", "Truck")

    def __init__(self, rng, timestamp=None):
        n = int(rng.integers(0, 9))
        self.labels = rng.integers(-1, 4, n)  # -1: a class outside the list, 3: a class not counted
        self.boxes = np.concatenate([rng.uniform(-30, 60, (n, 2)), np.ones((n, 5))], 1).astype(np.float32)
        self.timestamp = timestamp
        self.meta = {}


def frames(n, seed=0):
    rng = np.random.default_rng(seed)
    return {10 * i + 3: FakeFrame(rng, timestamp=0.1 * i) for i in range(n)}


def truth(pairs):
    return {fid: {c: int((f.labels == k).sum()) for k, c in enumerate(CLASSES)} for fid, f in pairs.items()}


def stored(idx, source="labels"):
    got = idx.sql('SELECT frame_id, "Car", "Pedestrian", "Cyclist" FROM counts WHERE source = ? ORDER BY frame_id',
                  [source])
    return {int(r.frame_id): {"Car": r.Car, "Pedestrian": r.Pedestrian, "Cyclist": r.Cyclist} for r in got.itertuples()}


def test_labels_counts_and_centres(tmp_path):
    pairs = frames(23)
    out = build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, LabelsSource(CLASSES), batch=3, part_frames=5)
    assert (out.indexed, out.skipped, out.failed) == (23, 0, [])
    assert set(out.stage_seconds) == {"load", "count", "write"}
    idx = FrameIndex.open(tmp_path / "idx")
    want = truth(pairs)
    assert stored(idx) == want
    assert len(list((tmp_path / "idx" / "counts" / "labels").glob("*.parquet"))) == 5  # ceil(23 / 5) parts
    n_centres = int(idx.sql("SELECT count(*) AS n FROM centres")["n"][0])
    assert n_centres == sum(sum(v.values()) for v in want.values())
    stamps = idx.sql("SELECT frame_id, timestamp FROM counts ORDER BY frame_id")
    assert np.allclose(stamps["timestamp"], [0.1 * i for i in range(23)])
    # a region equals counting the labelled boxes inside it
    region = (0.0, -10.0, 30.0, 10.0)
    inside = sum(int(((f.labels == 0) & (f.boxes[:, 0] >= 0) & (f.boxes[:, 0] < 30) & (f.boxes[:, 1] >= -10)
                      & (f.boxes[:, 1] < 10)).sum()) for f in pairs.values())
    assert idx.sum("Car", region=region) == inside


def test_workers_give_the_same_index(tmp_path):
    pairs = frames(17, seed=4)
    build_index(tmp_path / "a", list(pairs), pairs.__getitem__, LabelsSource(CLASSES), batch=4, workers=0)
    build_index(tmp_path / "b", list(pairs), pairs.__getitem__, LabelsSource(CLASSES), batch=4, workers=2)
    assert stored(FrameIndex.open(tmp_path / "b")) == stored(FrameIndex.open(tmp_path / "a")) == truth(pairs)


def test_a_stopped_build_resumes_without_duplicates(tmp_path):
    pairs = frames(30, seed=1)
    calls = {"n": 0}
    inner = LabelsSource(CLASSES)

    def dying(batch):  # the process is stopped while counting the fifth batch
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return inner(batch)

    with pytest.raises(KeyboardInterrupt):
        build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, dying, source_name="labels",
                    classes=inner.classes, batch=3, part_frames=6)
    assert FrameIndex.open(tmp_path / "idx").frame_count("labels") == 12  # two parts of 6 landed
    out = build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, inner, batch=3, part_frames=6)
    assert (out.indexed, out.skipped) == (18, 12)
    idx = FrameIndex.open(tmp_path / "idx")
    assert idx.retrieve({}) == sorted(pairs)  # every frame once
    assert stored(idx) == truth(pairs)
    again = build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, inner)
    assert (again.indexed, again.skipped) == (0, 30)


def test_centres_of_a_part_whose_counts_never_landed_are_not_read(tmp_path):
    """A kill between a part's centres and its counts leaves an orphan centres file: not counted, and
    overwritten by the build run again."""
    pairs = frames(6, seed=2)
    build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, LabelsSource(CLASSES), part_frames=3)
    counts = tmp_path / "idx" / "counts" / "labels"
    last = sorted(counts.glob("*.parquet"))[-1]
    last.unlink()  # as if killed after writing this part's centres
    idx = FrameIndex.open(tmp_path / "idx")
    want = truth(pairs)
    kept = sorted(pairs)[:3]
    assert idx.frame_count("labels") == 3
    assert int(idx.sql("SELECT count(*) AS n FROM centres")["n"][0]) == sum(sum(want[f].values()) for f in kept)
    build_index(tmp_path / "idx", list(pairs), pairs.__getitem__, LabelsSource(CLASSES), part_frames=3)
    idx = FrameIndex.open(tmp_path / "idx")
    assert stored(idx) == want
    assert int(idx.sql("SELECT count(*) AS n FROM centres")["n"][0]) == sum(sum(v.values()) for v in want.values())


def test_unreadable_frames_raise_or_are_listed(tmp_path):
    pairs = frames(9, seed=3)

    def load(fid):
        if fid in (23, 63):
            raise FrameError(f"frame {fid}: scan unreadable")
        return pairs[fid]

    with pytest.raises(FrameError, match="frame 23"):
        build_index(tmp_path / "idx", list(pairs), load, LabelsSource(CLASSES), batch=2)
    out = build_index(tmp_path / "idx2", list(pairs), load, LabelsSource(CLASSES), batch=2, on_error="skip")
    assert out.indexed == 7 and [f for f, _ in out.failed] == [23, 63] and "unreadable" in out.failed[0][1]
    assert FrameIndex.open(tmp_path / "idx2").retrieve({}) == [f for f in sorted(pairs) if f not in (23, 63)]
    retry = build_index(tmp_path / "idx2", list(pairs), pairs.__getitem__, LabelsSource(CLASSES))
    assert (retry.indexed, retry.skipped) == (2, 7)


@pytest.mark.parametrize("kwargs,message", [
    (dict(batch=0), "batch must be an integer >= 1"),
    (dict(part_frames=1.5), "part_frames must be an integer >= 1"),
    (dict(workers=-1), "workers must be an integer >= 0"),
    (dict(on_error="ignore"), "on_error must be 'raise' or 'skip'"),
])
def test_bad_build_arguments_are_named(tmp_path, kwargs, message):
    with pytest.raises(QueryError, match=message):
        build_index(tmp_path / "idx", [1], lambda f: None, LabelsSource(CLASSES), **kwargs)


def test_duplicate_ids_are_refused(tmp_path):
    with pytest.raises(QueryError, match=r"ids holds duplicates, e.g. \[4\]"):
        build_index(tmp_path / "idx", [4, 5, 4], lambda f: None, LabelsSource(CLASSES))


# ---------------------------------------------------------------- a KITTI folder, written by hand

LABEL = "{name} 0.00 0 0.0 100.0 120.0 200.0 220.0 1.5 1.6 3.9 {x:.2f} 1.70 {z:.2f} 0.10\n"


def kitti_folder(root: Path, n: int, seed: int = 0, points: int = 200) -> dict[int, dict[str, int]]:
    """``n`` frames (ids 100, 101, ...) with random labels; returns each frame's true counts per class,
    counted from the names written (Van and DontCare are not counted)."""
    rng = np.random.default_rng(seed)
    want = {}
    for d in ("velodyne", "label_2", "calib"):
        (root / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        fid = 100 + i
        pts = np.concatenate([rng.uniform(-40, 40, (points, 3)), rng.uniform(0, 1, (points, 1))], 1)
        pts.astype(np.float32).tofile(root / "velodyne" / f"{fid:06d}.bin")
        names = rng.choice(["Car", "Pedestrian", "Cyclist", "Van", "DontCare"], int(rng.integers(0, 7)))
        (root / "label_2" / f"{fid:06d}.txt").write_text(
            "".join(LABEL.format(name=nm, x=rng.uniform(-10, 10), z=rng.uniform(5, 40)) for nm in names))
        write_calib(root / "calib" / f"{fid:06d}.txt", KittiCalib.default())
        want[fid] = {c: int((names == c).sum()) for c in CLASSES}
    return want


def test_cli_builds_a_kitti_folder(tmp_path, capsys):
    want = kitti_folder(tmp_path / "kitti", 7)
    out = str(tmp_path / "idx")
    assert main(["index", "build", str(tmp_path / "kitti"), "--out", out, "--no-progress", "--workers", "0",
                 "--min-points", "0"]) == 0
    printed = capsys.readouterr().out
    assert "indexed 7 frame(s) with source labels" in printed and "load" in printed and "count" in printed
    idx = FrameIndex.open(out)
    assert stored(idx) == want
    paths = idx.sql("SELECT frame_id, path FROM counts ORDER BY frame_id")
    assert [Path(p).name for p in paths["path"]] == [f"{f:06d}.bin" for f in sorted(want)]


def test_cli_names_a_corrupt_scan_or_lists_it(tmp_path, capsys):
    want = kitti_folder(tmp_path / "kitti", 6, seed=1)
    (tmp_path / "kitti" / "velodyne" / "000102.bin").write_bytes(b"\x00" * 10)  # not a whole point
    (tmp_path / "kitti" / "label_2" / "000104.txt").unlink()
    out = str(tmp_path / "idx")
    assert main(["index", "build", str(tmp_path / "kitti"), "--out", out, "--no-progress", "--workers", "0",
                 "--min-points", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "000102.bin" in err[0], err
    assert main(["index", "build", str(tmp_path / "kitti"), "--out", out, "--no-progress", "--skip-bad",
                 "--min-points", "0"]) == 1
    printed = capsys.readouterr().out
    assert "left out 2 frame(s)" in printed and "000102.bin" in printed and "000104: no labels" in printed
    assert sorted(stored(FrameIndex.open(out))) == [100, 101, 103, 105]
    # the detector does not need labels: the frame without them is counted, the corrupt scan still named
    assert FrameIndex.open(out).sources == ["labels"]
    assert {f: want[f] for f in (100, 101, 103, 105)} == stored(FrameIndex.open(out))


@pytest.mark.parametrize("setup,message", [
    (lambda p: p.mkdir(), "is not a KITTI object directory"),
    (lambda p: (p / "velodyne").mkdir(parents=True), "holds no .bin scans"),
    (lambda p: kitti_folder(p, 1) and None, None),
])
def test_cli_empty_or_unlabelled_folders(tmp_path, capsys, setup, message):
    folder = tmp_path / "kitti"
    setup(folder)
    if message is None:  # a folder without label_2/ asked for the labels
        import shutil
        shutil.rmtree(folder / "label_2")
        message = "has no label_2/ folder: --source labels counts the labels"
    assert main(["index", "build", str(folder), "--out", str(tmp_path / "idx"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def _cli(*args, env=None):
    return [sys.executable, "-c", "import sys; from lidarops.cli import main; sys.exit(main(sys.argv[1:]))", *args]


def test_sigkill_midway_then_resume(tmp_path):
    """A real SIGKILL during a build (parts of one frame, so it dies between parts), then the same command
    again: every frame once, counts equal to the labels."""
    want = kitti_folder(tmp_path / "kitti", 60, seed=2, points=20000)
    out = tmp_path / "idx"
    cmd = _cli("index", "build", str(tmp_path / "kitti"), "--out", str(out), "--no-progress", "--workers", "0",
               "--part-frames", "1", "--batch", "1", "--min-points", "0")
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    parts = out / "counts" / "labels"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and len(list(parts.glob("*.parquet"))) < 3:
        time.sleep(0.01)
    assert proc.poll() is None, "the build ended before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    landed = FrameIndex.open(out).frame_count("labels")
    assert 3 <= landed < 60
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"({landed} already there)" in done.stdout
    idx = FrameIndex.open(out)
    assert idx.retrieve({}) == sorted(want)
    assert stored(idx) == want


@pytest.mark.slow
def test_torchrun_two_ranks_make_one_index(tmp_path):
    """``torchrun --nproc_per_node=2 lidarops index build``: two gloo processes, each its share of the
    frames and its own parts; the index is their union, every frame once."""
    want = kitti_folder(tmp_path / "kitti", 13, seed=3)
    out = tmp_path / "idx"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "--no-python",
           *_cli("index", "build", str(tmp_path / "kitti"), "--out", str(out), "--no-progress", "--workers", "0",
                 "--part-frames", "4", "--min-points", "0")]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "indexed 13 frame(s) with source labels" in done.stdout and "on 2 ranks" in done.stdout
    names = sorted(p.name for p in (out / "counts" / "labels").glob("*.parquet"))
    assert names == ["part-r000-00000.parquet", "part-r000-00001.parquet",
                     "part-r001-00000.parquet", "part-r001-00001.parquet"]  # 7 + 6 frames, parts of 4
    idx = FrameIndex.open(out)
    assert stored(idx) == want


def test_report_shares():
    r = BuildReport(indexed=10, seconds=2.0, stage_seconds={"load": 0.5, "count": 1.0, "write": 0.5})
    assert r.frames_per_second == 5.0
    assert r.shares() == "load 25 %, count 50 %, write 25 %"


def test_cli_build_and_query(tmp_path, capsys):
    from lidarops.data.synthetic import SyntheticFrames

    out = str(tmp_path / "idx")
    assert main(["index", "build", "--scenario", "driving_city", "--frames", "3", "--out", out, "--no-progress",
                 "--workers", "0"]) == 0
    printed = capsys.readouterr().out
    assert "indexed 3 frame(s) with source labels" in printed
    assert "boxes centred in x [0, 69.12), y [-39.68, 39.68) holding >= 1 point(s)" in printed
    idx = FrameIndex.open(out)
    # the default rule, counted by hand from the simulated frames: within the shipped detector's range, seen
    sim = SyntheticFrames("driving_city", num_frames=3, seed=5000)
    for i in range(3):
        f = sim[i]
        ok = ((f.boxes[:, 0] >= 0) & (f.boxes[:, 0] < 69.12) & (f.boxes[:, 1] >= -39.68) & (f.boxes[:, 1] < 39.68)
              & (f.num_points_in_box >= 1))
        want = {c: int(((f.labels == f.class_names.index(c)) & ok).sum()) for c in CLASSES}
        assert stored(idx)[i] == want
    everywhere = str(tmp_path / "all")
    assert main(["index", "build", "--scenario", "driving_city", "--frames", "1", "--out", everywhere,
                 "--no-progress", "--workers", "0", "--labels-range", "all", "--min-points", "0"]) == 0
    capsys.readouterr()
    f = sim[0]
    assert stored(FrameIndex.open(everywhere))[0] == {c: int((f.labels == f.class_names.index(c)).sum()) for c in CLASSES}
    cars = idx.sum("Car")
    assert idx.sql("SELECT DISTINCT sequence FROM counts")["sequence"].tolist() == ["driving_city:5000"]
    assert main(["query", "sum", out, "--class", "Car"]) == 0
    assert capsys.readouterr().out.strip() == str(cars)
    assert main(["query", "retrieve", out, "--where", "Car>=0", "--frames", "0:2"]) == 0
    assert capsys.readouterr().out.strip() == "2 frame(s): 0, 1"
    assert main(["query", "count", out, "--where", f"Car>{cars}"]) == 0
    assert capsys.readouterr().out.strip() == "0"


def test_cli_build_counts_frames_of_a_realism_profile(tmp_path, capsys):
    """--realism: the frames of `data synth --realism` (the same simulator), counted by the same rule; its sequence
    names the profile; a profile that is none is named."""
    from lidarops.data.synthetic import SyntheticFrames

    out = str(tmp_path / "idx")
    assert main(["index", "build", "--scenario", "driving_city", "--frames", "2", "--out", out, "--no-progress",
                 "--workers", "0", "--labels-range", "all", "--min-points", "1", "--realism", "kitti"]) == 0
    capsys.readouterr()
    real = SyntheticFrames("driving_city", num_frames=2, seed=5000, realism="kitti")
    cast = SyntheticFrames("driving_city", num_frames=2, seed=5000)
    idx = FrameIndex.open(out)
    for i in range(2):
        f = real[i]
        assert f.points.shape != cast[i].points.shape  # the profile's frames, not the ray-cast ones
        seen = f.num_points_in_box >= 1
        assert stored(idx)[i] == {c: int(((f.labels == f.class_names.index(c)) & seen).sum()) for c in CLASSES}
    assert idx.sql("SELECT DISTINCT sequence FROM counts")["sequence"].tolist() == ["driving_city:5000:kitti"]
    with pytest.raises(SystemExit) as bad:  # argparse's own refusal, the option named
        main(["index", "build", "--scenario", "driving_city", "--frames", "1", "--out", str(tmp_path / "n"),
              "--realism", "glossy"])
    assert bad.value.code == 2 and "--realism" in capsys.readouterr().err


@pytest.mark.parametrize("argv,message", [
    (["query", "retrieve", "{idx}", "--where", "Car=>1"], "expected CLASS OP NUMBER"),
    (["query", "retrieve", "{idx}", "--where", "Truck>=1"], "unknown class 'Truck'; the index's classes: Car"),
    (["query", "count", "{idx}", "--where", "Car>1", "--where", "Cyclist>1"], "count takes one --where"),
    (["query", "sum", "{idx}"], "sum needs --class, one of: Car, Pedestrian, Cyclist"),
    (["query", "sum", "{idx}", "--class", "Car", "--frames", "5-9"], "expected FIRST:STOP"),
    (["query", "avg", "{idx}", "--class", "Car", "--region", "1,2,3"], "expected X0,Y0,X1,Y1"),
    (["query", "sum", "{idx}", "--class", "Car", "--source", "radar"], "--source 'radar': the index's sources are labels"),
    (["query", "sum", "{nowhere}", "--class", "Car"], "no frame index at"),
    (["index", "build", "--out", "{new}"], "give a KITTI folder, or --scenario NAME --frames N"),
    (["index", "build", "--scenario", "driving_city", "--out", "{new}"], "--frames must be >= 1"),
    (["index", "build", "--scenario", "driving_city", "--frames", "2", "--batch", "0", "--out", "{new}"],
     "--batch must be >= 1"),
    (["index", "build", "{nowhere}", "--out", "{new}"], "is not a folder"),
])
def test_cli_errors_are_one_line(tmp_path, capsys, argv, message):
    idx = tmp_path / "idx"
    FrameIndex.create(idx, {"frame_id": [0, 1], "Car": [1, 2], "Pedestrian": [0, 0], "Cyclist": [0, 1]})
    argv = [a.format(idx=idx, nowhere=tmp_path / "nowhere", new=tmp_path / "new") for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


class _CountingModel:
    """A stand-in detector: per frame, one Car (label 1) at its points' mean scoring 0.9, and as many
    Pedestrians (label 2) as the frame has points above z = 1, scoring 0.3."""

    class config:
        class_names = ["Car", "Pedestrian", "Cyclist"]

    def parameters(self):
        import torch
        yield torch.zeros(1)

    def predict(self, batch):
        import torch
        pts = batch["points"]
        out = []
        for i in range(batch["batch_size"]):
            p = pts[pts[:, 0] == i, 1:]
            tall = int((p[:, 2] > 1).sum())
            boxes = torch.zeros(1 + tall, 7)
            boxes[0, :2] = p[:, :2].mean(0)
            out.append({"boxes": boxes, "labels": torch.tensor([1] + [2] * tall),
                        "scores": torch.tensor([0.9] + [0.3] * tall)})
        return out


@pytest.mark.parametrize("as_tensor", [False, True])
def test_detector_source_batches_frames_and_thresholds_scores(as_tensor):
    import torch

    from lidarops.query.build import DetectorSource, Scan

    rng = np.random.default_rng(6)
    clouds = [rng.uniform(-5, 5, (n, 4)).astype(np.float32) for n in (7, 0 + 3, 12)]
    frames_ = [Scan(torch.from_numpy(c)) if as_tensor else FakeFrame(rng) for c in clouds]
    if not as_tensor:
        for f, c in zip(frames_, clouds):
            f.points = c
    low = DetectorSource(_CountingModel(), score_thresh=0.25)(frames_)
    high = DetectorSource(_CountingModel(), score_thresh=0.5)(frames_)
    for c, (counts, centres), (counts_hi, _) in zip(clouds, low, high):
        tall = int((c[:, 2] > 1).sum())
        assert counts == {"Car": 1, "Pedestrian": tall, "Cyclist": 0}
        assert counts_hi == {"Car": 1, "Pedestrian": 0, "Cyclist": 0}
        assert centres[0][0] == "Car" and np.allclose(centres[0][1:3], c[:, :2].mean(0), atol=1e-5)


class _RaggedDetector:
    """A stand-in detector with a real one's contract: a batch whose frames do not each hold a point is
    refused (an empty scan is a batch of its own). Per frame, one detection per point above z = 1: label
    1 + (its row mod 3), centre its x, y, score its intensity; a frame with no point above z = 1 has none.
    Records the autocast and TF32 settings it ran under."""

    class config:
        class_names = ["Car", "Pedestrian", "Cyclist"]

    def __init__(self):
        self.seen = []

    def parameters(self):
        import torch
        yield torch.zeros(1)

    def predict(self, batch):
        import torch
        self.seen.append((torch.is_autocast_enabled("cpu"), torch.backends.cudnn.allow_tf32,
                          torch.backends.cuda.matmul.allow_tf32))
        pts, out = batch["points"], []
        for i in range(batch["batch_size"]):
            p = pts[pts[:, 0] == i, 1:]
            if batch["batch_size"] > 1 and not len(p):
                raise ValueError(f"frame {i} of the batch holds no point")
            tall = p[p[:, 2] > 1]
            boxes = torch.zeros(len(tall), 7)
            boxes[:, :2] = tall[:, :2]
            out.append({"boxes": boxes, "labels": 1 + torch.arange(len(tall)) % 3, "scores": tall[:, 3].clone()})
        return out


def _counted_reference(model, frames_, score_thresh):
    """A plain per-frame loop: each frame alone through ``predict``, its detections read one by one."""
    import torch

    out = []
    for f in frames_:
        p = torch.as_tensor(f.points[:, :4]).float()
        pred = model.predict({"points": torch.cat([torch.zeros(len(p), 1), p], 1), "batch_size": 1})[0]
        keep = pred["scores"] >= score_thresh
        counts = {c: 0 for c in model.config.class_names}
        centres = []
        for box, label, score in zip(pred["boxes"][keep].tolist(), pred["labels"][keep].tolist(),
                                     pred["scores"][keep].tolist()):
            counts[model.config.class_names[label - 1]] += 1
            centres.append((model.config.class_names[label - 1], box[0], box[1], score))
        out.append((counts, centres))
    return out


def _ragged_scans():
    """Scans of ragged sizes, one with no points, one with points but none above z = 1 (no detections)."""
    import torch

    from lidarops.query.build import Scan

    rng = np.random.default_rng(11)
    out = []
    for n in (7, 0, 30, 1, 12, 5, 0, 18, 9):
        c = rng.uniform(-5, 5, (n, 4)).astype(np.float32)
        c[:, 3] = rng.uniform(0, 1, n)
        out.append(Scan(torch.from_numpy(c)))
    out[5].points[:, 2] = -1.0  # points, none above z = 1: no detections
    return out


@pytest.mark.parametrize("score_thresh", [0.0, 0.25, 0.5])
def test_detector_source_equals_a_per_frame_loop(score_thresh):
    """One batched predict, counts scattered on the device, one read-back: the same counts and centres, in the
    same order, as predicting each frame alone and reading its detections one by one."""
    from lidarops.query.build import DetectorSource

    scans = _ragged_scans()
    want = _counted_reference(_RaggedDetector(), scans, score_thresh)
    assert want[1] == ({"Car": 0, "Pedestrian": 0, "Cyclist": 0}, []) and want[5][1] == []
    assert sum(len(c) for _, c in want) > 5
    source = DetectorSource(_RaggedDetector(), score_thresh)
    assert source(scans) == want
    assert source(scans[1:2]) == [want[1]] and source([]) == []
    for counts, centres in source(scans):  # the counts are the centres, class by class
        assert counts == {c: sum(k == c for k, *_ in centres) for c in CLASSES}


@pytest.mark.parametrize("batch", [1, 2, 4, 9])
def test_build_with_the_detector_equals_a_per_frame_loop(tmp_path, batch):
    """build_index runs a model source three batches deep (copy, network, read-back overlapped on CUDA): the
    index holds the per-frame loop's counts and centres, whatever the batch, with a batch whose frames all
    failed to load."""
    from lidarops.query.build import DetectorSource

    scans = dict(enumerate(_ragged_scans()))
    bad = {2, 3}  # with batch=2, the whole second batch

    def load(fid):
        if fid in bad:
            raise FrameError(f"frame {fid}: unreadable")
        return scans[fid]

    report = build_index(tmp_path / "idx", list(scans), load, DetectorSource(_RaggedDetector(), 0.25), batch=batch,
                         part_frames=3, on_error="skip")
    assert report.indexed == len(scans) - len(bad) and sorted(f for f, _ in report.failed) == sorted(bad)
    want = dict(zip(scans, _counted_reference(_RaggedDetector(), list(scans.values()), 0.25)))
    idx = FrameIndex.open(tmp_path / "idx")
    assert stored(idx, "detector") == {f: counts for f, (counts, _) in want.items() if f not in bad}
    got = idx.sql("SELECT frame_id, class, x, y, score FROM centres WHERE source = 'detector'")
    rows = sorted((int(r.frame_id), r["class"], r.x, r.y, r.score) for _, r in got.iterrows())
    assert rows == sorted((f, *c) for f, (_, cs) in want.items() if f not in bad for c in cs)


def test_detector_source_precision():
    """``precision`` runs predict under lidarops.models.cuda_graph.precision_mode (bm_detector's and
    GraphedPointPillars' mechanism) and puts torch's settings back; None leaves them as they are; anything
    else is refused, naming the argument."""
    import torch

    from lidarops.query.build import CounterSource, DetectorSource

    scans = _ragged_scans()[:3]
    before = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    want = {None: (False, *before), "fp32": (False, False, False), "tf32": (False, True, True),
            "fp16": (True, False, False)}
    for precision, settings in want.items():
        model = _RaggedDetector()
        assert DetectorSource(model, 0.25, precision=precision)(scans) == _counted_reference(model, scans, 0.25)
        assert set(model.seen[:2]) == {settings}, precision
        assert (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32) == before
    for bad in ("fp8", "FP16", "", "half", 16, True):
        for make in (lambda p: DetectorSource(_RaggedDetector(), precision=p),
                     lambda p: CounterSource(_RaggedDetector(), p)):
            with pytest.raises(QueryError, match=r"precision must be one of 'fp32', 'tf32', 'fp16' or None, got"):
                make(bad)


@pytest.mark.slow  # the shipped PointPillars on the CPU: seconds
def test_shipped_detector_source_equals_a_per_frame_loop():
    """The shipped PointPillars: a batch of ragged frames (one empty, one outside the detector's range) counted
    by the source equals each frame predicted alone and read one detection at a time."""
    import torch

    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models import load_model, weights
    from lidarops.query.build import DetectorSource, Scan

    model = load_model(weights.path()).eval()
    sim = SyntheticFrames("driving_city", num_frames=2, seed=3)
    first = torch.from_numpy(sim[0].points[:, :4]).float()
    scans = [Scan(first[first[:, 0] > 0][::4].contiguous()), Scan(torch.zeros(0, 4)),
             Scan(torch.from_numpy(sim[1].points[:, :4]).float()[::9].contiguous()),
             Scan(torch.tensor([[-50.0, 0.0, 0.0, 0.5]]))]  # behind the detector: nothing to find
    want = _counted_reference(model, scans, 0.3)
    assert sum(len(c) for _, c in want) > 0 and want[1][1] == want[3][1] == []
    got = DetectorSource(model, 0.3)(scans)
    assert [counts for counts, _ in got] == [counts for counts, _ in want]
    for (_, centres), (_, ref) in zip(got, want):
        assert [c[0] for c in centres] == [c[0] for c in ref]
        np.testing.assert_allclose([c[1:] for c in centres], [c[1:] for c in ref], rtol=1e-5, atol=1e-5)



def test_detector_source_graph_needs_a_dense_pointpillars_on_cuda():
    import torch

    from lidarops.models.pointpillars import PointPillars
    from lidarops.query.build import DetectorSource

    from helpers.models import TINY

    assert DetectorSource(_RaggedDetector()).graph is False  # not a PointPillars: eager
    cpu = PointPillars(TINY)
    assert DetectorSource(cpu).graph is False  # on the CPU: eager
    with pytest.raises(QueryError, match="graph=True needs a PointPillars with backbone_mode='dense' on a CUDA device"):
        DetectorSource(cpu, graph=True)
    with pytest.raises(QueryError, match="graph must be True, False or None"):
        DetectorSource(cpu, graph="yes")
    with pytest.raises(QueryError, match="optimize must be True or False"):
        DetectorSource(cpu, optimize="yes")
    if torch.cuda.is_available():
        assert DetectorSource(cpu.cuda()).graph is True


def _same_counts_both_ways(tmp_path, scans, eager, graph) -> None:
    """The eager and the graph source index the scans (4 frames a batch) and store the same counts."""
    for source in (eager, graph):
        build_index(tmp_path / "idx", list(scans), scans.__getitem__, source, source_name=f"s{source.graph}", batch=4)
    idx = FrameIndex.open(tmp_path / "idx")
    want = stored(idx, "sFalse")
    assert sum(sum(c.values()) for c in want.values()) > 0, "the case must count objects"
    assert stored(idx, "sTrue") == want


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("precision", [None, "fp16"])
def test_graph_detector_source_equals_the_eager_one(tmp_path, precision):
    """The CUDA-graph path counts what the eager path counts, batch by batch through build_index (ragged
    frames, an empty one, a larger frame that makes the graph be recorded again, a batch with more pillars than the
    graph's rows, a last batch shorter than the graph's); a bad intensity raises the eager check's message."""
    import torch

    from lidarops.models.pointpillars import PointPillars
    from lidarops.query.build import DetectorSource, Scan

    from helpers.models import TINY

    torch.manual_seed(0)
    model = PointPillars({**TINY, "class_names": ["Car", "Pedestrian", "Cyclist"], "score_thresh": 0.3,
                          "anchor_generator_config": [{**TINY["anchor_generator_config"][0], "class_name": c}
                                                      for c in CLASSES]}).cuda().eval()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(5)
    scans = {i: Scan(torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0]))
             for i, n in enumerate((300, 0, 40, 7, 12, 5, 900, 30, 300, 40000, 300, 300, 20))}
    eager = DetectorSource(model, 0.3, precision, graph=False)
    graph = DetectorSource(model, 0.3, precision, graph=True)
    graph.pillar_step = 1  # pillar rows sized to the first batch (from the third on): the third needs more
    _same_counts_both_ways(tmp_path, scans, eager, graph)
    assert graph._graphed.capacity >= 40000 and graph._graphed.batch_size == 4
    # the second batch needed more pillar rows than the first's graph: counted eagerly, the graph recorded again
    assert graph.eager_batches >= 1 and graph._graphed.max_pillars >= graph._pillars > 64
    bad = Scan(scans[0].points.clone())
    bad.points[3, 3] = float("nan")
    with pytest.raises(ValueError, match=r"frame\(s\) \[1\] of this batch: batch\['points'\]\[:, 4:\] \(intensity"):
        graph([scans[2], bad])


def test_cli_precision_fp16_needs_cuda(tmp_path, capsys):
    base = ["index", "build", "--scenario", "driving_city", "--frames", "1", "--out", str(tmp_path / "i"),
            "--no-progress", "--device", "cpu", "--source", "detector"]
    assert main(base + ["--precision", "fp16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--precision fp16 needs a CUDA device" in err[0], err
    with pytest.raises(SystemExit) as e:
        main(base + ["--precision", "fp8"])
    assert e.value.code == 2 and "argument --precision: invalid choice: 'fp8'" in capsys.readouterr().err
    assert not (tmp_path / "i").exists()


def test_cli_compare_html_and_evaluate(tmp_path, capsys):
    """--compare puts each source's answer beside the labels' (numbers worked out from the tables here);
    --html writes the page; evaluate prints its tables and writes JSON."""
    import json

    rng = np.random.default_rng(8)
    n = 40
    labels = {"frame_id": np.arange(n), "Car": rng.integers(0, 8, n), "Pedestrian": rng.integers(0, 4, n),
              "Cyclist": rng.integers(0, 2, n)}
    detector = {**labels, "Car": np.maximum(labels["Car"] + rng.integers(-2, 2, n), 0)}
    out = tmp_path / "idx"
    idx = FrameIndex.create(out, labels)
    idx.append(detector, source="detector")
    assert main(["query", "retrieve", str(out), "--where", "Car>=5", "--compare"]) == 0
    printed = capsys.readouterr().out
    want = set(np.flatnonzero(labels["Car"] >= 5).tolist())
    got = set(np.flatnonzero(detector["Car"] >= 5).tolist())
    assert f"{len(got & want)} of the labels' {len(want)} found, {len(got - want)} not in them" in printed
    assert main(["query", "sum", str(out), "--class", "Car", "--compare"]) == 0
    printed = capsys.readouterr().out
    diff = int(detector["Car"].sum()) - int(labels["Car"].sum())
    assert f"detector  {int(detector['Car'].sum())}" in printed and f"{diff:+d}" in printed
    page = tmp_path / "answer.html"
    assert main(["query", "count", str(out), "--where", "Pedestrian>=2", "--source", "detector", "--html",
                 str(page), "--html-frames", "3"]) == 0
    printed = capsys.readouterr().out
    assert printed.splitlines()[0] == str(int((detector["Pedestrian"] >= 2).sum()))
    assert page.is_file() and "of" in printed.splitlines()[1] and "3 of" in printed.splitlines()[1]
    report = tmp_path / "eval.json"
    assert main(["query", "evaluate", str(out), "--groups", "4", "--queries", "20", "--group-frames", "5:10",
                 "--json", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "RETRIEVAL" in printed and "COUNT" in printed and "AGGREGATION" in printed
    data = json.loads(report.read_text())
    true, pred = int(labels["Car"].sum()), int(detector["Car"].sum())
    assert data["aggregation"]["true"]["Car"] == true and data["aggregation"]["pred"]["Car"] == pred
    assert data["aggregation"]["q_error"]["Car"] == pytest.approx(max(true, pred) / min(true, pred))
    assert data["frames"] == n


def test_kitti_scans_cropped_to_the_camera_view_unless_fov_all(tmp_path):
    """A model source on a KITTI folder sees the points the camera sees (what KITTI detectors are trained on and
    the labels cover): none behind the camera or outside the image; --fov all keeps the whole scan."""
    from lidarops.cli.query import _KittiLoader
    from lidarops.data.formats.kitti import KittiDataset, read_velodyne
    from lidarops.query.build import FrameError

    kitti_folder(tmp_path / "kitti", 2, seed=4, points=2000)
    data = KittiDataset(tmp_path / "kitti")
    calib = KittiCalib.default()
    for fid, name in ((100, "000100"), (101, "000101")):
        every = read_velodyne(tmp_path / "kitti" / "velodyne" / f"{name}.bin")
        kept = _KittiLoader(data, data.ids, needs_labels=False, fov=True)(fid).points.numpy()
        assert 0 < len(kept) < len(every) and (every[:, 0] < 0).any()
        # independently: in the rectified camera frame in front of the camera, projected inside 1242 x 375
        xyz1 = np.concatenate([kept[:, :3], np.ones((len(kept), 1))], 1).astype(np.float64)
        cam = xyz1 @ calib.Tr_velo_to_cam.T @ calib.R0_rect.T
        uvw = np.concatenate([cam, np.ones((len(cam), 1))], 1) @ calib.P2.T
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        assert (cam[:, 2] > 0).all() and (u >= -1e-3).all() and (u < 1242 + 1e-3).all()
        assert (v >= -1e-3).all() and (v < 375 + 1e-3).all()
        whole = _KittiLoader(data, data.ids, needs_labels=False, fov=False)(fid).points.numpy()
        np.testing.assert_array_equal(whole, every)
    (tmp_path / "kitti" / "calib" / "000101.txt").unlink()
    with pytest.raises(FrameError, match=r"frame 000101: no calibration .*--fov all"):
        _KittiLoader(data, data.ids, needs_labels=False, fov=True)(101)


def test_cli_fov_camera_needs_calib(tmp_path, capsys):
    import shutil

    kitti_folder(tmp_path / "kitti", 1)
    shutil.rmtree(tmp_path / "kitti" / "calib")
    base = ["index", "build", str(tmp_path / "kitti"), "--out", str(tmp_path / "idx"), "--no-progress",
            "--source", "detector", "--device", "cpu"]
    assert main(base) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no calib/ folder" in err[0] and "--fov all" in err[0], err
    assert not (tmp_path / "idx").exists()


def test_cli_retrieve_counts_prints_every_source_side_by_side(tmp_path, capsys):
    """``query retrieve --counts``: the shown frames' counts per class, labels first, each source's value as
    stored; a frame one source lacks shows '-'."""
    rng = np.random.default_rng(4)
    ids = np.arange(0, 30, 3)
    labels = {"frame_id": ids, **{c: rng.integers(0, 6, len(ids)) for c in CLASSES}}
    other = {"frame_id": ids[:-1], **{c: rng.integers(0, 6, len(ids) - 1) for c in CLASSES}}
    idx = FrameIndex.create(tmp_path / "idx", labels)
    idx.append(other, source="counter")
    assert main(["query", "retrieve", str(tmp_path / "idx"), "--where", "Car>=0", "--counts", "--show", "50"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[1] == "counts per frame (labels / counter):" and lines[2].split() == ["frame", *CLASSES]
    table = {int(line.split()[0]): line.split()[1:] for line in lines[3:]}
    assert sorted(table) == ids.tolist()
    for i, fid in enumerate(ids):
        for j, c in enumerate(CLASSES):
            want = f"{labels[c][i]} / " + (str(other[c][i]) if i < len(ids) - 1 else "-")
            assert " ".join(table[fid][3 * j:3 * j + 3]) == want, (fid, c)
