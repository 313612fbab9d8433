"""Hardening, second pass: one hand-written regression per case found against the model floor, the box ops,
the KITTI readers and evaluator, the command line and the sparse and stream edges. Each input reproduces a
reported silent wrong answer, allocation before the refusal, or unclear error, so each test fails if its
guard is removed; tests/fuzz covers the same ground with generated inputs."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lidarops
from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError, load_config
from lidarops.models import PointPillars, PointPillarsConfig, load_model, weights

from helpers.devices import DEVICES


def _one_line(capsys, command: str, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"lidarops {command}: error: "), err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# ---------------------------------------------------------------------------------------------
# checkpoints and configs: non-finite weights and thresholds are refused by name
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def nan_checkpoint(tmp_path_factory):
    """The shipped checkpoint with one NaN weight in the backbone."""
    ckpt = torch.load(str(weights.path()), weights_only=True)
    ckpt["model_state"]["backbone_2d.blocks.1.4.weight"][0, 0, 0, 0] = math.nan
    path = tmp_path_factory.mktemp("ckpt") / "nan.pth"
    torch.save(ckpt, path)
    return path


def test_a_nan_weight_is_refused_on_every_load_path(nan_checkpoint, capsys):
    for load in (lambda: PointPillars.from_checkpoint(nan_checkpoint), lambda: load_model(nan_checkpoint)):
        with pytest.raises(CheckpointError, match=r"non-finite .*backbone_2d\.blocks\.1\.4\.weight \(1 of 147456\)"):
            load()
    model = PointPillars(weights.info()["model_config"])
    state = torch.load(str(nan_checkpoint), weights_only=True)["model_state"]
    with pytest.raises(CheckpointError, match="backbone_2d.blocks.1.4.weight"):
        model.load_weights(state)
    model.load_weights(state, check_finite=False)  # on request, as it is
    assert torch.isnan(model.backbone_2d.blocks[1][4].weight).any()
    from lidarops.cli import main

    assert main(["detect", "--checkpoint", str(nan_checkpoint), "--scenario", "driving_city", "--device", "cpu",
                 "--out", str(nan_checkpoint.parent / "det")]) == 2
    _one_line(capsys, "detect", "backbone_2d.blocks.1.4.weight")


def test_a_nan_buffer_is_refused_too(tmp_path):
    model = PointPillars(weights.info()["model_config"])
    state = dict(model.state_dict())
    state["vfe.pfn_layers.0.norm.running_var"] = state["vfe.pfn_layers.0.norm.running_var"].clone()
    state["vfe.pfn_layers.0.norm.running_var"][3] = math.inf
    with pytest.raises(CheckpointError, match="vfe.pfn_layers.0.norm.running_var"):
        model.load_weights(state)


@pytest.mark.parametrize("field, value, key", [
    ("score_thresh", math.nan, "SCORE_THRESH"),
    ("score_thresh", math.inf, "SCORE_THRESH"),
    ("score_thresh", 1.0, "SCORE_THRESH"),
    ("nms_thresh", -0.5, "NMS_THRESH"),
    ("nms_pre_maxsize", 4096.5, "NMS_PRE_MAXSIZE"),
    ("max_voxels_test", 0, "MAX_NUMBER_OF_VOXELS.test"),
    ("cls_weight", math.nan, "cls_weight"),
    ("code_weights", [1.0] * 6 + [math.inf], "code_weights[6]"),
    ("voxel_size", [0.16, 0.0, 4.0], "VOXEL_SIZE[1]"),
    ("use_norm", "yes", "USE_NORM"),
    ("dir_offset", math.nan, "DIR_OFFSET"),
])
def test_config_numbers_are_checked_by_key(field, value, key):
    import re

    with pytest.raises(ConfigError, match=re.escape(key) + ".* got "):
        PointPillarsConfig(**{field: value})


def test_yaml_thresholds_are_checked_by_key(tmp_path):
    """From a YAML file: ``.nan`` and a word where a number belongs name their key; nothing is coerced."""
    base = open(str(_repo_config("pointpillars_synth.yaml"))).read()
    for bad, key in (("SCORE_THRESH: 0.1", "SCORE_THRESH: .nan"), ("NMS_THRESH: 0.01", "NMS_THRESH: high")):
        cfg = tmp_path / f"{key.split(':')[0]}.yaml"
        cfg.write_text(base.replace(bad, key).replace("_BASE_CONFIG_: datasets/kitti.yaml",
                                                         f"_BASE_CONFIG_: {_repo_config('kitti.yaml')}"))
        with pytest.raises(ConfigError, match=key.split(":")[0]):
            PointPillars(load_config(cfg))


def test_anchor_thresholds_and_sizes_are_checked():
    cfg = PointPillarsConfig().to_dict()
    cfg["anchor_generator_config"][1]["anchor_sizes"] = [[0.8, math.nan, 1.73]]
    with pytest.raises(ConfigError, match=r"ANCHOR_GENERATOR_CONFIG\[1\]\.anchor_sizes"):
        PointPillarsConfig.from_dict(cfg)
    cfg = PointPillarsConfig().to_dict()
    cfg["anchor_generator_config"][0]["unmatched_threshold"] = 0.9
    with pytest.raises(ConfigError, match="unmatched_threshold 0.9 must not exceed matched_threshold 0.6"):
        PointPillarsConfig.from_dict(cfg)


def _repo_config(name: str):
    from pathlib import Path

    return sorted((Path(__file__).resolve().parents[2] / "configs").rglob(name))[0]


def test_config_files_in_other_encodings_and_cycles(tmp_path):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"MODEL:\n  NAME: \xff\xfe\x00")
    with pytest.raises(ConfigError, match=r"binary.yaml: not a YAML text file"):
        load_config(binary)
    bom = tmp_path / "bom.yaml"
    bom.write_bytes("\ufeffCLASS_NAMES: ['Car']\n".encode("utf-8"))
    assert load_config(bom) == {"CLASS_NAMES": ["Car"]}  # the first key is CLASS_NAMES, not '\ufeffCLASS_NAMES'
    loop = tmp_path / "loop.yaml"
    loop.write_text("_BASE_CONFIG_: loop.yaml\nX: 1\n")
    with pytest.raises(ConfigError, match="includes itself"):
        load_config(loop)


# ---------------------------------------------------------------------------------------------
# the detector's batch
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def shipped():
    return weights.load()


@pytest.mark.parametrize("batch_size", [10_000, 2**24, 2**40])
def test_a_batch_size_the_points_do_not_hold_is_refused_before_allocating(shipped, batch_size):
    with pytest.raises(ValueError, match=rf"batch\['batch_size'\]={batch_size} but batch\['points'\] holds 0 point"):
        shipped.predict({"points": torch.zeros(0, 5), "batch_size": batch_size})


def test_frames_without_points_are_named(shipped):
    points = torch.tensor([[0, 10.0, 0, -1, 0.5], [2, 10.0, 1, -1, 0.5], [2, 11.0, 1, -1, 0.5]])
    with pytest.raises(ValueError, match=r"names no point of frame\(s\) \[1\] of batch\['batch_size'\]=3"):
        shipped.predict({"points": points, "batch_size": 3})
    assert len(shipped.predict({"points": torch.zeros(0, 5), "batch_size": 1})) == 1  # an empty scan: no boxes


# ---------------------------------------------------------------------------------------------
# box ops: values outside the supported range are refused (headings, sizes, centres)
# ---------------------------------------------------------------------------------------------
def _pair(heading=0.3, size=None):
    b = torch.tensor([[0.0, 0, 0, 2, 1, 1, heading], [0.5, 0, 0, 2, 1, 1, heading]], dtype=torch.float64)
    if size is not None:
        b[:, 3:6] = size
    return b


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("boxes", [_pair(heading=1e20), _pair(heading=-2e6), _pair(size=1e160), _pair(size=1e-200),
                                   _pair(size=-1.0)], ids=["heading 1e20", "heading -2e6", "size 1e160",
                                                           "size 1e-200", "size -1"])
def test_box_values_out_of_range_are_refused(device, boxes):
    boxes = boxes.to(device)
    scores = torch.tensor([0.9, 0.8], device=device)
    pattern = r"must hold centres within 1e\+06 m, sizes .* and headings within 1e\+06 rad; rows \[0, 1\]"
    for call in (lambda: lidarops.box_iou_bev(boxes, boxes), lambda: lidarops.box_iou_3d(boxes, boxes),
                 lambda: lidarops.box_overlap_bev(boxes, boxes), lambda: lidarops.nms_bev(boxes, scores, 0.1),
                 lambda: lidarops.nms_bev(boxes, scores, 0.1, padded=True),
                 lambda: lidarops.batched_nms_bev(boxes, scores, torch.zeros(2, dtype=torch.long, device=device), 0.1),
                 lambda: lidarops.points_in_boxes(torch.zeros(3, 3, dtype=boxes.dtype, device=device), boxes)):
        with pytest.raises(ValueError, match=pattern):
            call()


@pytest.mark.parametrize("device", DEVICES)
def test_headings_up_to_the_bound_are_exact(device):
    """Identical boxes have IoU 1 at any heading within the bound, and the op agrees with the float64 reference
    (which reduces the heading with Python's exact math.cos) there."""
    from lidarops.ops import references

    for heading in (1e5, -9.9e5, 123456.789):
        b = _pair(heading=heading)
        iou = lidarops.box_iou_bev(b.to(device), b.to(device)).cpu()
        assert iou[0, 0] == iou[1, 1] == 1.0
        assert torch.allclose(iou, references.box_iou_bev(b, b), atol=1e-9)


def test_padded_must_be_a_bool():
    b = _pair()
    with pytest.raises(ValueError, match="padded must be True or False, got 'no'"):
        lidarops.nms_bev(b, torch.tensor([0.9, 0.8]), 0.1, padded="no")


def test_pairwise_outputs_that_cannot_fit_are_refused_before_allocating():
    a = torch.zeros(1, 7).expand(50_000, 7)  # a view: no memory for the boxes either
    with pytest.raises(ValueError, match=r"a \(50000 boxes\) and b \(50000 boxes\): the pairwise matrix"):
        lidarops.box_iou_bev(a, a)


def test_meta_tensors_do_not_reach_data_dependent_kernels():
    m = torch.empty(5, 7, device="meta")
    with pytest.raises(ValueError, match="meta device: the number of boxes kept is data"):
        lidarops.nms_bev(m, torch.empty(5, device="meta"), 0.1)
    with pytest.raises(ValueError, match="meta device"):
        lidarops.batched_nms_bev(m, torch.empty(5, device="meta"), torch.zeros(5, dtype=torch.long, device="meta"), 0.1)
    keep, count = lidarops.nms_bev(m, torch.empty(5, device="meta"), 0.1, padded=True)  # shapes only: fine
    assert keep.device.type == "meta" and keep.shape == (5,)


# ---------------------------------------------------------------------------------------------
# KITTI readers and the evaluator
# ---------------------------------------------------------------------------------------------
_ROW = "Car 0.00 0 -1.57 100.00 150.00 200.00 200.00 1.50 1.60 3.90 1.00 1.50 20.00 -1.57"


def test_a_byte_order_mark_is_not_part_of_the_first_type(tmp_path):
    from lidarops.data.formats.kitti import KittiCalib, read_calib, read_label, write_calib

    plain, bom = tmp_path / "plain.txt", tmp_path / "bom.txt"
    plain.write_text(_ROW + "\n")
    bom.write_bytes(b"\xef\xbb\xbf" + (_ROW + "\n").encode())
    assert read_label(bom).names == ["Car"] == read_label(plain).names
    write_calib(tmp_path / "calib.txt", KittiCalib.default())
    text = (tmp_path / "calib.txt").read_bytes()
    (tmp_path / "calib_bom.txt").write_bytes(b"\xef\xbb\xbf" + text)
    a, b = read_calib(tmp_path / "calib.txt"), read_calib(tmp_path / "calib_bom.txt")
    assert np.array_equal(a.P2, b.P2) and np.array_equal(a.R0_rect, b.R0_rect)


def test_objects_with_non_positive_sizes_are_refused_by_line(tmp_path):
    from lidarops.data.formats.kitti import read_label

    path = tmp_path / "000000.txt"
    path.write_text("DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n"
                    + _ROW.replace("1.60 3.90", "-1.60 3.90") + "\n")
    with pytest.raises(ValueError, match=r"000000.txt:2: a Car with dimensions h, w, l = \['1.50', '-1.60', '3.90'\]"):
        read_label(path)


@pytest.mark.parametrize("truncation, level", [("0.15", "easy"), ("0.30", "moderate"), ("0.50", "hard")])
def test_truncation_on_a_difficulty_boundary_counts_as_kitti_reads_it(tmp_path, truncation, level):
    """KITTI's evaluator reads fields as double: a truncation of exactly 0.15 is easy (<= 0.15), which a
    float32 read (0.15000000596) put one level down."""
    from lidarops.eval import kitti

    occluded = {"easy": 0, "moderate": 1, "hard": 2}[level]
    row = _ROW.replace("Car 0.00 0", f"Car {truncation} {occluded}")
    (tmp_path / "000000.txt").write_text(row + "\n")
    counts = kitti.count_difficulties(kitti.read_annos(tmp_path))
    assert counts["Car"][level] == 1, counts


# ---------------------------------------------------------------------------------------------
# the command line
# ---------------------------------------------------------------------------------------------
def test_detect_frames_zero_is_refused(capsys, tmp_path):
    from lidarops.cli import main

    assert main(["detect", "--scenario", "driving_city", "--frames", "0", "--device", "cpu",
                 "--out", str(tmp_path)]) == 2
    _one_line(capsys, "detect", "--frames must be >= 1")


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_detect_tells_nuscenes_scans_from_kitti_ones(tmp_path, capsys):
    from lidarops.cli import main
    from lidarops.data.formats.nuscenes import write_nuscenes_bin

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-20, 20, (400, 2)), rng.uniform(-2, 1, 400), rng.uniform(0, 255, 400)].astype(np.float32)
    scan = write_nuscenes_bin(tmp_path / "n015-2018_LIDAR_TOP__1532402927647951.pcd.bin", points)
    assert scan.stat().st_size % 16 == 0  # 400 points of 20 bytes: a whole number of KITTI records too
    assert main(["detect", str(scan), "--device", "cpu", "--out", str(tmp_path / "a"), "--png", "0"]) == 0
    assert "1532402927647951" in capsys.readouterr().out
    loose = tmp_path / "scan.bin"
    loose.write_bytes(scan.read_bytes())
    assert main(["detect", str(loose), "--device", "cpu", "--out", str(tmp_path / "b")]) == 2
    _one_line(capsys, "detect", "fit both KITTI's 4 and nuScenes' 5 floats", "--format")
    assert main(["detect", str(loose), "--format", "nuscenes", "--device", "cpu", "--out", str(tmp_path / "c"),
                 "--png", "0"]) == 0


