"""``lidarops detect`` (lidarops/cli/detect.py) and the shipped checkpoint it runs by default, in-process."""
from __future__ import annotations

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


@pytest.mark.slow
def test_shipped_model_finds_the_cars_of_an_unseen_scene():
    """A simulated frame from a seed the training set does not use: most labelled cars are found."""
    import lidarops
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models import weights

    frame = SyntheticFrames("driving_city", num_frames=1, seed=424242)[0]
    calib = KittiCalib.default()
    pts = frame.points[kitti_fov_mask(frame.points, calib)]
    cars = frame.boxes[(frame.labels == 0) & (frame.num_points_in_box >= 50)
                       & kitti_fov_mask(frame.boxes[:, :3], calib) & (frame.boxes[:, 0] < 60)]
    assert len(cars) >= 3
    batch = {"points": torch.from_numpy(np.concatenate([np.zeros((len(pts), 1), np.float32), pts], 1)),
             "batch_size": 1}
    pred = weights.load().predict(batch)[0]
    found = lidarops.box_iou_bev(torch.from_numpy(cars), pred["boxes"][pred["labels"] == 1]).amax(1) > 0.5
    assert found.float().mean() >= 0.8, found


def test_detect_on_a_scenario(tmp_path, run_cli):
    """The shipped model on one simulated frame: boxes printed, a result file, a picture, AP and matches."""
    out = tmp_path / "det"
    code, text, err = run_cli(["detect", "--scenario", "driving_city", "--frames", "1", "--seed", "2026",
                               "--device", "cpu", "--out", out])
    assert code == 0, err
    assert "driving_city_000000:" in text and " detection(s), " in text
    assert "  Car " in text and "heading" in text  # a printed box
    assert "Car AP_R40@0.70, 0.70, 0.70:" in text and text.rstrip().splitlines()[-1].startswith("matches: Car: ")
    assert (out / "data" / "driving_city_000000.txt").is_file() and (out / "eval.json").is_file()
    png = out / "driving_city_000000.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


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
    (ax,) = figures[0].axes
    want = box_corners(box)[0, :4, :2]
    outlines = [p.get_xy()[:4] for p in ax.patches]
    assert len(outlines) == 2 and all(np.allclose(o, want, atol=1e-5) for o in outlines)
    heading = [line.get_xydata() for line in ax.lines if len(line.get_xydata()) == 2]
    assert len(heading) == 1 and np.allclose(heading[0][1], want[[0, 3]].mean(0), atol=1e-5)


def test_module_entry_point_help():
    proc = subprocess.run([sys.executable, "-m", "lidarops", "detect", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "--checkpoint" in proc.stdout


@pytest.mark.parametrize("content", [b"junk\n", None])
def test_damaged_checkpoints_are_one_line_errors(content, tmp_path, run_cli):
    """A file that is not a checkpoint, or a truncated one, names the file (no pickle traceback)."""
    from lidarops.models import weights

    bad = tmp_path / "bad.pth"
    bad.write_bytes(content if content is not None else weights.path().read_bytes()[:100_000])
    code, _, err = run_cli(["detect", "--checkpoint", bad, "--scenario", "driving_city", "--frames", "1",
                            "--device", "cpu"])
    assert code == 2 and "bad.pth: not a readable checkpoint" in one_error_line(err, "detect")


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
