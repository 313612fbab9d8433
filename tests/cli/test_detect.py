"""``lidarops detect`` (lidarops/cli/detect.py) and the shipped checkpoint it runs by default, in-process."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import torch

from .helpers import REPO, one_error_line


def test_shipped_checkpoint_describes_itself():
    from lidarops.models import weights

    path = weights.path()
    assert path.stat().st_size <= 20 * 2**20  # the cap
    info = weights.info()
    assert info["class_names"] == ["Car", "Pedestrian", "Cyclist"]
    assert "lidarops data synth" in info["data_recipe"]["command"]
    assert info["train_command"].startswith("lidarops train")
    assert info["evaluation"]["metrics"]["Car_3d_moderate_R40"] >= 75.0  # the bar
    model = weights.load()
    assert model.config.class_names == info["class_names"] and not model.training


def _cars_found(name: str, realism, seed: int, iou) -> torch.Tensor:
    """Per labelled car (50+ points, in the camera's view, within 60 m) of one unseen simulated city frame:
    whether the shipped model ``name`` finds it, at ``iou`` (lidarops.box_iou_bev or box_iou_3d) > 0.5."""
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models import weights

    frame = SyntheticFrames("driving_city", num_frames=1, seed=seed, realism=realism)[0]
    calib = KittiCalib.default()
    pts = frame.points[kitti_fov_mask(frame.points, calib)]
    cars = frame.boxes[(frame.labels == 0) & (frame.num_points_in_box >= 50)
                       & kitti_fov_mask(frame.boxes[:, :3], calib) & (frame.boxes[:, 0] < 60)]
    assert len(cars) >= 3
    batch = {"points": torch.from_numpy(np.concatenate([np.zeros((len(pts), 1), np.float32), pts], 1)),
             "batch_size": 1}
    pred = weights.load(name).predict(batch)[0]
    return iou(torch.from_numpy(cars), pred["boxes"][pred["labels"] == 1]).amax(1) > 0.5


@pytest.mark.slow
def test_shipped_model_finds_the_cars_of_an_unseen_scene():
    """A simulated frame from a seed the training set does not use: most labelled cars are found."""
    import lidarops

    found = _cars_found("pointpillars_synth", None, 424242, lidarops.box_iou_bev)
    assert found.float().mean() >= 0.8, found


@pytest.mark.slow
def test_real_scan_model_finds_the_cars_of_an_unseen_realism_scene():
    """The shipped real-scan detector: trained on frames the realism profile shapes (its recorded recipe),
    it finds most labelled cars of a realism frame from an unseen seed, boxes at 3D IoU 0.5."""
    import lidarops
    from lidarops.models import weights

    info = weights.info("pointpillars_synth_real")
    assert info["data_recipe"]["realism"] == "kitti" and info["config_path"].endswith("pointpillars_synth_real.yaml")
    assert weights.path("pointpillars_synth_real").stat().st_size <= 20 * 2**20  # the cap
    found = _cars_found("pointpillars_synth_real", "kitti", 424243, lidarops.box_iou_3d)
    assert found.float().mean() >= 0.8, found


@pytest.mark.slow
def test_detect_picks_the_shipped_model_for_its_input(tmp_path, run_cli):
    """A scan file gets the real-scan model, the simulator's ray-cast frames (--scenario, a data synth
    folder without --realism) the model trained on them, a realism folder the real-scan one; --checkpoint
    takes a shipped name."""
    from lidarops.data.synthetic import SyntheticFrames

    scan = tmp_path / "000000.bin"
    SyntheticFrames("driving_city", num_frames=1, seed=5001)[0].points.astype(np.float32).tofile(scan)
    cases = [([scan], "pointpillars_synth_real"),
             (["--scenario", "driving_city", "--frames", "1"], "pointpillars_synth "),
             (["--scenario", "driving_city", "--frames", "1", "--realism", "kitti"], "pointpillars_synth_real")]
    for realism, name in ((None, "pointpillars_synth "), ("kitti", "pointpillars_synth_real")):
        folder = tmp_path / f"synth_{realism}"
        assert run_cli(["data", "synth", "--scenario", "driving_city", "--frames", "1", "--seed", "5002",
                        "--val-fraction", "0", "--out", folder, "--no-progress",
                        *(["--realism", realism] if realism else [])])[0] == 0
        cases.append(([folder, "--frames", "1"], name))
    for k, (args, name) in enumerate(cases):
        code, out, err = run_cli(["detect", *args, "--png", "0", "--device", "cpu", "--out", tmp_path / f"d{k}",
                                  "--no-progress", "--print-frames", "0"])
        assert code == 0 and f"model: the shipped {name}" in out + " ", (args, out, err)
    code, out, err = run_cli(["detect", scan, "--checkpoint", "pointpillars_synth", "--png", "0", "--device", "cpu",
                              "--out", tmp_path / "named", "--no-progress", "--print-frames", "0"])
    assert code == 0 and "model: the shipped" not in out
    assert "pointpillars_synth.pth" in json.loads((tmp_path / "named" / "detect.json").read_text())["checkpoint"]
    code, out, err = run_cli(["detect", scan, "--realism", "kitti", "--out", tmp_path / "bad", "--no-progress"])
    assert code == 2 and "--realism makes --scenario frames" in err, err


def test_detect_realism_makes_the_profiles_frames(monkeypatch, tmp_path, run_cli):
    """--scenario with --realism: the frames are the simulator's frames of that profile (the same points), and a
    profile that is not one is refused by argparse, naming the option."""
    from lidarops.cli import detect as detect_cli
    from lidarops.data.synthetic import SyntheticFrames

    args = detect_cli.argparse.Namespace(scenario="drone_lock", frames=1, seed=7, realism="avia", png=0, print_frames=0,
                                         print_boxes=0, draw_score=0.3, input=None)
    frame_id, frame, _, _ = next(iter(detect_cli._frames(args)))
    want = SyntheticFrames("drone_lock", num_frames=1, seed=7, realism="avia")[0]
    plain = SyntheticFrames("drone_lock", num_frames=1, seed=7)[0]
    assert frame_id == "drone_lock_000000" and np.array_equal(frame.points, want.points)
    assert plain.points.shape != want.points.shape or not np.array_equal(plain.points, want.points)
    with pytest.raises(SystemExit) as e:
        run_cli(["detect", "--scenario", "drone_lock", "--realism", "avai", "--out", tmp_path / "x"])
    assert e.value.code == 2


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_detect_on_a_scenario(tmp_path, run_cli):
    """The shipped model on one simulated frame: boxes printed, a result file, a picture, AP and matches."""
    out = tmp_path / "det"
    code, text, err = run_cli(["detect", "--scenario", "driving_city", "--frames", "1", "--seed", "2026",
                               "--device", "cpu", "--out", out])
    assert code == 0, err
    assert "driving_city_000000:" in text and " detection(s), " in text
    assert "  Car " in text and "heading" in text  # a printed box
    assert "KITTI AP (R40, %) on 1 frame(s)" in text and re.search(r"\n  Car +3D +[0-9.]+ / ", text)
    assert "(recorded when trained: 97.1)" in text  # the shipped model's own evaluation, beside
    last = text.rstrip().splitlines()[-1]
    assert last.startswith("matches (labelled objects in range and a KITTI difficulty): Car: ")
    # one count of labelled objects: the frame line and the matches line agree
    frame_count = int(re.search(r"(\d+) labelled in range", text).group(1))
    matched = sum(int(n) for n in re.findall(r"\d+ of (\d+) found", last))
    assert frame_count == matched
    assert (out / "data" / "driving_city_000000.txt").is_file() and (out / "eval.json").is_file()
    assert "Car AP_R40@0.70, 0.70, 0.70:" in (out / "eval.txt").read_text()  # KITTI's full table
    png = out / "driving_city_000000.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


@pytest.mark.slow  # the 504 x 504 Aerial-PointPillars on the CPU: a few seconds a frame
def test_detect_runs_a_whole_view_model_on_its_whole_view(tmp_path, run_cli):
    """aerial_pointpillars was trained on drone labels of the Avia's whole view (data synth --labels all): detect
    gives it every point, keeps its boxes above the camera's image, and scores them without image boxes (BEV and
    3D only), counting the drones above the image; a camera-view model on the same scene keeps the camera's view."""
    from lidarops.cli.detect import _sees_whole_view
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models import weights

    assert _sees_whole_view({"data_recipe": weights.info("aerial_pointpillars")["data_recipe"]})
    assert not _sees_whole_view({"data_recipe": weights.info("pointpillars_synth")["data_recipe"]})
    assert not _sees_whole_view({})
    seed, n = 5022, 2  # an unseen seed whose first frame has a drone above the image
    frames = SyntheticFrames("drone_bridge", num_frames=n, seed=seed)
    out = tmp_path / "det"
    code, text, err = run_cli(["detect", "--scenario", "drone_bridge", "--frames", str(n), "--seed", str(seed),
                               "--checkpoint", "aerial_pointpillars", "--device", "cpu", "--out", out, "--png", "0"])
    assert code == 0, err
    assert "  Drone " in text and "KITTI AP (R40, %)" in text
    results = json.loads((out / "eval.json").read_text())
    assert "Drone_3d_moderate_R40" in results and not any("bbox" in k or "aos" in k for k in results)
    labelled = sum(int(c) for c in re.findall(r"(\d+) labelled in range", text))
    in_image = 0
    for i in range(n):
        f = frames[i]
        seen = f.boxes[(f.num_points_in_box > 0) & (f.boxes[:, 0] <= 80.64) & (np.abs(f.boxes[:, 1]) <= 40.32)]
        in_image += int(kitti_fov_mask(seen[:, :3], KittiCalib.default()).sum())
    assert labelled > in_image >= 1, (labelled, in_image)  # the drones above the image count