def test_detect_meta_device_is_one_line(capsys, tmp_path):
    from lidarops.cli import main

    assert main(["detect", "--scenario", "driving_city", "--device", "meta", "--out", str(tmp_path)]) == 2
    _one_line(capsys, "detect", "--device")


def test_binary_split_file_names_the_file(capsys, tmp_path):
    from lidarops.cli import main

    (tmp_path / "r").mkdir()
    (tmp_path / "split.txt").write_bytes(b"000000\n\xff\xfe\x00\n")
    assert main(["eval", "--results", str(tmp_path / "r"), "--labels", str(tmp_path / "r"),
                 "--split", str(tmp_path / "split.txt")]) == 2
    _one_line(capsys, "eval", "split.txt: not a text file")


# ---------------------------------------------------------------------------------------------
# sparse and stream edges
# ---------------------------------------------------------------------------------------------
def test_pillar_coords_are_range_checked_before_the_int32_cast():
    from lidarops.stream import PillarGrid, PillarStream

    grid = PillarGrid((0.0, 0.0, -1.0, 4.0, 4.0, 1.0), (0.5, 0.5))
    stream = PillarStream(grid, window=0.1)
    stream.push(torch.tensor([[0.2, 0.2, 0.0, 0.5]]), torch.tensor([0.0], dtype=torch.float64))
    wraps = torch.tensor([[0, 2**32, 2**32]])  # int32 of 2^32 is 0: the active pillar (0, 0)
    with pytest.raises(ValueError, match=r"coords\[0\] = \[0, 4294967296, 4294967296\] is not an active pillar"):
        stream.pillars(wraps)
    assert stream.pillars(torch.tensor([[0, 0, 0]])).num_points.tolist() == [1]


