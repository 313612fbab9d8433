"""The benchmark machinery (benchmarks/common.py) and the benchmarks' result rows, on CPU: run counts that a
slow first call cannot cut short, result files that merge and keep errors, errors reported instead of blanked."""
from __future__ import annotations

import json
import sys
import time
import types
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import common  # noqa: E402


class SlowFirstCall:
    """A function whose first (cold) call sleeps ``first_s``; the later ones return at once."""

    def __init__(self, first_s: float):
        self.first_s, self.calls = first_s, 0

    def __call__(self):
        self.calls += 1
        if self.calls == 1:
            time.sleep(self.first_s)


KW = dict(min_runs=3, max_runs=12, budget_s=0.05, slow_single_s=2.0)


def test_time_cpu_run_count_does_not_depend_on_a_slow_first_call():
    warm = common.time_cpu(SlowFirstCall(0.0), (), **KW)
    cold = common.time_cpu(SlowFirstCall(0.3), (), **KW)
    assert warm.runs == KW["max_runs"]
    assert cold.runs == warm.runs, f"a slow first call cut the runs to {cold.runs}"
    assert max(cold.times_ms) < 300, "the cold call must not be among the timed runs"


def test_time_call_on_cpu_run_count_does_not_depend_on_a_slow_first_call():
    t = common.time_call(SlowFirstCall(0.3), (), "cpu", **KW)
    assert t.runs == KW["max_runs"]


def test_time_cpu_interleaved_gives_every_implementation_the_same_runs():
    fast, cold = SlowFirstCall(0.0), SlowFirstCall(0.3)
    timings = common.time_cpu_interleaved([(fast, ()), (cold, ())], **KW)
    assert [t.runs for t in timings] == [KW["max_runs"]] * 2
    assert fast.calls == cold.calls  # the same warm-up and run count


def test_time_cpu_interleaved_reports_an_error_in_place_of_a_timing():
    def boom():
        raise RuntimeError("not implemented for this device")

    timings = common.time_cpu_interleaved([(SlowFirstCall(0.0), ()), (boom, ())], **KW)
    assert isinstance(timings[0], common.Timing) and timings[0].runs == KW["max_runs"]
    assert isinstance(timings[1], RuntimeError)


def test_a_warm_call_slower_than_slow_single_counts_alone():
    t = common.time_cpu(lambda: time.sleep(0.02), (), min_runs=3, max_runs=10, budget_s=1.0, slow_single_s=0.01)
    assert t.runs == 1


def test_run_count_floor_and_ceiling():
    assert common._run_count(10.0, 3, 30, 1.0) == 3
    assert common._run_count(1e-9, 3, 30, 1.0) == 30
    assert common._run_count(0.1, 3, 30, 1.0) == 10


def test_write_results_merges_sections_and_keeps_errors(tmp_path):
    meta = {"device": "test cpu", "commit": "abc"}
    rows = [{"op": "a", "median_ms": 1.0, "status": "ok"},
            {"op": "b", "median_ms": None, "status": "error: RuntimeError: strided layers fail"}]
    path = common.write_results("one", "cpu", rows, meta, results_dir=tmp_path)
    assert path.parent == tmp_path
    common.write_results("two", "cpu", [{"op": "x", "median_ms": 2.0, "status": "ok"}], meta, results_dir=tmp_path)
    # a rerun of op "a" only: the row of op "b" (an error) stays
    common.write_results("one", "cpu", [{"op": "a", "median_ms": 0.5, "status": "ok"}], {"commit": "def"},
                         results_dir=tmp_path)
    data = json.loads(path.read_text())
    assert set(data["sections"]) == {"one", "two"}
    one = {r["op"]: r for r in data["sections"]["one"]["rows"]}
    assert one["a"]["median_ms"] == 0.5 and one["a"]["commit"] == "def"
    assert one["b"]["status"].startswith("error: RuntimeError") and one["b"]["commit"] == "abc"
    assert data["sections"]["two"]["rows"][0]["median_ms"] == 2.0


def test_results_dir_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("LIDAROPS_RESULTS_DIR", str(tmp_path))
    assert common.results_path("cpu").parent == tmp_path


def test_bm_voxelize_quick_cpu_writes_result_rows(tmp_path, capsys):
    from benchmarks import bm_voxelize

    assert bm_voxelize.main(["--device", "cpu", "--quick", "--points", "3000", "--json",
                             "--results-dir", str(tmp_path)]) == 0
    files = list(tmp_path.glob("*.json"))
    assert [f.name for f in files] == [common.results_path("cpu").name]
    data = json.loads(files[0].read_text())
    section = data["sections"]["voxelize"]
    assert section["meta"]["device_type"] == "cpu" and section["meta"]["points"] == 3000
    rows = section["rows"]
    impls = {r["impl"] for r in rows}
    assert {"lidarops.voxelize", "pure PyTorch", "lidarops PointToVoxel (compat face)"} <= impls
    for r in rows:
        assert r["status"] == "ok", r
        assert r["median_ms"] > 0 and r["runs"] >= 3
    # every implementation of a config gets the same run count (interleaved timing)
    for config in {r["config"] for r in rows}:
        assert len({r["runs"] for r in rows if r["config"] == config}) == 1
    assert all(r["same_as_lidarops"] for r in rows if r["impl"] == "pure PyTorch")
    assert "wrote" in capsys.readouterr().out


