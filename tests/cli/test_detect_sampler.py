"""``lidarops detect --sampler ... --ratio D`` (lidarops/cli/detect.py): the detector behind a point sampler
(issue 37), on one small scan and a tiny detector so that every sampler runs in a second on the CPU."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lidarops.cli.sample import METHODS, sample_count

from .helpers import one_error_line

#: a small PointPillars (one class, a 32 x 32 grid of 1 m pillars, 8 filters) that builds and runs in milliseconds
_TINY_DETECTOR = dict(
    class_names=["Car"],
    point_cloud_range=[0.0, -16.0, -3.0, 32.0, 16.0, 1.0],
    voxel_size=[1.0, 1.0, 4.0],
    vfe_num_filters=[8],
    layer_nums=[1, 1, 1], layer_strides=[2, 2, 2], num_filters=[8, 8, 8],
    upsample_strides=[1, 2, 4], num_upsample_filters=[4, 4, 4],
    anchor_generator_config=[{"class_name": "Car", "anchor_sizes": [[3.9, 1.6, 1.56]], "anchor_rotations": [0, 1.57],
                              "anchor_bottom_heights": [-1.78], "align_center": False, "feature_map_stride": 2,
                              "matched_threshold": 0.6, "unmatched_threshold": 0.45}],
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A KITTI scan of 1,500 points of a simulated street in the camera's view (``velodyne/000000.bin``),
    the points of it the camera sees (what the detector gets without a sampler), a tiny detector and an untrained CAS-Net."""
    from lidarops.checkpoint import format_fields, save_checkpoint
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models import PointPillars
    from lidarops.models.casnet import CASNet

    root = tmp_path_factory.mktemp("detect-sampler")
    points = SyntheticFrames("driving_city", num_frames=1, seed=11)[0].points
    near = points[(points[:, 0] < 32) & (np.abs(points[:, 1]) < 16) & kitti_fov_mask(points, KittiCalib.default())]
    points = near[np.sort(np.random.default_rng(0).choice(len(near), 1500, replace=False))].astype(np.float32)
    scan = root / "velodyne" / "000000.bin"
    scan.parent.mkdir()
    scan.write_bytes(points.tobytes())
    torch.manual_seed(0)
    model = PointPillars(_TINY_DETECTOR).eval()
    with torch.no_grad():  # detections that depend on the points: random weights, a head that scores
        for p in model.parameters():
            p.normal_(0.0, 0.3)
    detector = root / "tiny_detector.pth"
    save_checkpoint({**format_fields(), "model_class": "PointPillars", "model_config": model.config.to_dict(),
                     "class_names": list(model.config.class_names), "model_state": model.state_dict()}, [detector])
    torch.manual_seed(0)
    casnet = CASNet(num_out=64, k=8, radius=2.0).save(root / "casnet.pth")
    seen = points[kitti_fov_mask(points, KittiCalib.default())]
    return {"scan": scan, "seen": seen, "detector": detector, "casnet": casnet, "root": root}


@pytest.fixture
def detector_inputs(monkeypatch):
    """The points (P, 1 + C) of every batch the detector is given."""
    from lidarops.models import PointPillars

    seen, predict = [], PointPillars.predict

    def spy(self, batch, *args, **kwargs):
        seen.append(batch["points"].detach().cpu().numpy().copy())
        return predict(self, batch, *args, **kwargs)

    monkeypatch.setattr(PointPillars, "predict", spy)
    return seen


def _detect(run_cli, scene, out, *extra):
    code, text, err = run_cli(["detect", scene["scan"], "--checkpoint", scene["detector"], "--device", "cpu",
                               "--score-thresh", "0", "--png", "0", "--no-progress", "--out", out, *extra])
    assert code == 0, err
    return text, json.loads((out / "detect.json").read_text()), (out / "data" / "000000.txt").read_text()


def _rows_of(kept: np.ndarray, points: np.ndarray) -> bool:
    """Whether every row of ``kept`` is a row of ``points``, each at most once."""
    rows = {r.tobytes() for r in points}
    got = [r.tobytes() for r in np.ascontiguousarray(kept)]
    return len(set(got)) == len(got) and all(r in rows for r in got)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("ratio", [8, 3])