def test_a_window_below_the_time_resolution_is_refused():
    from lidarops.stream import PillarGrid, PillarStream

    with pytest.raises(ValueError, match="window must be a finite number of seconds >= 1e-05"):
        PillarStream(PillarGrid.kitti(), window=1e-300)


def test_a_simulated_stream_span_is_bounded():
    from lidarops.data import Simulator

    with pytest.raises(ValueError, match=r"span \[t0, t1\) of stream\(\) is at most 10 s, got 100000 s"):
        Simulator("driving_city", seed=0).stream(0.0, 1e5)


def _delta():
    from lidarops.sscater import DeltaBackbone

    from helpers.models import small_backbone

    return DeltaBackbone(small_backbone().eval(), (16, 16))


def test_delta_update_refuses_wrapped_duplicate_and_nan_input():
    delta = _delta()
    cin = delta.in_channels
    delta.refresh(torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0, cin))
    feats = torch.ones(2, cin)
    removed = torch.zeros(2, dtype=torch.bool)
    with pytest.raises(ValueError, match="outside the"):
        delta.update(torch.tensor([[2**32 + 1, 1], [0, 0]]), feats, removed)  # would wrap to (1, 1)
    with pytest.raises(ValueError, match=r"each appear once: \(1, 1\)"):
        delta.update(torch.tensor([[1, 1], [1, 1]]), feats, removed)
    bad = feats.clone()
    bad[1, 0] = math.nan
    with pytest.raises(ValueError, match="features must be finite"):
        delta.update(torch.tensor([[1, 1], [2, 2]]), bad, removed)
    delta.update(torch.tensor([[1, 1], [2, 2]]), feats, removed)  # the same, right
    assert math.isfinite(delta.state_max)


def test_sparse_duplicate_sites_are_refused_by_dense_and_the_1x1_shortcut():
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs

    x = SparseConvTensor(torch.randn(3, 4), torch.tensor([[0, 1, 1], [0, 1, 1], [0, 2, 2]], dtype=torch.int32),
                         [4, 4], 1)
    with pytest.raises(ValueError, match=r"site \[0, 1, 1\] .* more than once"):
        x.dense()
    with pytest.raises(ValueError, match=r"site \[0, 1, 1\] .* more than once"):
        Fs.conv(x, torch.randn(8, 1, 1, 4), None, "subm")
    outside = SparseConvTensor(torch.randn(2, 4), torch.tensor([[0, 1, 1], [0, 9, 1]], dtype=torch.int32), [4, 4], 1)
    with pytest.raises(ValueError, match="outside"):
        Fs.conv(outside, torch.randn(8, 1, 1, 4), None, "subm")