def test_bm_casnet_quick_cpu_writes_result_rows(tmp_path, capsys):
    from benchmarks import bm_casnet

    # a CAS-Net checkpoint of the quick size (segments of 512 = 64 x 8 points), timed beside the untrained ones
    torch.manual_seed(0)
    ckpt = bm_casnet.CASNet.fast(num_out=64).save(tmp_path / "casnet.pt")
    threads = torch.get_num_threads()
    assert bm_casnet.main(["--device", "cpu", "--quick", "--threads", "1", "--json", "--results-dir", str(tmp_path),
                           "--checkpoint", str(ckpt)]) == 0
    assert torch.get_num_threads() == threads
    data = json.loads((tmp_path / common.results_path("cpu").name).read_text())
    section = data["sections"]["casnet"]
    assert section["meta"]["device_type"] == "cpu" and section["meta"]["cloud"]["points"] == 2048
    rows = {r["op"]: r for r in section["rows"]}
    assert len(rows) == len(section["rows"]), "op names must be unique"
    sampling = [r for r in rows.values() if r["section"] == "sampling"]
    assert {r["case"] for r in sampling} == {"sampler", "CASNetSampler", "segment_and_sample",
                                             "CASNetSampler(whole=True)", "CASNetSampler(whole=True, raw)"}
    # random, FPS, chunked FPS; full, fast, both with chunk='fused', and the checkpoint, two rows each; the anchored
    # head's full and fast on the whole cloud, with and without distinct picks (the float16 autocast rows are CUDA only)
    assert len(sampling) == 3 + 2 * 5 + 2 * 2
    for r in sampling:
        assert r["status"] == "ok", r
        assert r["median_ms"] > 0 and r["N"] == 2048 and r.get("commit") == section["meta"].get("commit")
        if r["case"] not in ("segment_and_sample", "CASNetSampler(whole=True, raw)"):  # m = N // 8 distinct points
            assert r["m"] == 256 and r["distinct"] == 256, r
    graphs = [r for r in rows.values() if r["section"] == "cuda_graph"]
    assert graphs and all(r["status"].startswith("skipped (CUDA only") for r in graphs)
    whole = [r for r in rows.values() if r["section"] == "whole_cloud"]
    assert {(r["path"], r["step"]) for r in whole} == {(p, s) for p in ("whole", "whole, fused", "segmented")
                                                       for s in ("inference", "training")} | {
        ("whole, fused, fp16", "inference")}
    half = [r for r in whole if r["path"] == "whole, fused, fp16"]
    assert len(half) == 1 and half[0]["status"].startswith("skipped (CUDA only"), half
    for r in (r for r in whole if r not in half):
        assert r["status"] == "ok" and r["median_ms"] > 0 and r["m"] == r["N"] // 8, r
        assert "peak_mb" not in r  # CUDA only
    out = capsys.readouterr().out
    assert "== 1. sampling" in out and "== 3. whole cloud" in out and "wrote" in out


def test_bm_sparse_reports_errors_instead_of_blank_cells():
    from benchmarks import bm_sparse

    def boom(*_, **__):
        raise RuntimeError("spconv: stride 2 is not supported here\nmore lines")

    t = bm_sparse._try(boom, (), "cpu")
    assert t == "error: RuntimeError: spconv: stride 2 is not supported here"
    assert bm_sparse._cell(t) == "error"
    assert bm_sparse._row(t) == {"status": t, "median_ms": None}
    assert bm_sparse._cell(None) == "-" and bm_sparse._row(None) is None

    # a peer whose strided layer cannot even be built: the error, not None
    broken = types.SimpleNamespace(SparseConv2d=boom, SubMConv2d=boom)
    idx = bm_sparse.bev_sites((32, 32), 50)
    x = bm_sparse.SparseConvTensor(torch.randn(idx.shape[0], 4), idx, [32, 32], 1)
    status = bm_sparse._module_layer_time(broken, "conv", x, torch.randn(4, 3, 3, 4), "cpu")
    assert isinstance(status, str) and status.startswith("error: RuntimeError")


@pytest.mark.parametrize("kind", ["subm", "conv"])
def test_bm_sparse_lidarops_module_row_is_timed(kind):
    from benchmarks import bm_sparse

    idx = bm_sparse.bev_sites((32, 32), 50)
    x = bm_sparse.SparseConvTensor(torch.randn(idx.shape[0], 4), idx, [32, 32], 1)
    t = bm_sparse._module_layer_time(bm_sparse.lspconv, kind, x, torch.randn(4, 3, 3, 4), "cpu")
    assert isinstance(t, common.Timing) and t.median > 0


def test_report_reads_every_section_and_shows_errors(tmp_path):
    from benchmarks import report

    meta = {"device": "test cpu", "device_type": "cpu", "commit": "abc"}
    common.write_results("sparse", "cpu", [
        {"section": "layer", "op": "layer/x", "grid": "drone", "lidarops": {"median_ms": 0.5},
         "spconv": {"status": "error: RuntimeError: strided", "median_ms": None}, "dense_cudnn": None}],
        meta, results_dir=tmp_path)
    common.write_results("voxelize", "cpu", [
        {"op": "p/a", "config": "p", "impl": "a", "status": "ok", "median_ms": 1.5, "ratio": 1.0},
        {"op": "p/b", "config": "p", "impl": "b", "status": "error: ValueError: no", "median_ms": None}],
        meta, results_dir=tmp_path)
    assert report.sections_in(tmp_path) == ["sparse", "voxelize"]
    text = report.section_markdown("sparse", report.load(tmp_path, "sparse"))
    assert "| drone | 0.500 | error |" in text
    text = report.section_markdown("voxelize", report.load(tmp_path, "voxelize"))
    assert "| p | a | ok | 1.50 | 1.0x |" in text and "| p | b | error: ValueError: no | error |" in text


def test_bm_counternet_quick_cpu_writes_result_rows(tmp_path, capsys):
    from benchmarks import bm_counternet

    threads = torch.get_num_threads()
    assert bm_counternet.main(["--device", "cpu", "--quick", "--threads", "1", "--json",
                               "--results-dir", str(tmp_path)]) == 0
    assert torch.get_num_threads() == threads
    data = json.loads((tmp_path / common.results_path("cpu").name).read_text())
    section = data["sections"]["counternet"]
    assert section["meta"]["device_type"] == "cpu" and section["meta"]["frames"]["frames"] == 2
    assert section["meta"]["batch"] == 2
    rows = {r["op"]: r for r in section["rows"]}
    assert len(rows) == len(section["rows"]), "op names must be unique"
    models = ("CN_pt=1", "CN_pt=4^o", "PointPillars counter")
    assert {(r["model"], r["case"]) for r in rows.values()} == (
        {(m, c) for m in models for c in ("latency", "throughput")} | {(m, "postprocess") for m in models[:2]})
    for r in rows.values():
        assert r["status"] == "ok", r
        assert r["median_ms"] > 0 and r.get("commit") == section["meta"].get("commit")
        if r["case"] == "postprocess":
            assert 0 < r["share_of_latency"] <= 1
        else:
            assert r["frames_per_s"] == pytest.approx(r["batch"] * 1e3 / r["median_ms"], rel=1e-3)
    out = capsys.readouterr().out
    assert "== CounterNet vs the PointPillars counter" in out and "wrote" in out