def test_detect_png_draws_box_corners(tmp_path, monkeypatch):
    """The outlines drawn are lidarops.data.geometry.box_corners' bottom corners; the heading line ends at the
    middle of the front face."""
    from lidarops.cli.detect import save_detections_png
    from lidarops.data import viz
    from lidarops.data.geometry import box_corners

    figures, new_figure = [], viz.new_figure
    monkeypatch.setattr(viz, "new_figure", lambda *a, **k: figures.append(new_figure(*a, **k)) or figures[-1])
    box = np.array([[20.0, 5.0, -1.0, 4.0, 2.0, 1.5, 0.7]], np.float32)
    save_detections_png(tmp_path / "x.png", np.zeros((10, 4), np.float32), {"boxes": box, "labels": np.array([1]),
                        "scores": np.array([0.9])}, ["Car"], gt_boxes=box, gt_names=["Car"])
    ax, key = figures[0].axes  # the picture and the colour key of the point heights
    assert key.get_ylabel() == "point height z (m)"
    want = box_corners(box)[0, :4, :2]
    outlines = [p.get_xy()[:4] for p in ax.patches]
    assert len(outlines) == 2 and all(np.allclose(o, want, atol=1e-5) for o in outlines)
    heading = [line.get_xydata() for line in ax.lines if len(line.get_xydata()) == 2]
    assert len(heading) == 1 and np.allclose(heading[0][1], want[[0, 3]].mean(0), atol=1e-5)


