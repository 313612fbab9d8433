"""``lidarops eval`` (lidarops/cli/eval.py): KITTI AP of result files against labels, run in-process."""
from __future__ import annotations

import json

import numpy as np
import pytest

from .helpers import one_error_line


def test_eval_scores_result_files(synth_kitti, tmp_path, run_cli):
    """Result files equal to the labels (with scores) give the same APs as evaluate() on the labels."""
    from lidarops.data.formats.kitti import read_label, write_label
    from lidarops.eval import kitti

    labels = synth_kitti / "training" / "label_2"
    split = synth_kitti / "ImageSets" / "val.txt"
    ids = split.read_text().split()
    for i in ids:
        rows = read_label(labels / f"{i}.txt")
        rows.score = np.linspace(0.9, 0.5, len(rows)).astype(np.float32)
        write_label(tmp_path / "res" / f"{i}.txt", rows)
    code, out, _ = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels, "--split", split,
                            "--json", tmp_path / "r.json"])
    assert code == 0 and "Car AP_R40@0.70, 0.70, 0.70:" in out
    got = json.loads((tmp_path / "r.json").read_text())
    gt = kitti.read_annos(labels, ids)
    dt = kitti.read_annos(tmp_path / "res", ids)
    assert got == pytest.approx(kitti.evaluate(gt, dt)[1], nan_ok=True)
    # without --split: every result file
    code, out, _ = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels])
    assert code == 0 and "Car AP_R40@0.70, 0.70, 0.70:" in out
    (tmp_path / "res" / f"{ids[0]}.txt").unlink()
    code, _, err = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels, "--split", split])
    assert code == 2 and "have no result file" in one_error_line(err, "eval")


def test_eval_needs_frames(synth_kitti, tmp_path, run_cli):
    labels = synth_kitti / "training" / "label_2"
    (tmp_path / "res").mkdir()
    code, _, err = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels])
    assert code == 2 and "no frames to score" in one_error_line(err, "eval")
    (tmp_path / "empty.txt").write_text("\n")
    code, _, err = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels, "--split",
                            tmp_path / "empty.txt"])
    assert code == 2 and "lists none" in one_error_line(err, "eval")


def test_match_summary_counts_found_objects():
    """A detection on a labelled car is found, one elsewhere is another detection; labelled objects in no KITTI
    difficulty (too small in the image, too occluded) or beyond the model's range are not counted."""
    from lidarops.cli.eval import match_summary

    def anno(locations, scores=None, height=50.0, occluded=0):
        n = len(locations)
        out = {"name": np.array(["Car"] * n), "location": np.array(locations, np.float64).reshape(n, 3),
               "dimensions": np.tile([[3.9, 1.6, 1.5]], (n, 1)), "rotation_y": np.zeros(n),
               "bbox": np.tile([[100.0, 100.0, 200.0, 100.0 + height]], (n, 1)), "truncated": np.zeros(n),
               "occluded": np.full(n, occluded)}
        if scores is not None:
            out["score"] = np.array(scores, np.float64)
        return out

    gt = [anno([[0.0, 1.5, 10.0]])]
    dt = [anno([[0.0, 1.5, 10.0], [5.0, 1.5, 30.0]], [0.9, 0.8])]
    line = match_summary(gt, dt, ["Car", "Pedestrian"])
    assert line == ("matches (labelled objects in a KITTI difficulty): Car: 1 of 1 found (3D IoU >= 0.7), 1 other "
                    "detections; Pedestrian: 0 of 0 found (3D IoU >= 0.5), 0 other detections")
    for hidden in (anno([[0.0, 1.5, 10.0]], height=20.0), anno([[0.0, 1.5, 10.0]], occluded=3)):
        assert "Car: 0 of 0 found" in match_summary([hidden], dt, ["Car"])
    far = [anno([[0.0, 1.5, 10.0], [0.0, 1.5, 80.0]])]  # 80 m ahead: beyond a 69.12 m range
    pc_range = [0, -39.68, -3, 69.12, 39.68, 1]
    assert "Car: 1 of 1 found" in match_summary(far, dt, ["Car"], point_cloud_range=pc_range)
    assert "Car: 1 of 2 found" in match_summary(far, dt, ["Car"])

def test_eval_whole_view_scores_drones_beyond_the_camera(tmp_path, run_cli):
    """--whole-view: drone labels of the Avia's whole view (data synth's default for drone scenes), scored without
    image boxes. Results equal to the labels score 100 on BEV and 3D for every drone (the camera's protocol ignores
    drones under 25 px, nearly all of them), and no bbox or AOS rows are printed."""
    from lidarops.data.formats.kitti import read_label, write_label
    from lidarops.eval import kitti

    data = tmp_path / "drones"
    code, _, err = run_cli(["data", "synth", "--scenario", "drone_bridge", "drone_lock", "--frames", "40",
                            "--out", data, "--no-progress", "--seed", "9"])
    assert code == 0, err
    labels = data / "training" / "label_2"
    ids = sorted(p.stem for p in labels.glob("*.txt"))
    for i in ids:
        rows = read_label(labels / f"{i}.txt")
        rows.score = np.linspace(0.9, 0.5, len(rows)).astype(np.float32)
        write_label(tmp_path / "res" / f"{i}.txt", rows)
    gt = [kitti.whole_view_annos(a) for a in kitti.read_annos(labels, ids)]
    assert sum(len(a["name"]) for a in gt) >= 41  # enough for R40 to reach 100
    code, out, err = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels, "--classes", "Drone",
                              "--whole-view", "--json", tmp_path / "w.json"])
    assert code == 0, err
    got = json.loads((tmp_path / "w.json").read_text())
    assert got["Drone_3d_moderate_R40"] == got["Drone_bev_hard_R40"] == 100.0
    assert "bbox AP" not in out and not any(k.startswith("Drone_bbox") for k in got)
    code, _, _ = run_cli(["eval", "--results", tmp_path / "res", "--labels", labels, "--classes", "Drone",
                          "--json", tmp_path / "c.json"])
    camera = json.loads((tmp_path / "c.json").read_text())
    assert code == 0 and camera["Drone_3d_moderate_R40"] < 100.0  # the camera's view leaves most drones out