def _counts_index(root, frames, cars, source="detector"):
    from lidarops.query import FrameIndex

    return FrameIndex.create(root, {"frame_id": list(frames), "Car": list(cars), "Pedestrian": [1] * len(frames)},
                             source=source)


def test_bm_scaling_union_check_finds_missing_duplicated_and_changed_frames(tmp_path):
    """compare_indexes: a faithful union passes; a frame left out, a frame counted differently and a part
    written twice (two ranks counting the same frames) are each found."""
    pytest.importorskip("duckdb")
    import shutil

    from benchmarks.bm_scaling import compare_indexes

    _counts_index(tmp_path / "one", range(10), range(10))
    _counts_index(tmp_path / "same", range(10), range(10))
    assert compare_indexes(tmp_path / "one", tmp_path / "same", range(10)) == {
        "frames": 10, "missing": 0, "extra": 0, "duplicated": 0, "counts_differ": 0, "compared": 10}
    cars = list(range(9))
    cars[3] = 7
    _counts_index(tmp_path / "bad", range(9), cars)
    got = compare_indexes(tmp_path / "one", tmp_path / "bad", range(10))
    assert (got["missing"], got["extra"], got["duplicated"], got["counts_differ"]) == (1, 0, 0, 1)
    _counts_index(tmp_path / "twice", range(10), range(10))
    parts = tmp_path / "twice" / "counts" / "detector"
    shutil.copy(next(parts.glob("*.parquet")), parts / "part-r001-00000.parquet")
    got = compare_indexes(tmp_path / "one", tmp_path / "twice", list(range(10)) + [11])
    assert (got["frames"], got["missing"], got["duplicated"], got["counts_differ"]) == (20, 1, 10, 0)


@pytest.mark.slow
def test_bm_scaling_allreduce_probe_under_torchrun(tmp_path, capsys):
    """The all-reduce bound, as the benchmark launches it: 2 gloo processes under torchrun, the sum checked
    inside the probe, one row with the detector's gradient size."""
    from benchmarks import bm_scaling

    argv = sys.argv
    sys.argv = ["bm_scaling.py", "--device", "cpu", "--gpus", "1,2", "--tasks", "allreduce", "--work", str(tmp_path)]
    try:
        assert bm_scaling.main() == 0
    finally:
        sys.argv = argv
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [(r["case"], r["gpus"]) for r in rows] == [("allreduce_pointpillars", 2)]
    assert rows[0]["parameters"] > 4_000_000 and rows[0]["allreduce_ms"] > 0


def test_bm_sim2real_counts_false_positives_in_dontcare_regions_as_kitti_does():
    """KITTI's evaluation ignores a detection whose 2D box lies more than half inside a DontCare box: a box over a
    detection's whole projection overlaps it 1, one over its left part in proportion, one elsewhere 0; frame_figures
    leaves the ignored ones out of its second count only; fp_rows lists the false positives above 0.5 with what is
    under them."""
    import numpy as np

    from benchmarks.bm_sim2real import dontcare_overlap, fp_rows, frame_figures
    from lidarops.data.formats.kitti import KITTI_IMAGE_SIZE, KittiCalib, _image_boxes

    calib = KittiCalib.default()
    det = np.array([[15.0, 0.0, -0.8, 4.0, 1.7, 1.5, 0.0], [30.0, 8.0, -0.8, 0.8, 0.6, 1.7, 0.0]])
    (u0, v0, u1, v1), other = _image_boxes(det, calib, KITTI_IMAGE_SIZE)[0].astype(np.float64)
    assert u1 - u0 > 10 and v1 - v0 > 10 and other[2] < u0 - 5  # the second box: left of the first
    for dc, want in (([[u0 - 5, v0 - 5, u1 + 5, v1 + 5]], 1.0), ([[u0 - 5, v0 - 5, (u0 + u1) / 2, v1 + 5]], 0.5),
                     ([[0, 0, 5, 5]], 0.0)):
        got = dontcare_overlap(det, calib, np.array(dc, np.float64))
        assert abs(got[0] - want) < 1e-4 and got[1] == 0, (got, want)
    assert dontcare_overlap(det, calib, np.zeros((0, 4))).tolist() == [0.0, 0.0]
    gt = np.array([[5.0, 3.0, -0.9, 0.8, 0.6, 1.7, 0.0]])
    out = frame_figures(gt, ["Pedestrian"], det, np.array([0.6, 0.4]), ["Car", "Pedestrian"],
                        det_dontcare=np.array([0.9, 0.2]))
    assert out["fp"] == {0.3: 2, 0.5: 1} and out["fp_outside_dontcare"] == {0.3: 1, 0.5: 0}
    points = np.array([[15.0, 0.2, -1.5, 0.1], [15.5, -0.5, 0.0, 0.2], [17.5, 0.0, 0.0, 0.3], [30.0, 8.0, 0.0, 0.4]])
    (row,) = fp_rows("000001", points, det, np.array([0.6, 0.4]), ["Car", "Pedestrian"], out["alone"],
                     np.array([0.9, 0.2]))
    assert (row["frame"], row["class"], row["range_m"], row["returns"], row["dontcare"]) == ("000001", "Car", 15.0, 2, 0.9)
    assert row["height_span_m"] == 1.5 and row["bottom_m"] == -1.55