def test_detect_png_leaves_out_low_scores_and_colliding_labels(tmp_path, monkeypatch):
    from lidarops.cli.detect import save_detections_png
    from lidarops.data import viz

    figures, new_figure = [], viz.new_figure
    monkeypatch.setattr(viz, "new_figure", lambda *a, **k: figures.append(new_figure(*a, **k)) or figures[-1])
    boxes = np.array([[20.0, 5.0, -1.0, 4.0, 2.0, 1.5, 0.0], [20.2, 5.1, -1.0, 4.0, 2.0, 1.5, 0.0],
                      [40.0, -5.0, -1.0, 4.0, 2.0, 1.5, 0.0]], np.float32)
    save_detections_png(tmp_path / "x.png", np.zeros((10, 4), np.float32),
                        {"boxes": boxes, "labels": np.array([1, 1, 1]), "scores": np.array([0.9, 0.8, 0.1])},
                        ["Car"], score_floor=0.3, title="t")
    ax = figures[0].axes[0]
    assert len(ax.patches) == 2  # the 0.1 box is not drawn
    assert [t.get_text() for t in ax.texts] == ["0.90"]  # the 0.80 label would sit on the 0.90 one
    assert ax.get_title() == "t; 1 below 0.3 not drawn"


def test_module_entry_point_help():
    proc = subprocess.run([sys.executable, "-m", "lidarops", "detect", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "--checkpoint" in proc.stdout


@pytest.mark.parametrize("content, message", [
    (b"junk\n", r"bad.pth: not a checkpoint \(neither a torch zip archive nor a pickle"),
    (b"\x89PNG\r\n\x1a\n" + bytes(64), r"bad.pth: not a checkpoint \(neither"),
    (None, r"bad.pth: a damaged or truncated checkpoint"),
])
def test_damaged_checkpoints_are_one_line_errors(content, message, tmp_path, run_cli):
    """A file that is not a checkpoint, or a truncated one, names the file (no pickle traceback), and never
    passes on torch's advice to unpickle it (which would run code from an untrusted file)."""
    from lidarops.models import weights

    bad = tmp_path / "bad.pth"
    bad.write_bytes(content if content is not None else weights.path().read_bytes()[:100_000])
    code, _, err = run_cli(["detect", "--checkpoint", bad, "--scenario", "driving_city", "--frames", "1",
                            "--device", "cpu"])
    line = one_error_line(err, "detect")
    assert code == 2 and re.search(message, line), line
    assert "weights_only" not in line


def test_a_torch_file_holding_objects_gets_the_trust_advice(tmp_path, run_cli):
    import argparse

    path = tmp_path / "objects.pth"
    torch.save({"args": argparse.Namespace(lr=0.1)}, path)
    code, _, err = run_cli(["detect", "--checkpoint", path, "--scenario", "driving_city", "--device", "cpu"])
    line = one_error_line(err, "detect")
    assert code == 2 and "only if you trust where it came from" in line and "weights_only=False" in line


@pytest.mark.parametrize("value", ["nan", "2", "-0.1"])
def test_score_threshold_must_be_a_score(value, run_cli):
    code, _, err = run_cli(["detect", "--scenario", "driving_city", "--frames", "1", "--device", "cpu",
                            "--score-thresh", value])
    assert code == 2 and "--score-thresh must be in [0, 1)" in one_error_line(err, "detect")


def test_detect_input_errors(tmp_path, run_cli):
    code, _, err = run_cli(["detect", "--device", "cpu"])
    assert code == 2 and "give a .bin file, a KITTI folder, or --scenario NAME" in one_error_line(err, "detect")
    (tmp_path / "x.txt").write_text("")
    code, _, err = run_cli(["detect", tmp_path / "x.txt", "--device", "cpu"])
    assert code == 2 and "expected a KITTI velodyne .bin, a nuScenes .pcd.bin or a folder" in one_error_line(err, "detect")
    code, _, err = run_cli(["detect", "--scenario", "driving_city", "--device", "cpu", "--out", tmp_path / "x.txt"])
    assert code == 2 and "is a file; give a folder" in one_error_line(err, "detect")


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_the_models_own_training_frames_are_named_by_detect_and_eval(tmp_path, run_cli):
    """The shipped model's recipe simulated driving_city with seed 0: frames of it are flagged, by detect on
    the scenario and on a folder data synth made with that seed, and by eval on what detect wrote."""
    code, out, err = run_cli(["detect", "--scenario", "driving_city", "--seed", "0", "--frames", "1", "--png", "0",
                              "--device", "cpu", "--out", tmp_path / "sim", "--no-progress"])
    assert code == 0 and "1 of the 1 frame(s) are frames of the model's own data recipe" in err
    assert json.loads((tmp_path / "sim" / "detect.json").read_text())["frames_of_the_model_recipe"] == \
        ["driving_city_000000"]
    assert run_cli(["data", "synth", "--scenario", "driving_city", "--frames", "2", "--seed", "0", "--val-fraction",
                    "0", "--out", tmp_path / "kitti", "--no-progress"])[0] == 0
    code, out, err = run_cli(["detect", tmp_path / "kitti", "--png", "0", "--device", "cpu", "--out",
                              tmp_path / "det", "--no-progress"])
    assert code == 0 and "2 of the 2 frame(s) are frames of the model's own data recipe" in err
    code, out, err = run_cli(["eval", "--results", tmp_path / "det" / "data", "--labels",
                              tmp_path / "kitti" / "training" / "label_2"])
    assert code == 0 and "2 of the 2 frames scored are frames the model was trained or validated on" in err


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_default_seeds_are_unseen_and_detect_reports_its_speed(tmp_path, run_cli):
    from lidarops.models import weights

    seeds = {s["seed"] for s in weights.info()["data_recipe"]["scenarios"]}
    code, out, err = run_cli(["detect", "--scenario", "driving_highway", "--frames", "2", "--png", "0", "--device",
                              "cpu", "--out", tmp_path, "--no-progress"])
    assert code == 0 and "warning" not in err, err
    assert re.search(r"2 frame\(s\) in [0-9.]+ s \([0-9.]+ frames/s with reading and writing\); the model: "
                     r"[0-9.]+ ms per frame on cpu \(first frame [0-9]+ ms\)", out), out
    assert json.loads((tmp_path / "detect.json").read_text())["frames_of_the_model_recipe"] == []
    from lidarops.conventions import HELD_OUT_SEED

    assert HELD_OUT_SEED not in seeds and HELD_OUT_SEED + 1000 not in seeds