def test_each_sampler_gives_the_detector_n_over_d_rows_of_its_input(method, ratio, scene, tmp_path, run_cli,
                                                                    detector_inputs):
    extra = ["--sampler-checkpoint", scene["casnet"]] if method == "casnet" else []
    text, record, _ = _detect(run_cli, scene, tmp_path, "--sampler", method, "--ratio", str(ratio), *extra)
    n = len(scene["seen"])
    m = sample_count(n, ratio)
    (batch,) = detector_inputs
    assert batch.shape == (m, 5) and (batch[:, 0] == 0).all()  # every channel: x, y, z and intensity
    assert _rows_of(batch[:, 1:], scene["seen"])
    assert "000000: " in text and f"; {method} 1/{ratio}: {n:,} -> {m:,} points in " in text
    assert f"the sampler ({method}, 1/{ratio}): " in text and " ms per frame on cpu" in text
    (frame,) = record["per_frame"]
    assert frame["frame"] == "000000" and frame["points_in"] == n and frame["points_kept"] == m
    assert frame["sample_ms"] >= 0
    assert record["sampler"]["method"] == method and record["sampler"]["ratio"] == ratio
    assert ("seed" in record["sampler"]) == (method == "random")
    assert record["sampler"].get("checkpoint") == (str(scene["casnet"]) if method == "casnet" else None)


def test_the_ratio_defaults_to_8(scene, tmp_path, run_cli, detector_inputs):
    _, record, _ = _detect(run_cli, scene, tmp_path, "--sampler", "random")
    assert record["sampler"]["ratio"] == 8 and len(detector_inputs[0]) == sample_count(len(scene["seen"]), 8)


@pytest.mark.parametrize("method", METHODS)
def test_ratio_one_is_the_run_without_a_sampler(method, scene, tmp_path, run_cli, detector_inputs):
    _, plain, reference = _detect(run_cli, scene, tmp_path / "plain")
    assert plain["sampler"] is None and plain["per_frame"][0]["sample_ms"] is None
    assert plain["per_frame"][0]["points_in"] == plain["per_frame"][0]["points_kept"] == len(scene["seen"])
    extra = ["--sampler-checkpoint", scene["casnet"]] if method == "casnet" else []
    _, record, boxes = _detect(run_cli, scene, tmp_path / "d1", "--sampler", method, "--ratio", "1", *extra)
    assert record["per_frame"][0]["points_kept"] == len(scene["seen"])
    assert np.array_equal(detector_inputs[0], detector_inputs[1])  # the same points in the same order
    assert reference.strip() and boxes == reference


def test_random_sampler_repeats_with_its_seed(scene, tmp_path, run_cli, detector_inputs):
    runs = [_detect(run_cli, scene, tmp_path / str(k), "--sampler", "random", "--ratio", "4", "--sampler-seed", seed)
            for k, seed in enumerate(["7", "7", "8"])]
    assert runs[0][2].strip() and runs[0][2] == runs[1][2]  # the same boxes
    assert np.array_equal(detector_inputs[0], detector_inputs[1])
    assert not np.array_equal(detector_inputs[0], detector_inputs[2])  # another seed: other points, other boxes
    assert runs[2][2] != runs[0][2]
    assert runs[0][1]["sampler"]["seed"] == 7


def test_the_picture_shows_the_points_the_detector_saw(scene, tmp_path, run_cli, detector_inputs, monkeypatch):
    from lidarops.cli import detect

    drawn = []
    monkeypatch.setattr(detect, "save_detections_png",
                        lambda path, points, *a, **k: drawn.append((points, k["title"])) or path)
    code, text, err = run_cli(["detect", scene["scan"], "--checkpoint", scene["detector"], "--device", "cpu",
                               "--no-progress", "--out", tmp_path, "--sampler", "fps", "--ratio", "5"])
    assert code == 0, err
    (points, title), = drawn
    assert np.array_equal(points, detector_inputs[0][:, 1:])
    assert f"the detector's {len(points):,} of {len(scene['seen']):,} points (fps, 1/5)" in title


def test_casnet_reads_the_shipped_detection_casnet_when_there_is_one(scene, tmp_path, run_cli, detector_inputs,
                                                                   monkeypatch):
    import shutil

    from lidarops.cli.detect import SHIPPED_CASNET
    from lidarops.models import weights

    shipped = tmp_path / "weights"
    shipped.mkdir()
    shutil.copy(scene["casnet"], shipped / f"{SHIPPED_CASNET}.pth")
    monkeypatch.setattr(weights, "WEIGHTS_DIR", shipped)
    _, record, _ = _detect(run_cli, scene, tmp_path / "default", "--sampler", "casnet")
    assert record["sampler"]["checkpoint"] == str(shipped / f"{SHIPPED_CASNET}.pth")
    _, record, _ = _detect(run_cli, scene, tmp_path / "named", "--sampler", "casnet", "--sampler-checkpoint",
                           SHIPPED_CASNET)
    assert record["sampler"]["checkpoint"] == str(shipped / f"{SHIPPED_CASNET}.pth")
    assert len(detector_inputs) == 2 and np.array_equal(detector_inputs[0], detector_inputs[1])