def test_bm_sim2real_profiles_with_fields_and_simulated_frames_alone(capsys):
    """``--realism kitti:roadside_structures=0.7`` is the kitti profile with that field changed; a field that is
    not one, or a value out of range, is refused naming it; ``--real none --sim-detect`` runs a detector on the
    simulated frames alone and prints its counts."""
    import dataclasses

    import numpy as np

    from benchmarks.bm_sim2real import main, parse_profile, seen_labels
    from lidarops.data.realism import make_realism

    boxes = np.array([[10.0, 0, 0, 4, 2, 2, 0], [-10.0, 0, 0, 4, 2, 2, 0], [20.0, 5, 0, 1, 1, 2, 0]])
    points = np.array([[10.5, 0.2, 0.1, 0.3], [19.9, 5.1, 0.5, 0.1], [30.0, 0, 0, 0]])
    got, names = seen_labels(points, boxes, ["Car", "Car", "Pedestrian"])
    np.testing.assert_array_equal(got, boxes[[0, 2]])  # the car with no return is not labelled
    assert names == ["Car", "Pedestrian"]

    assert parse_profile(None) is None and parse_profile("none") is None and parse_profile("kitti") == "kitti"
    got = parse_profile("kitti_dr:roadside_structures=0.5,low_clutter=1")
    assert got == dataclasses.replace(make_realism("kitti_dr"), roadside_structures=0.5, low_clutter=1.0)
    with pytest.raises(ValueError, match="no_such_field"):
        parse_profile("kitti:no_such_field=1")
    with pytest.raises(ValueError, match="roadside_structures"):
        parse_profile("kitti:roadside_structures=11")
    with pytest.raises(SystemExit):
        main(["--real", "none", "--realism", "kitti:roadside_structures"])
    with pytest.raises(SystemExit):
        main(["--real", "none"])  # nothing to measure
    capsys.readouterr()
    assert main(["--real", "none", "--sim-detect", "--sim-frames", "1", "--checkpoint", "pointpillars_synth",
                 "--realism", "kitti:roadside_structures=1"]) == 0
    out = capsys.readouterr().out
    assert "on 1 simulated frames (kitti:roadside_structures=1)" in out and "false positives per frame" in out


def test_bm_sim2real_frame_figures_on_a_hand_made_frame():
    """A car detected 0.4 m too low (3D IoU 1.1 / 1.9 = 0.58: found at 0.5, not at 0.7; found in bird's-eye
    view), a second detection of it (one-to-one: not found twice, not a false positive), a detection on a
    labelled Van (not a Car, not a false positive), and two detections on nothing (false positives at 0.55
    and 0.4)."""
    import numpy as np

    from benchmarks.bm_sim2real import frame_figures

    car = [10.0, 0.0, -0.8, 4.0, 1.7, 1.5, 0.0]
    gt = np.array([car, [5.0, 3.0, -0.9, 0.8, 0.6, 1.7, 0.0], [20.0, 5.0, -0.6, 5.0, 2.0, 2.0, 0.3]])
    low = car[:2] + [car[2] - 0.4] + car[3:]
    det = np.array([low, low, [20.0, 5.0, -0.6, 5.0, 2.0, 2.0, 0.3], [40.0, -10.0, -0.8, 4.0, 1.7, 1.5, 0.0],
                    [5.0, 6.0, -0.9, 0.8, 0.6, 1.7, 0.0]])
    scores = np.array([0.9, 0.6, 0.8, 0.55, 0.4])
    out = frame_figures(gt, ["Car", "Pedestrian", "Van"], det, scores, ["Car", "Car", "Car", "Car", "Pedestrian"])
    assert out["labelled"] == {"Car": 1, "Pedestrian": 1, "Cyclist": 0}
    assert out["found"][("Car", "3d", 0.5)] == 1 and out["found"][("Car", "3d", 0.7)] == 0
    assert out["found"][("Car", "bev", 0.5)] == 1 and out["found"][("Pedestrian", "bev", 0.5)] == 0
    assert out["fp"] == {0.3: 2, 0.5: 1}
    np.testing.assert_allclose(out["errors"]["Car"], [[-0.4, -0.4, -0.4, 0.0, 0.0, 0.0]], atol=1e-9)
    assert out["errors"]["Pedestrian"].shape == (0, 6)
    # the car is taken for a car, the pedestrian (a detection 3 m off) for nothing, the Van is not counted
    assert out["taken_for"] == {("Car", "Car"): 1, ("Pedestrian", "none"): 1}
    ped = np.array([[5.0, 3.0, -0.9, 0.8, 0.6, 1.7, 0.0]])
    out = frame_figures(ped, ["Pedestrian"], np.array([[5.1, 3.0, -0.9, 1.6, 0.6, 1.7, 0.0], ped[0]]),
                        np.array([0.7, 0.2]), ["Cyclist", "Pedestrian"])
    assert out["taken_for"] == {("Pedestrian", "Cyclist"): 1}  # the higher score decides
    # the car hard (difficulty 2): it leaves the easy-and-moderate count; moderate, it stays in it
    for level, counted in ((2, 0), (1, 1)):
        out = frame_figures(gt, ["Car", "Pedestrian", "Van"], det, scores, ["Car", "Car", "Car", "Car", "Pedestrian"],
                            np.array([level, 0, 0]))
        assert out["labelled_em"]["Car"] == counted and out["found_em"]["Car"] == counted
        assert out["labelled_em"]["Pedestrian"] == 1 and out["found_em"]["Pedestrian"] == 0


