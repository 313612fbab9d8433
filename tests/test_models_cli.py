"""lidarops train / detect / eval from the command line, and the shipped checkpoint: each on tiny data,
errors as one line with exit code 2."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lidarops.cli import main

REPO = Path(__file__).resolve().parents[1]


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    assert main(["data", "synth", "--scenario", "driving_city", "--frames", "6", "--val-fraction", "0.34",
                 "--out", str(out), "--no-progress", "--seed", "3"]) == 0
    return out


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


def test_eval_scores_result_files(synth, tmp_path, capsys):
    """Result files equal to the labels (with scores) give the same APs as evaluate() on the labels."""
    from lidarops.data.formats.kitti import read_label, write_label
    from lidarops.eval import kitti

    labels = synth / "training" / "label_2"
    ids = (synth / "ImageSets" / "val.txt").read_text().split()
    for i in ids:
        rows = read_label(labels / f"{i}.txt")
        rows.score = np.linspace(0.9, 0.5, len(rows)).astype(np.float32)
        write_label(tmp_path / "res" / f"{i}.txt", rows)
    code, out, _ = _run(["eval", "--results", str(tmp_path / "res"), "--labels", str(labels), "--split",
                         str(synth / "ImageSets" / "val.txt"), "--json", str(tmp_path / "r.json")], capsys)
    assert code == 0 and "Car AP_R40@0.70, 0.70, 0.70:" in out
    got = json.loads((tmp_path / "r.json").read_text())
    gt = kitti.read_annos(labels, ids)
    dt = kitti.read_annos(tmp_path / "res", ids)
    assert got == pytest.approx(kitti.evaluate(gt, dt)[1], nan_ok=True)
    (tmp_path / "res" / f"{ids[0]}.txt").unlink()
    code, _, err = _run(["eval", "--results", str(tmp_path / "res"), "--labels", str(labels), "--split",
                         str(synth / "ImageSets" / "val.txt")], capsys)
    assert code == 2 and err.count("\n") == 1 and "have no result file" in err


def test_train_then_resume_then_detect(synth, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--config", str(REPO / "configs" / "pointpillars_demo.yaml"), "--data", str(synth), "--out",
            str(run), "--workers", "0", "--no-progress", "--epochs", "2", "--eval-every", "0"]
    code, out, _ = _run(args + ["--max-steps", "3"], capsys)
    assert code == 0 and "stopped (max_steps)" in out and (run / "latest.pth").is_file()
    code, out, _ = _run(args + ["--resume"], capsys)
    assert code == 0 and "finished: 4 steps" in out and (run / "final.pth").is_file()  # 4 frames, batch 2, 2 epochs
    ckpt = torch.load(run / "final.pth", weights_only=False)
    assert ckpt["class_names"] == ["Car", "Pedestrian", "Cyclist"] and ckpt["data_recipe"]["frames"] == 6
    code, out, _ = _run(["detect", str(synth), "--split", "val", "--checkpoint", str(run / "final.pth"), "--out",
                         str(tmp_path / "det"), "--score-thresh", "0.0", "--print-boxes", "3"], capsys)
    assert code == 0 and "KITTI result file(s)" in out
    files = sorted((tmp_path / "det" / "data").glob("*.txt"))
    assert [f.stem for f in files] == sorted((synth / "ImageSets" / "val.txt").read_text().split())
    assert (tmp_path / "det" / f"{files[0].stem}.png").is_file() and (tmp_path / "det" / "eval.json").is_file()


@pytest.mark.parametrize("argv,pattern", [
    (["train", "--config", str(REPO / "configs" / "pointpillars_demo.yaml"), "--data", "/no/such/dir", "--out", "x"],
     "data folder /no/such/dir not found"),
    (["train", "--config", "/no/such.yaml", "--out", "x"], "config file not found"),
    (["detect", "/no/such.bin"], "/no/such.bin not found"),
    (["detect", "--scenario", "driving_city", "--device", "cuda:7"] if not torch.cuda.is_available()
     else ["detect", "--checkpoint", "/no/ckpt.pth", "--scenario", "driving_city"], "cuda|checkpoint"),
    (["eval", "--results", "/no/such/dir", "--labels", "/no/such/dir"], "--results /no/such/dir is not a folder"),
])
def test_errors_are_one_line(argv, pattern, capsys):
    import re

    code, _, err = _run(argv, capsys)
    assert code == 2 and err.count("\n") == 1 and re.search(pattern, err), err


def test_module_entry_point_help():
    proc = subprocess.run([sys.executable, "-m", "lidarops", "detect", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "--checkpoint" in proc.stdout


@pytest.mark.parametrize("argv,pattern", [
    (["data", "show", "driving_city", "--index", "-1"], "--index must be >= 0"),
    (["data", "synth", "--frames", "0", "--out", "/tmp/lidarops_no_frames"], "at least 1 in all"),
    (["train", "--config", str(REPO / "README.md"), "--out", "x"], "not valid YAML"),
])
def test_more_errors_are_one_line(argv, pattern, capsys):
    import re

    code, _, err = _run(argv, capsys)
    assert code == 2 and err.count("\n") == 1 and re.search(pattern, err), err


@pytest.mark.parametrize("content", [b"junk\n", None])
def test_damaged_checkpoints_are_one_line_errors(content, tmp_path, capsys):
    """A file that is not a checkpoint, or a truncated one, names the file (no pickle traceback)."""
    import re

    from lidarops.models import weights

    bad = tmp_path / "bad.pth"
    bad.write_bytes(content if content is not None else weights.path().read_bytes()[:100_000])
    code, _, err = _run(["detect", "--checkpoint", str(bad), "--scenario", "driving_city", "--frames", "1",
                         "--device", "cpu"], capsys)
    assert code == 2 and err.count("\n") == 1 and re.search(r"bad\.pth: not a readable checkpoint", err), err


@pytest.mark.parametrize("value", ["nan", "2", "-0.1"])
def test_score_threshold_must_be_a_score(value, capsys):
    code, _, err = _run(["detect", "--scenario", "driving_city", "--frames", "1", "--device", "cpu",
                         "--score-thresh", value], capsys)
    assert code == 2 and "--score-thresh must be in [0, 1)" in err, err