def test_casnet_default_is_the_one_trained_for_the_detector_that_runs(scene, tmp_path, monkeypatch):
    import argparse
    import shutil

    from lidarops.cli.detect import SHIPPED_CASNET, SHIPPED_CASNET_REAL, _sampling
    from lidarops.models import weights

    shipped = tmp_path / "weights"
    shipped.mkdir()
    for name in (SHIPPED_CASNET, SHIPPED_CASNET_REAL):
        shutil.copy(scene["casnet"], shipped / f"{name}.pth")
    monkeypatch.setattr(weights, "WEIGHTS_DIR", shipped)

    def default_for(checkpoint, scenario=None):
        args = argparse.Namespace(sampler="casnet", ratio=None, sampler_seed=None, sampler_checkpoint=None,
                                  checkpoint=checkpoint, scenario=scenario, input=str(scene["scan"]))
        return Path(_sampling(args).checkpoint).name

    # a user's scan without --checkpoint runs pointpillars_synth_real: its own CAS-Net
    assert default_for(None) == f"{SHIPPED_CASNET_REAL}.pth"
    assert default_for("pointpillars_synth_real") == f"{SHIPPED_CASNET_REAL}.pth"
    # the ray-cast model (named, or picked for --scenario) and a user's own file: the one of pointpillars_synth
    assert default_for("pointpillars_synth") == f"{SHIPPED_CASNET}.pth"
    assert default_for(None, scenario="driving_city") == f"{SHIPPED_CASNET}.pth"
    assert default_for(str(scene["detector"])) == f"{SHIPPED_CASNET}.pth"
    (shipped / f"{SHIPPED_CASNET_REAL}.pth").unlink()
    assert default_for(None) == f"{SHIPPED_CASNET}.pth"


def test_casnet_without_a_shipped_one_asks_for_a_checkpoint(scene, tmp_path, run_cli, monkeypatch):
    from lidarops.models import weights

    monkeypatch.setattr(weights, "WEIGHTS_DIR", tmp_path / "no-weights")
    code, _, err = run_cli(["detect", scene["scan"], "--checkpoint", scene["detector"], "--device", "cpu",
                            "--out", tmp_path / "out", "--sampler", "casnet"])
    line = one_error_line(err, "detect")
    assert code == 2 and "--sampler casnet: the shipped detection CAS-Net" in line
    assert "--sampler-checkpoint" in line and "CASNet.save" in line and "CASNetPointPillars" in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, message", [
    (["--ratio", "8"], "--ratio 8 needs --sampler"),
    (["--sampler-seed", "3"], "--sampler-seed 3 needs --sampler"),
    (["--sampler-checkpoint", "{casnet}"], "needs --sampler"),
    (["--sampler", "voxel"], "--sampler must be one of random, fps, chunked-fps, casnet, got 'voxel'"),
    (["--sampler", "FPS"], "--sampler must be one of random, fps, chunked-fps, casnet, got 'FPS'"),
    (["--sampler", "fps", "--ratio", "0"], "--ratio must be an int >= 1, got 0"),
    (["--sampler", "fps", "--ratio", "1.5"], "--ratio must be an int >= 1, got '1.5'"),
    (["--sampler", "random", "--sampler-seed", "-1"], "--sampler-seed must be an int in [0, 2^63), got '-1'"),
    (["--sampler", "random", "--sampler-seed", "x"], "--sampler-seed must be an int in [0, 2^63), got 'x'"),
    (["--sampler", "fps", "--sampler-checkpoint", "{casnet}"],
     "--sampler-checkpoint {casnet} is a CAS-Net's, for --sampler casnet only (got --sampler fps)"),
    (["--sampler", "casnet", "--sampler-checkpoint", "{root}/no.pth"], "--sampler-checkpoint {root}/no.pth not found"),
    (["--sampler", "casnet", "--sampler-checkpoint", "{root}"], "--sampler-checkpoint {root} is a directory"),
    (["--sampler", "casnet", "--sampler-checkpoint", "{scan}"], "--sampler-checkpoint {scan}: not a checkpoint"),
    (["--sampler", "casnet", "--sampler-checkpoint", "{detector}"], "--sampler-checkpoint {detector}"),
])
def test_sampler_flag_errors_are_one_line(argv, message, scene, tmp_path, run_cli):
    argv = [a.format(**scene) for a in argv]
    code, _, err = run_cli(["detect", scene["scan"], "--checkpoint", scene["detector"], "--device", "cpu",
                            "--out", tmp_path / "out", *argv])
    line = one_error_line(err, "detect")
    assert code == 2 and message.format(**scene) in line, line
    assert not (tmp_path / "out").exists()  # refused before anything is written