def test_bm_sim2real_score_curve_by_hand(tmp_path):
    """Two frames: a car found at score 0.9, a pedestrian found at 0.4, a false positive at 0.6 inside a DontCare
    region and one at 0.35 outside; kept at >= 0.3 / 0.5 / 0.7 / 0.95 a user sees, per class and per frame, what is
    counted by hand here; the plot is written."""
    import numpy as np

    from benchmarks.bm_sim2real import plot_curves, score_curve

    car = [10.0, 0.0, -0.8, 4.0, 1.7, 1.5, 0.0]
    ped = [5.0, 3.0, -0.9, 0.8, 0.6, 1.7, 0.0]
    nowhere = [[40.0, -10.0, -0.8, 4.0, 1.7, 1.5, 0.0], [30.0, 12.0, -0.9, 0.8, 0.6, 1.7, 0.0]]
    frames = [(np.array([car]), ["Car"], np.array([0]), np.array([car, nowhere[0]]), np.array([0.9, 0.6]),
               ["Car", "Car"], np.array([0.0, 0.8])),
              (np.array([ped]), ["Pedestrian"], np.array([1]), np.array([ped, nowhere[1]]), np.array([0.4, 0.35]),
               ["Pedestrian", "Pedestrian"], np.array([0.0, 0.1]))]
    cv = score_curve(frames, (0.3, 0.5, 0.7, 0.95))
    assert cv["labelled_em"] == {"Car": 1, "Pedestrian": 1, "Cyclist": 0}
    assert cv["found_em"] == {"Car": [1, 1, 1, 0], "Pedestrian": [1, 0, 0, 0], "Cyclist": [0, 0, 0, 0]}
    assert cv["fp_per_frame"] == [1.0, 0.5, 0.0, 0.0]  # 2, 1, 0, 0 over 2 frames
    assert cv["fp_per_frame_outside_dontcare"] == [0.5, 0.0, 0.0, 0.0]
    plot_curves({"hand": cv}, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000


def test_bm_sim2real_cyclist_head_offset_by_hand():
    """A cyclist heading along +y (yaw 90 degrees, 1.8 m long): its top returns (z within a fifth of the span of the
    highest) at y = 0.3 and 0.1 below its centre lie 0.2 m behind it, -0.2 / 0.9 of half its length; the low
    returns do not count; a cyclist with fewer than ``least`` returns and a pedestrian give nothing."""
    import numpy as np

    from benchmarks.bm_sim2real import cyclist_head_offset

    boxes = np.array([[5.0, 2.0, -0.9, 1.8, 0.6, 1.7, np.pi / 2], [20.0, 0.0, -0.9, 1.8, 0.6, 1.7, 0.0],
                      [5.0, 10.0, -0.9, 0.8, 0.6, 1.7, 0.0]])
    low = [[5.0, 2.0 + y, -1.6, 0.1] for y in (-0.8, 0.8, 0.0)]
    top = [[5.0, 1.7, -0.1, 0.2], [5.05, 1.9, -0.15, 0.2]]   # within 0.2 x 1.5 m of the highest (-0.1)
    far = [[20.0, 0.0, -0.5, 0.1]] * 3
    ped = [[5.0, 10.0, -0.5, 0.1]] * 20
    points = np.array(low + top + far + ped)
    got = cyclist_head_offset(points, boxes, ["Cyclist", "Cyclist", "Pedestrian"], least=5)
    np.testing.assert_allclose(got, [-0.2 / 0.9], atol=1e-9)
    assert cyclist_head_offset(points, boxes, ["Pedestrian"] * 3, least=5) == []


def test_bm_sim2real_aspect_and_box_frame_by_hand():
    """The aspect folds the heading against the ray to [0, 90] degrees; points go into a box's frame (x along its
    heading, z from its bottom) and back."""
    import numpy as np

    from benchmarks.bm_sim2real import aspect_deg, from_box_frame, to_box_frame

    for box, want in (([10, 0, 0, 1, 1, 1, 0.0], 0), ([10, 0, 0, 1, 1, 1, np.pi / 2], 90), ([10, 0, 0, 1, 1, 1, np.pi], 0),
                      ([0, 10, 0, 1, 1, 1, 0.0], 90), ([10, 10, 0, 1, 1, 1, np.pi / 4], 0),
                      ([10, 10, 0, 1, 1, 1, -np.pi / 4], 90), ([10, 0, 0, 1, 1, 1, np.radians(-30)], 30),
                      ([-10, 0, 0, 1, 1, 1, np.radians(150)], 30)):
        assert abs(aspect_deg(box) - want) < 1e-9, (box, aspect_deg(box))
    box = [10.0, 5.0, 1.0, 4.0, 2.0, 2.0, np.pi / 2]
    local = to_box_frame(np.array([[10.0, 6.0, 0.5, 0.3]]), box)
    np.testing.assert_allclose(local, [[1.0, 0.0, 0.5, 0.3]], atol=1e-12)  # 1 m ahead along +y, 0.5 m up
    pts = np.random.default_rng(0).normal(size=(20, 4))
    np.testing.assert_allclose(from_box_frame(to_box_frame(pts, box), box), pts, atol=1e-5)


def test_bm_sim2real_cyclist_aspects_counts_and_placement(monkeypatch):
    """Simulated cyclists are counted by aspect in their own frames (those with fewer than 15 returns or beyond
    45 m left out); on a real frame each road spot without a label within 2.5 m gets one cyclist riding along the
    road and one across it, on the local ground, with its returns moved inside its new box."""
    import numpy as np

    from benchmarks import bm_sim2real as b

    rng = np.random.default_rng(1)

    def cyclist(box, n):  # n returns inside a box (x, y, z centre, l, w, h, yaw)
        local = np.c_[rng.uniform(-0.8, 0.8, n) * box[3] / 2, rng.uniform(-0.8, 0.8, n) * box[4] / 2,
                      rng.uniform(0.1, 0.9, n) * box[5], rng.uniform(0, 1, n)]
        return b.from_box_frame(local, box)

    along = np.array([21.0, -2.0, -0.8, 1.8, 0.6, 1.7, 0.1])       # aspect about 11 degrees
    across = np.array([24.0, 2.0, -0.8, 1.8, 0.6, 1.7, 1.6])       # about 78 degrees
    sparse = np.array([15.0, 0.0, -0.8, 1.8, 0.6, 1.7, 0.0])       # 5 returns: left out
    far = np.array([60.0, 0.0, -0.8, 1.8, 0.6, 1.7, 0.0])          # beyond 45 m: left out
    sim_pts = np.r_[cyclist(along, 40), cyclist(across, 30), cyclist(sparse, 5), cyclist(far, 40)]
    ped_a, ped_b = np.array([12.0, 5.0, -1.0, 0.6, 0.6, 1.7, 0.0]), np.array([12.0, 6.0, -1.0, 0.6, 0.6, 1.7, 0.0])
    ped_c = np.array([12.0, -6.0, -1.0, 0.6, 0.6, 1.7, 0.0])       # 1.0 m apart: a group of two; c alone
    sim_pts = np.r_[sim_pts, cyclist(ped_a, 12), cyclist(ped_b, 12), cyclist(ped_c, 12)]
    sim = [("sim0", sim_pts, np.array([along, across, sparse, far, ped_a, ped_b, ped_c]),
            ["Cyclist"] * 4 + ["Pedestrian"] * 3)]
    ground = np.c_[rng.uniform(15, 30, 4000), rng.uniform(-6, 6, 4000), np.full(4000, -1.7), np.zeros(4000)]
    label = np.array([[25.5, 3.5, -0.9, 4.0, 1.8, 1.6, 0.0]])      # a car within 2.5 m of the second spot
    real = [("r0", ground, label, ["Car"], np.zeros(1), None, np.zeros((0, 4))),
            ("r1", ground, np.zeros((0, 7)), [], np.zeros(0), None, np.zeros((0, 4)))]
    seen = []

    def fake_taken_as(model, points, box):
        inside = b._in_box(points, box)
        seen.append((round(b.aspect_deg(box)), int(inside.sum()), float(box[2] - box[5] / 2)))
        return "Cyclist" if b.aspect_deg(box) < b.BROADSIDE else "Pedestrian"

    monkeypatch.setattr(b, "taken_as", fake_taken_as)
    got = b.cyclist_aspects(None, sim, real, per_spot=1)
    assert got["sim_along"] == {"Car": 0, "Pedestrian": 0, "Cyclist": 1, "none": 0}
    assert got["sim_broadside"]["Pedestrian"] == 1 and sum(got["sim_broadside"].values()) == 1
    # r0: the first spot only (a car near the second); r1: both spots; each an along and a broadside cyclist
    assert sum(got["placed_real_along"].values()) == 3 and got["placed_real_along"]["Cyclist"] == 3
    assert sum(got["placed_real_broadside"].values()) == 3 and got["placed_real_broadside"]["Pedestrian"] == 3
    assert sum(got["sim_pedestrian_in_group"].values()) == 2 and sum(got["sim_pedestrian_alone"].values()) == 1
    placed = seen[5:]
    for aspect, n, bottom in placed:
        assert n in (40, 30) and abs(bottom - (-1.7)) < 1e-6  # every return moved along, the box on the ground
    assert [a for a, _, _ in placed] == [round(b.aspect_deg(along)), round(b.aspect_deg(across))] * 3
    seen.clear()
    got = b.cyclist_aspects(None, sim, real, per_spot=2)  # each of the two cyclists at every spot, nearest first
    assert sum(got["placed_real_along"].values()) == 6 and sum(got["placed_real_broadside"].values()) == 6
    assert [a for a, _, _ in seen[5:9]] == [round(b.aspect_deg(along)), round(b.aspect_deg(across)),
                                            round(b.aspect_deg(across)), round(b.aspect_deg(along))]


def test_bm_sim2real_object_grades_by_hand():
    """A car 20 m ahead whose label's bottom is 0.5 m above the ground under the sensor (the 5th percentile of the
    returns within 8 m, -1.7 here) stands on a 2.5 % grade, a cyclist 30 m ahead to the side 0.3 m below it on -1 %;
    a pedestrian 5 m away, a car behind the sensor and a van are not counted; without returns near the sensor there
    is no ground to measure."""
    import numpy as np

    from benchmarks.bm_sim2real import object_grades

    ground = [[x, y, -1.7, 0.1] for x in np.linspace(1, 5, 10) for y in (-2.0, 2.0)]
    points = np.array(ground + [[3.0, 0.0, -1.0, 0.1]])  # one raised return: the 5th percentile keeps the ground
    boxes = np.array([[20.0, 0.0, -1.2 + 0.75, 4.0, 1.6, 1.5, 0.0], [18.0, 24.0, -2.0 + 0.85, 1.8, 0.6, 1.7, 0.0],
                      [5.0, 0.0, -0.8, 0.8, 0.6, 1.7, 0.0], [-20.0, 0.0, -0.5, 4.0, 1.6, 1.5, 0.0],
                      [25.0, 0.0, -0.5, 4.5, 1.8, 2.0, 0.0]])
    got = object_grades(points, boxes, ["Car", "Cyclist", "Pedestrian", "Car", "Van"])
    np.testing.assert_allclose(got, [0.5 / 20.0, -0.3 / 30.0], atol=1e-9)
    assert object_grades(points[-1:], boxes, ["Car"] * 5) == []


def test_sscater_sparsity_figures_by_hand():
    """Two 2 x 2 maps of 3 channels: one site changes one channel, another two; zeros counted over everything."""
    from benchmarks.sscater_sparsity import figures

    prev = torch.zeros(2, 2, 3)
    prev[0, 0] = torch.tensor([1.0, 0.0, 2.0])
    feats = prev.clone()
    feats[0, 0, 1] = 5.0           # site (0, 0): one channel of three changed
    feats[1, 1] = torch.tensor([0.0, 3.0, 4.0])  # site (1, 1): two of three
    zeros, changed, zero_delta, any_change = figures(feats, prev).tolist()
    assert zeros == pytest.approx(7 / 12)       # 12 values; non-zero: 1, 5, 2 at (0, 0) and 3, 4 at (1, 1)
    assert changed == pytest.approx(2 / 4)
    assert zero_delta == pytest.approx(3 / 6)   # at the two changed sites, 6 channels, 3 unchanged
    assert any_change == 1.0
    assert figures(prev, prev).tolist()[1:] == [0.0, 0.0, 0.0]


def test_bm_sscater_detector_section_times_the_same_boxes():
    from benchmarks import bm_sscater

    rows = []
    summary = bm_sscater.bench_detector(torch.device("cpu"), steps=6, every=3, checkpoint="shipped", rows=rows)
    assert len(rows) == 1 and rows[0]["op"] == "detector_stream/driving_city/pointpillars_synth"
    # the streamed boxes equal the detector's on every checked step, and the PFN ran on the changed pillars only
    assert summary["checked"] == 2 and summary["same_boxes"] == 2
    assert 0 < summary["pfn_saved"] < 1 and 0 < summary["pillars_changed_share"] < 1
    for name in ("sscater_step", "detector_predict", "sscater_backbone", "detector_backbone"):
        s = summary[name]
        assert 0 < s["median_ms"] <= s["p95_ms"] and s["mean_ms"] > 0, name


def test_kernel_totals_leave_out_the_ranges_gpu_annotations():
    """A record_function range appears on the GPU's timeline too, as an annotation spanning its kernels and the
    gaps between them: counting it as a kernel inflated profile/detector.py's stage sums several times over."""
    from benchmarks.profile_eager import kernel_totals

    def event(name, device, us, annotation=False):
        span = types.SimpleNamespace(elapsed_us=lambda: us)
        return types.SimpleNamespace(name=name, device_type=f"DeviceType.{device}", is_user_annotation=annotation,
                                     time_range=span)

    events = [event("backbone", "CPU", 900.0, annotation=True), event("backbone", "CUDA", 800.0, annotation=True),
              event("conv_kernel", "CUDA", 300.0), event("conv_kernel", "CUDA", 100.0), event("aten::mm", "CPU", 50.0)]
    assert kernel_totals(events, calls=2) == [("conv_kernel", 200.0, 1.0)]


class _FakeClock:
    """Events stamped by a counter of calls made so far: a call's "time" is how many calls it made."""

    def __init__(self):
        self.now, self.syncs = 0, 0

    def event(self):
        clock = self

        class Event:
            def record(self):
                self.t = clock.now

            def elapsed_time(self, end):
                return float(end.t - self.t)

        return Event()

    def sync(self):
        self.syncs += 1


def test_time_cuda_interleaved_takes_turns_and_reports_errors():
    """The implementations' timed calls alternate (A, B, A, B, ...), each gets the same runs, an event pair
    brackets each call alone, and a failing implementation reports its exception in its place."""
    clock = _FakeClock()
    order = []

    def impl(name, cost):
        def fn():
            order.append(name)
            clock.now += cost
        return fn

    def boom():
        raise RuntimeError("no kernel for this")

    calls = [(impl("a", 1), ()), (boom, ()), (impl("c", 3), ())]
    out = common.time_cuda_interleaved(calls, warmup=2, min_runs=4, max_runs=4, budget_s=1e-9, clock=clock)
    assert isinstance(out[1], RuntimeError)
    a, c = out[0], out[2]
    assert a.runs == c.runs == 4 and a.times_ms == [1.0] * 4 and c.times_ms == [3.0] * 4
    # each: a cold call and 2 warm-up calls, in turn; then the timed calls alternate
    assert order[:6] == ["a"] * 3 + ["c"] * 3 and order[6:] == ["a", "c"] * 4, order


def test_time_cuda_interleaved_idle_and_rotated():
    """``idle`` synchronises before every timed call; ``rotate`` turns the order each round, so that each
    implementation follows each other one. Without them the calls go in one order, back to back."""
    def logged(**kw):
        clock, log = _FakeClock(), []
        clock.sync = lambda: log.append("|")

        def impl(name):
            def fn():
                log.append(name)
                clock.now += 1
            return fn

        out = common.time_cuda_interleaved([(impl("a"), ()), (impl("b"), ()), (impl("c"), ())], warmup=1,
                                           min_runs=3, max_runs=3, budget_s=1e-9, clock=clock, **kw)
        assert [t.times_ms for t in out] == [[1.0] * 3] * 3
        return "".join(log)

    # after the warm-up (each implementation's cold and warm calls): rounds a b c, b c a, c a b, each after a sync
    assert logged(idle=True, rotate=True).endswith("|a|b|c|b|c|a|c|a|b|")
    assert logged().endswith("|c|abcabcabc|")


def test_time_cuda_interleaved_in_blocks():
    """``block``: each implementation's turn is that many calls in a row, the first untimed (it pays for the switch
    from the other implementation), the rest timed; whole turns until each has at least the common run count."""
    clock, log = _FakeClock(), []
    cost = {"a": 1, "b": 2}

    def impl(name):
        def fn():
            log.append(name)
            clock.now += cost[name] + (5 if len(log) > 1 and log[-2] != name else 0)  # a switch costs 5 more
        return fn

    out = common.time_cuda_interleaved([(impl("a"), ()), (impl("b"), ()), ], warmup=1, min_runs=5, max_runs=5,
                                       budget_s=1e-9, clock=clock, block=3, rotate=True)
    # 5 runs in turns of 2 timed calls: 3 turns each, 6 timed calls, none of them a switch
    assert [t.times_ms for t in out] == [[1.0] * 6, [2.0] * 6]
    assert "".join(log[4:]) == "aaabbbbbbaaaaaabbb", log  # after the cold and warm-up calls: a, b, b, a, a, b
    with pytest.raises(ValueError, match="block must be an int >= 1"):
        common.time_cuda_interleaved([(impl("a"), ())], clock=clock, block=0)


def test_time_cuda_interleaved_fails_mid_run_in_place():
    clock = _FakeClock()
    n = {"calls": 0}

    def flaky():
        n["calls"] += 1
        clock.now += 1
        if n["calls"] == 6:  # cold, 2 warm-up, then the third timed call fails
            raise ValueError("late failure")

    out = common.time_cuda_interleaved([(flaky, ()), (lambda: None, ())], warmup=2, min_runs=5, max_runs=5,
                                       budget_s=1e-9, clock=clock)
    assert isinstance(out[0], ValueError) and isinstance(out[1], common.Timing) and out[1].runs == 5
    assert n["calls"] == 6  # not called again after it failed


def test_bm_sparse_interleaved_cells_keep_missing_and_report_errors():
    from benchmarks import bm_sparse

    def boom():
        raise RuntimeError("spconv: no such layer\nmore")

    out = bm_sparse._try_interleaved([(lambda: None, ()), None, (boom, ())], "cpu", min_runs=3, max_runs=3,
                                     budget_s=1e-9)
    assert isinstance(out[0], common.Timing) and out[0].runs == 3
    assert out[1] is None and bm_sparse._cell(out[1]) == "-"
    assert out[2] == "error: RuntimeError: spconv: no such layer"


def test_bm_sparse_eager_section_on_cpu(capsys):
    """The eager section end to end on the CPU (no spconv there: its column is "-"), rows with the timing."""
    from benchmarks import bm_sparse

    rows = []
    bm_sparse.bench_eager("cpu", ("fp32",), True, rows)
    (row,) = rows
    assert row["timing"] == "the columns' calls interleaved" and row["subm_with_map"]["spconv"] is None
    assert row["subm_with_map"]["lidarops"]["median_ms"] > 0 and row["down_path_16_layers"]["lidarops"]["median_ms"] > 0
    assert "drone" in capsys.readouterr().out


def test_sscater_tools_stream_the_profile_the_detector_was_trained_on(monkeypatch):
    """bm_sscater, sscater_sparsity and sscater_work_bound stream a checkpoint's scene with the realism profile its
    first training frames of that scene were made with, unless --realism says otherwise (none: ray-cast)."""
    from benchmarks import sscater_sparsity
    from benchmarks.bm_sscater import stream_realism
    from benchmarks.profile import sscater_work_bound
    from lidarops.data import synthetic

    assert stream_realism("aerial_pointpillars", "drone_bridge", None) == "avia"
    assert stream_realism("aerial_pointpillars", "drone_bridge", "none") is None
    assert stream_realism("aerial_pointpillars", "drone_bridge", "kitti") == "kitti"
    assert stream_realism("pointpillars_synth", "driving_city", None) is None  # trained on ray-cast frames

    seen = []

    class Stop(Exception):
        pass

    class Recording(synthetic.Simulator):
        def __init__(self, scenario, seed=0, realism=None, **kw):
            seen.append((scenario, realism))
            raise Stop

    monkeypatch.setattr(synthetic, "Simulator", Recording)
    for argv in ([], ["--realism", "none"]):
        with pytest.raises(Stop):
            sscater_sparsity.main(["--device", "cpu", "--steps", "12", "--checkpoint", "aerial_pointpillars"] + argv)
        with pytest.raises(Stop):
            sscater_work_bound.main(["--checkpoint", "aerial_pointpillars", "--steps", "1"] + argv)
    assert seen == [("drone_bridge", "avia")] * 2 + [("drone_bridge", None)] * 2
    with pytest.raises(SystemExit):  # the random-weights mode has no profile to stream
        sscater_work_bound.main(["--realism", "avia"])


@pytest.mark.parametrize("name, cls, box", [
    ("pointpillars_synth", "Car", [15.0, 1.0, -0.9, 3.9, 1.6, 1.56, 0.1]),        # labels of the camera's view
    ("aerial_pointpillars", "Drone", [20.0, -30.0, 4.0, 0.7, 0.7, 0.3, 0.4])])    # of the sensor's whole view
def test_stream_ap_scores_the_windows_as_detect_does(name, cls, box):
    """bm_sscater's detection AP of SSCATeR against the detector: boxes equal to the labels score 100 (45 objects:
    R40 can reach it), none score 0, the same boxes on both sides the same figures; for a whole-view model an
    object outside the camera's view still counts."""
    import numpy as np

    from benchmarks.bm_sscater import _checkpoint_path, stream_ap
    from lidarops.data.frame import Frame
    from lidarops.models import weights

    model = weights.load(name)
    names = list(model.config.class_names)
    label = names.index(cls)
    frames = [Frame(points=np.zeros((0, 4), np.float32), boxes=np.array([box], np.float32),
                    labels=np.array([label]), num_points_in_box=np.array([50]), visibility=np.array([1.0], np.float32),
                    class_names=tuple(names), frame_index=i) for i in range(45)]
    exact = [{"boxes": torch.tensor([box]), "scores": torch.tensor([0.9]), "labels": torch.tensor([label + 1])}] * 45
    none = [{"boxes": torch.zeros(0, 7), "scores": torch.zeros(0), "labels": torch.zeros(0, dtype=torch.long)}] * 45
    args = (names, _checkpoint_path(name), list(model.config.point_cloud_range))
    ours, full = stream_ap(frames, exact, none, *args)
    assert ours[f"{cls}_3d_moderate_R40"] == pytest.approx(100.0)
    assert ours[f"{cls}_bev_moderate_R40"] == pytest.approx(100.0)
    assert full[f"{cls}_3d_moderate_R40"] == 0.0 and ours[f"{cls}_moderate_objects"] == 45
    same = stream_ap(frames, exact, exact, *args)
    assert same[0] == same[1]
    shifted = [{**d, "boxes": d["boxes"] + torch.tensor([0.0, 0.0, 0.6, 0, 0, 0, 0])} for d in exact]  # too high
    ours, _ = stream_ap(frames, shifted, exact, *args)
    assert ours[f"{cls}_3d_moderate_R40"] < 100.0


def test_bm_sparse_refuses_an_eager_block_below_one(capsys):
    from benchmarks import bm_sparse

    with pytest.raises(SystemExit):
        bm_sparse.main(["--device", "cpu", "--only", "eager", "--eager-block", "0"])
    assert "--eager-block must be >= 1, got 0" in capsys.readouterr().err
