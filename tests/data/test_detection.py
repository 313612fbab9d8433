"""Tests of lidarops.data.detection (OpenPCDet-style detection items) and lidarops.data.augment (augmentations,
gt sampling); ``lidarops data synth`` for training sets: tests/cli/test_data.py."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lidarops
from lidarops.data import collate_batch
from lidarops.data.augment import (
    BOX_MARGIN_XY,
    GtDatabase,
    GtSampler,
    build_gt_database,
    flip_along_x,
    flip_along_y,
    rotate_world,
    scale_world,
)
from lidarops.data.detection import (
    DetectionConfig,
    KittiDetectionDataset,
    mask_boxes_outside_range,
    mask_points_by_range,
)
from lidarops.data.formats.kitti import (
    KittiCalib,
    camera_to_lidar_boxes,
    kitti_difficulty,
    kitti_fov_mask,
    read_label,
    read_velodyne,
    write_calib,
    write_kitti_frame,
    write_velodyne,
)
from lidarops.data.synthetic import Simulator

CLASSES = ("Car", "Pedestrian", "Cyclist")
NO_AUG = dict(augmentations=(), fov_points_only=False, mask_outside_range=False, shuffle_train=False)
HAND_LABELS = """Car 0.00 0 -1.57 600.00 170.00 700.00 230.00 1.500000 1.600000 3.900000 2.000000 1.650000 15.000000 -1.570000
Van 0.00 1 -1.50 400.00 160.00 500.00 220.00 2.100000 1.900000 4.800000 -4.000000 1.650000 20.000000 -1.500000
DontCare -1 -1 -10 800.00 150.00 900.00 200.00 -1 -1 -1 -1000 -1000 -1000 -10
Pedestrian 0.00 0 0.10 300.00 150.00 330.00 230.00 1.750000 0.600000 0.800000 -3.000000 1.650000 9.000000 0.100000
Truck 0.10 2 1.00 100.00 150.00 300.00 220.00 3.200000 2.500000 8.000000 -8.000000 1.650000 30.000000 1.000000
"""


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """Three simulated frames written as KITTI (train: 0-2, val: 2) and a hand-labelled frame 000003."""
    root = tmp_path_factory.mktemp("kitti")
    frames = [Simulator("driving_city", seed=s).sweep(0) for s in range(3)]
    for i, frame in enumerate(frames):
        write_kitti_frame(root, frame, frame_id=i)
    split = root / "training"
    write_velodyne(split / "velodyne" / "000003.bin", frames[0].points)
    (split / "calib" / "000003.txt").write_text((split / "calib" / "000000.txt").read_text())
    (split / "label_2" / "000003.txt").write_text(HAND_LABELS)
    (root / "ImageSets").mkdir()
    (root / "ImageSets" / "train.txt").write_text("000000\n000001\n000002\n")
    (root / "ImageSets" / "val.txt").write_text("000002\n")
    return root, frames


def _angle_diff(a, b):
    return np.abs((np.asarray(a, np.float64) - b + np.pi) % (2 * np.pi) - np.pi)


# ---------------------------------------------------------------------------------------------
# items
# ---------------------------------------------------------------------------------------------
def test_items_match_simulator_boxes(synth):
    root, frames = synth
    ds = KittiDetectionDataset(root, "train", training=False)
    assert len(ds) == 3 and ds.ids == ["000000", "000001", "000002"]
    calib = KittiCalib.default()
    for i, frame in enumerate(frames):
        item = ds[i]
        assert item["frame_id"] == f"{i:06d}" and isinstance(item["calib"], KittiCalib)
        assert item["points"].dtype == np.float32 and item["points"].shape[1] == 4
        assert item["gt_boxes"].dtype == np.float32 and item["gt_boxes"].shape[1] == 8
        names = np.array(frame.names)
        # write_kitti_frame labels boxes with points whose centre is in the camera's view
        keep = (frame.num_points_in_box >= 1) & kitti_fov_mask(frame.boxes[:, :3], calib) & np.isin(names, CLASSES)
        expected = frame.boxes[keep]
        got = item["gt_boxes"]
        assert got.shape[0] == expected.shape[0] > 0
        np.testing.assert_allclose(got[:, :6], expected[:, :6], atol=2e-4)
        assert _angle_diff(got[:, 6], expected[:, 6]).max() < 1e-4
        np.testing.assert_array_equal(got[:, 7], [CLASSES.index(n) + 1 for n in names[keep]])
        # annos: every label of the file, dimensions in the file's h, w, l
        labels = read_label(root / "training" / "label_2" / f"{i:06d}.txt")
        assert list(item["annos"]["name"]) == labels.names
        np.testing.assert_array_equal(item["annos"]["dimensions_hwl"], labels.dimensions)
        np.testing.assert_array_equal(item["annos"]["difficulty"], kitti_difficulty(labels))


def test_other_types_stay_out_of_gt_boxes_but_in_annos(synth):
    root, _ = synth
    for training in (False, True):
        ds = KittiDetectionDataset(root, ["000003"], training=training,
                                   config=DetectionConfig(**{**NO_AUG, "augmentations": ("random_world_flip",)}))
        item = ds[0]
        assert item["gt_boxes"][:, 7].tolist() == [1.0, 2.0]  # Car, Pedestrian: no Van, Truck, DontCare
        assert list(item["annos"]["name"]) == ["Car", "Van", "DontCare", "Pedestrian", "Truck"]
        np.testing.assert_array_equal(item["annos"]["dimensions_hwl"][1], [2.1, 1.9, 4.8])
        np.testing.assert_array_equal(item["annos"]["occluded"], [0, 1, -1, 0, 2])
    item = KittiDetectionDataset(root, ["000003"], training=False)[0]
    box = camera_to_lidar_boxes([[2.0, 1.65, 15.0]], [[1.5, 1.6, 3.9]], [-1.57], item["calib"])[0]
    np.testing.assert_allclose(item["gt_boxes"][0, :7], box, atol=1e-5)
    np.testing.assert_allclose(item["gt_boxes"][0, 3:6], [3.9, 1.6, 1.5], atol=1e-6)  # dx, dy, dz = l, w, h
    # other class lists: ids follow class_names
    item = KittiDetectionDataset(root, ["000003"], class_names=("Pedestrian", "Van"), training=False)[0]
    assert item["gt_boxes"][:, 7].tolist() == [2.0, 1.0]
    # in training, a frame without boxes is replaced by another (OpenPCDet's resampling), deterministically
    cfg = DetectionConfig(augmentations=("random_world_flip",))
    vans = KittiDetectionDataset(root, ["000003", "000001"], class_names=("Van",), config=cfg)
    assert vans[0]["frame_id"] == "000003" and "resampled_from" not in vans[0]["augmentation"]
    item = vans[1]
    assert item["frame_id"] == "000003" and item["augmentation"]["resampled_from"] == 1
    assert item["gt_boxes"].shape == (1, 8)
    assert KittiDetectionDataset(root, ["000003", "000001"], class_names=("Van",), config=cfg,
                                 training=False)[1]["gt_boxes"].shape == (0, 8)


def test_fov_and_range_crops(synth, tmp_path):
    root, _ = synth
    raw = read_velodyne(root / "training" / "velodyne" / "000001.bin")
    calib = KittiCalib.default()
    cfg = DetectionConfig()
    r = cfg.point_cloud_range
    in_range = (raw[:, 0] >= r[0]) & (raw[:, 0] <= r[3]) & (raw[:, 1] >= r[1]) & (raw[:, 1] <= r[4])
    item = KittiDetectionDataset(root, "train", training=False)[1]
    np.testing.assert_array_equal(item["points"], raw[kitti_fov_mask(raw, calib) & in_range])
    assert (item["points"][:, 2] > r[5]).any()  # like OpenPCDet, z is left to the voxelizer
    item = KittiDetectionDataset(root, "train", training=False, config=DetectionConfig(fov_points_only=False))[1]
    np.testing.assert_array_equal(item["points"], raw[in_range])
    # a real KITTI frame's image size comes from the header of image_2/<id>.png
    copy = tmp_path / "training"
    for sub, ext in (("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt")):
        (copy / sub).mkdir(parents=True)
        (copy / sub / f"000001.{ext}").write_bytes((root / "training" / sub / f"000001.{ext}").read_bytes())
    (copy / "image_2").mkdir()
    header = b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + b"IHDR" + (600).to_bytes(4, "big") + (200).to_bytes(4, "big")
    (copy / "image_2" / "000001.png").write_bytes(header + b"\x08\x02\x00\x00\x00")
    small = KittiDetectionDataset(tmp_path, None, training=False)
    assert small.image_size(0) == (600, 200)
    np.testing.assert_array_equal(small[0]["points"], raw[kitti_fov_mask(raw, calib, (600, 200)) & in_range])
    pts = np.array([[0, 0, 9, 1], [-0.01, 0, 0, 1], [69.12, 39.68, -9, 1], [69.13, 0, 0, 1], [1, -39.69, 0, 1]], np.float32)
    assert mask_points_by_range(pts, r).tolist() == [True, False, True, False, False]


def test_boxes_kept_by_centre_or_corners_as_openpcdet():
    # OpenPCDet's mask_boxes_outside_range_numpy (master since 2022, USE_CENTER_TO_FILTER default True)
    r = (0.0, -39.68, -3.0, 69.12, 39.68, 1.0)
    boxes = np.array([
        [10, 0, -1, 4, 2, 1.5, 0],            # inside
        [-1.9, 0, -1, 4, 2, 1.5, 0],          # centre outside, front corners inside
        [-2.1, 0, -1, 4, 2, 1.5, 0],          # all corners behind x0
        [-1.3, 0, -1, 2, 2, 1.5, math.pi / 4],  # rotated: only the corner at x = -1.3 + 1.414 inside
        [-1.5, 0, -1, 2, 2, 1.5, math.pi / 4],  # rotated: the nearest corner at x = -0.086
        [30, 41.0, -1, 4, 2, 1.5, 0],         # beyond y1 by more than half the width
        [30, 40.5, -1, 4, 2, 1.5, 0],         # straddles y1, centre outside
        [30, 0, 2.0, 4, 2, 1.5, 0],           # centre and every corner above z1
        [30, 0, 0.9, 4, 2, 1.5, 0],           # centre below z1, top above it
        [0.0, 39.68, -3.0, 4, 2, 1.5, 0],     # centre on the closed range's ends
    ], np.float32)
    assert mask_boxes_outside_range(boxes, r).tolist() == [True, False, False, False, False, False, False, False,
                                                           True, True]
    # the corner rule counts corners in x and y only
    corners = mask_boxes_outside_range(boxes, r, use_center_to_filter=False)
    assert corners.tolist() == [True, True, False, True, False, False, True, True, True, True]
    assert mask_boxes_outside_range(boxes, r, min_num_corners=8, use_center_to_filter=False).tolist() == \
        [True] + [False] * 6 + [True, True, False]


def test_training_items_drop_boxes_whose_centre_is_out_of_range(synth):
    root, _ = synth
    box = KittiDetectionDataset(root, ["000001"], training=False)[0]["gt_boxes"][0]
    # a range starting 0.2 m past a box's centre: its centre is out, its far corners in
    near = (float(box[0]) + 0.2, -39.68, -3.0, 69.12, 39.68, 1.0)
    for use_centre in (True, False):
        cfg = DetectionConfig(**{**NO_AUG, "mask_outside_range": True, "point_cloud_range": near,
                                 "use_center_to_filter": use_centre})
        got = KittiDetectionDataset(root, ["000001"], config=cfg)[0]["gt_boxes"]
        every = KittiDetectionDataset(root, ["000001"], config=cfg, training=False)[0]["gt_boxes"]
        np.testing.assert_array_equal(got, every[mask_boxes_outside_range(every, near, 1, use_centre)])
        centres_in = ((every[:, :3] >= near[:3]) & (every[:, :3] <= near[3:])).all(1)
        if use_centre:
            assert got.shape[0] == int(centres_in.sum()) < every.shape[0]
        else:
            assert got.shape[0] > int(centres_in.sum())
    corner_rule = [{"NAME": "mask_points_and_boxes_outside_range", "USE_CENTER_TO_FILTER": False}]
    assert DetectionConfig.from_openpcdet({"DATA_PROCESSOR": corner_rule}).use_center_to_filter is False
    assert DetectionConfig().use_center_to_filter


# ---------------------------------------------------------------------------------------------
# augmentations
# ---------------------------------------------------------------------------------------------
def _scene(seed=0, n_boxes=6):
    """Non-overlapping boxes, points well inside them and background points away from all of them."""
    rng = np.random.default_rng(seed)
    boxes = np.zeros((n_boxes, 7), np.float32)
    boxes[:, 0] = 8.0 * np.arange(n_boxes) + 5
    boxes[:, 1] = rng.uniform(-10, 10, n_boxes)
    boxes[:, 2] = -1.0
    boxes[:, 3:6] = rng.uniform([3, 1.5, 1.4], [4.5, 2.0, 1.8], (n_boxes, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n_boxes)
    local = rng.uniform(-0.45, 0.45, (n_boxes, 50, 3)) * boxes[:, None, 3:6]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    inside = np.stack([c * local[..., 0] - s * local[..., 1], s * local[..., 0] + c * local[..., 1], local[..., 2]], -1)
    inside = (inside + boxes[:, None, :3]).reshape(-1, 3)
    background = np.stack([rng.uniform(0, 50, 300), rng.uniform(25, 40, 300), rng.uniform(-2, 1, 300)], 1)
    xyz = np.concatenate([inside, background]).astype(np.float32)
    return np.concatenate([xyz, rng.uniform(0, 1, (xyz.shape[0], 1)).astype(np.float32)], 1), boxes


def _owner(points, boxes):
    return lidarops.points_in_boxes(torch.from_numpy(points), torch.from_numpy(np.ascontiguousarray(boxes[:, :7]))).numpy()


def test_world_transforms_hand_computed():
    p = np.array([[1.0, 2.0, 3.0, 0.5]], np.float32)
    b = np.array([[1.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.3, 2.0]], np.float32)
    fp, fb = flip_along_x(p, b)
    np.testing.assert_array_equal(fp, [[1, -2, 3, 0.5]])
    np.testing.assert_allclose(fb, [[1, -2, -1, 4, 2, 1.5, -0.3, 2]])
    fp, fb = flip_along_y(p, b)
    np.testing.assert_array_equal(fp, [[-1, 2, 3, 0.5]])
    np.testing.assert_allclose(fb, [[-1, 2, -1, 4, 2, 1.5, -(0.3 + np.pi), 2]], rtol=1e-6)
    rp, rb = rotate_world(p, b, np.pi / 2)
    np.testing.assert_allclose(rp, [[-2, 1, 3, 0.5]], atol=1e-6)
    np.testing.assert_allclose(rb, [[-2, 1, -1, 4, 2, 1.5, 0.3 + np.pi / 2, 2]], atol=1e-6)
    sp, sb = scale_world(p, b, 1.05)
    np.testing.assert_allclose(sp, [[1.05, 2.1, 3.15, 0.5]], rtol=1e-6)
    np.testing.assert_allclose(sb, [[1.05, 2.1, -1.05, 4.2, 2.1, 1.575, 0.3, 2]], rtol=1e-6)
    assert p.tolist() == [[1.0, 2.0, 3.0, 0.5]]  # inputs untouched
    points, boxes = _scene()
    before = _owner(points, boxes)
    assert (before >= 0).sum() == 300 and (before < 0).sum() == 300
    for fn in (flip_along_x, flip_along_y, lambda q, c: rotate_world(q, c, 0.7), lambda q, c: scale_world(q, c, 0.95)):
        q, c = fn(points, boxes)
        np.testing.assert_array_equal(_owner(q, c), before)


def test_dataset_augmentations_follow_reported_draws(synth):
    root, _ = synth
    cfg = DetectionConfig(**{**NO_AUG, "augmentations": ("random_world_flip", "random_world_rotation",
                                                         "random_world_scaling")})
    base = KittiDetectionDataset(root, "train", training=False, config=cfg)
    ds = KittiDetectionDataset(root, "train", training=True, config=cfg)
    seen_flip, angles = set(), []
    for epoch in range(6):
        ds.set_epoch(epoch)
        ref, item = base[0], ds[0]
        aug = item["augmentation"]
        seen_flip.add(aug["flip_x"])
        angles.append(aug["rotation"])
        assert -np.pi / 4 <= aug["rotation"] <= np.pi / 4 and 0.95 <= aug["scale"] <= 1.05 and not aug["flip_y"]
        x, y, z = (ref["points"][:, i].astype(np.float64) for i in range(3))
        if aug["flip_x"]:
            y = -y
        c, s = math.cos(aug["rotation"]), math.sin(aug["rotation"])
        expected = np.stack([(c * x - s * y) * aug["scale"], (s * x + c * y) * aug["scale"], z * aug["scale"]], 1)
        np.testing.assert_allclose(item["points"][:, :3], expected, atol=2e-5)
        np.testing.assert_array_equal(item["points"][:, 3], ref["points"][:, 3])
        b = ref["gt_boxes"].astype(np.float64)
        bx, by, heading = b[:, 0], (-b[:, 1] if aug["flip_x"] else b[:, 1]), (-b[:, 6] if aug["flip_x"] else b[:, 6])
        np.testing.assert_allclose(item["gt_boxes"][:, 0], (c * bx - s * by) * aug["scale"], atol=2e-5)
        np.testing.assert_allclose(item["gt_boxes"][:, 1], (s * bx + c * by) * aug["scale"], atol=2e-5)
        np.testing.assert_allclose(item["gt_boxes"][:, 2:6], b[:, 2:6] * aug["scale"], rtol=1e-6)
        assert _angle_diff(item["gt_boxes"][:, 6], heading + aug["rotation"]).max() < 1e-5
        assert item["gt_boxes"][:, 6].min() >= -np.float32(np.pi) and item["gt_boxes"][:, 6].max() <= np.float32(np.pi)
        np.testing.assert_array_equal(item["gt_boxes"][:, 7], ref["gt_boxes"][:, 7])
    assert seen_flip == {False, True} and len(set(angles)) == 6


def test_transfer_augmentations_follow_reported_draws(synth):
    """random_point_dropout, random_intensity and random_beam_drop (lidarops' own, from an OpenPCDet-style
    AUG_CONFIG_LIST): the kept points are a subset of the frame's in its order, at about the reported rate;
    the intensities are the reported scale and zero share of the originals (jitter off here); a beam drop
    keeps every other elevation bin; boxes are untouched; OpenPCDet configs without them are unchanged."""
    root, _ = synth
    entries = [{"NAME": "random_point_dropout", "DROP_RANGE": [0.1, 0.4]},
               {"NAME": "random_intensity", "SCALE_RANGE": [0.5, 1.5], "JITTER": 0.0, "ZERO_RANGE": [0.1, 0.3]},
               {"NAME": "random_beam_drop", "PROB": 0.5, "BIN_DEG": 0.42}]
    cfg = DetectionConfig.from_openpcdet({"DATA_AUGMENTOR": {"AUG_CONFIG_LIST": entries}, "FOV_POINTS_ONLY": False,
                                          "DATA_PROCESSOR": [{"NAME": "transform_points_to_voxels"}]})
    assert cfg.augmentations == ("random_point_dropout", "random_intensity", "random_beam_drop")
    assert DetectionConfig().augmentations == ("gt_sampling", "random_world_flip", "random_world_rotation",
                                               "random_world_scaling")
    base = KittiDetectionDataset(root, "train", training=False, config=DetectionConfig(**NO_AUG))
    ds = KittiDetectionDataset(root, "train", training=True, config=cfg)
    ref = base[0]["points"].astype(np.float64)
    drops = set()
    for epoch in range(8):
        ds.set_epoch(epoch)
        item = ds[0]
        aug = item["augmentation"]
        assert 0.1 <= aug["point_dropout"] <= 0.4 and 0.5 <= aug["intensity_scale"] <= 1.5
        assert 0.1 <= aug["intensity_zero"] <= 0.3
        drops.add(aug["beam_drop"])
        # each kept point is one of the frame's, in the frame's order: match on xyz
        key = {tuple(p): i for i, p in enumerate(np.round(ref[:, :3], 5))}
        idx = np.array([key[tuple(p)] for p in np.round(item["points"][:, :3].astype(np.float64), 5)])
        assert (np.diff(idx) > 0).all()
        kept = len(idx) / len(ref)
        expect = (1 - aug["point_dropout"]) * (0.5 if aug["beam_drop"] else 1.0)
        assert abs(kept - expect) < 0.08, (kept, expect)
        i_new, i_old = item["points"][:, 3].astype(np.float64), ref[idx, 3]
        zero = i_new == 0
        assert abs(zero.mean() - aug["intensity_zero"]) < 0.05 + (i_old == 0).mean()
        np.testing.assert_allclose(i_new[~zero], np.clip(i_old[~zero] * aug["intensity_scale"], 0, 1), atol=1e-6)
        np.testing.assert_array_equal(item["gt_boxes"], base[0]["gt_boxes"])
    assert drops == {False, True}


def test_beam_drop_keeps_every_other_elevation_bin():
    from lidarops.data.detection import drop_alternate_beams

    elev = np.radians(np.array([0.1, 0.5, 0.9, -0.1, -0.5]))  # bins of 0.42 deg: 0, 1, 2, -1, -2
    pts = np.stack([10 * np.cos(elev), np.zeros(5), 10 * np.sin(elev), np.ones(5)], 1).astype(np.float32)
    np.testing.assert_array_equal(drop_alternate_beams(pts, 0.42, 0), pts[[0, 2, 4]])
    np.testing.assert_array_equal(drop_alternate_beams(pts, 0.42, 1), pts[[1, 3]])


@pytest.mark.parametrize("kw,name", [({"point_dropout_range": (0.2, 1.5)}, "point_dropout_range"),
                                     ({"intensity_zero_range": (-0.1, 0.2)}, "intensity_zero_range"),
                                     ({"intensity_scale_range": (1.2, 0.8)}, "intensity_scale_range"),
                                     ({"intensity_jitter": float("nan")}, "intensity_jitter"),
                                     ({"beam_drop_prob": 2.0}, "beam_drop_prob"), ({"beam_bin_deg": 0.0}, "beam_bin_deg")])
def test_transfer_augmentation_options_are_checked(kw, name):
    with pytest.raises(ValueError, match=name):
        DetectionConfig(**kw)


# ---------------------------------------------------------------------------------------------
# gt database and sampling
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def database(synth, tmp_path_factory):
    root, _ = synth
    path = tmp_path_factory.mktemp("db") / "db.npz"
    return build_gt_database(root, "train", class_names=None, out_path=path), path


def test_gt_database(synth, database):
    root, _ = synth
    db, path = database
    again = GtDatabase.load(path)
    rebuilt = build_gt_database(root, ["000000", "000001", "000002"], class_names=None)
    for name in GtDatabase._FIELDS:
        np.testing.assert_array_equal(getattr(again, name), getattr(db, name))
        np.testing.assert_array_equal(getattr(rebuilt, name), getattr(db, name))
    assert "DontCare" not in db.names and list(db.source_ids) == ["000000", "000001", "000002"]
    assert np.diff(db.offsets).tolist() == db.num_points.tolist() and db.num_points.max() > 20
    assert db.margin == again.margin == BOX_MARGIN_XY == 0.01
    for i in range(len(db)):
        pts = db.object_points(i)
        grown = _xy_grown(db.boxes[i:i + 1])
        grown[:, 3:6] += 1e-3  # the centre's float32 round trip
        assert (_owner(pts, grown) == 0).all()
        raw = read_velodyne(root / "training" / "velodyne" / f"{db.frame_ids[i]}.bin")
        assert (_owner(raw, _xy_grown(db.boxes[i:i + 1])) == 0).sum() == db.num_points[i]
        labels = read_label(root / "training" / "label_2" / f"{db.frame_ids[i]}.txt")
        assert labels.names[db.gt_index[i]] == db.names[i]
        assert kitti_difficulty(labels)[db.gt_index[i]] == db.difficulty[i]
    cars = build_gt_database(root, "val", class_names=("Car",))
    assert set(cars.names) == {"Car"} and set(cars.frame_ids) == {"000002"}


def _xy_grown(boxes, margin=BOX_MARGIN_XY):
    """Boxes (M, 7) with ``margin`` added to each half-length and half-width, as OpenPCDet's CPU box test."""
    grown = np.array(boxes[:, :7], dtype=np.float32)
    grown[:, 3:5] += 2 * margin
    return grown


def test_gt_database_gathers_points_as_openpcdet(synth, database):
    # OpenPCDet's create_groundtruth_database takes an object's points with its points_in_boxes_cpu, which
    # counts a point up to 1 cm beyond the box's sides (not above or below it). lidarops.compat.pcdet's
    # face of it gives OpenPCDet's own masks (compared with OpenPCDet's compiled op: docs/compat.md).
    from lidarops.compat.pcdet import roiaware_pool3d_utils

    root, _ = synth
    db, _ = database
    short = 0
    for frame_id in db.source_ids:
        raw = read_velodyne(root / "training" / "velodyne" / f"{frame_id}.bin")
        rows = np.flatnonzero(db.frame_ids == frame_id)
        mask = roiaware_pool3d_utils.points_in_boxes_cpu(raw[:, :3], db.boxes[rows])  # (M, N) int32
        np.testing.assert_array_equal(db.num_points[rows], mask.sum(1))
        short += int((_owner(raw, db.boxes[rows]) >= 0).sum())
    assert short < 0.9 * db.num_points.sum()  # the margin matters on simulated surfaces: > 10 % of the points


def test_gt_database_margin_hand_computed(synth, tmp_path):
    root, _ = synth
    calib = KittiCalib.default()
    label = "Car 0.00 0 -1.57 600.00 170.00 700.00 230.00 1.500000 1.600000 3.900000 2.000000 1.650000 15.000000 -1.570000\n"
    box = camera_to_lidar_boxes([[2.0, 1.65, 15.0]], [[1.5, 1.6, 3.9]], [-1.57], calib)[0].astype(np.float64)
    # points in the box's own frame: half sizes 1.95, 0.8, 0.75
    local = np.array([[0, 0, 0], [1.955, 0, 0], [-1.965, 0.3, 0], [0, 0.809, 0.2], [0.5, -0.811, 0],
                      [0, 0, 0.74], [0, 0, 0.755], [1.958, 0.807, -0.7]])
    inside = [True, True, False, True, False, True, False, True]
    c, s = math.cos(box[6]), math.sin(box[6])
    pts = np.stack([box[0] + c * local[:, 0] - s * local[:, 1], box[1] + s * local[:, 0] + c * local[:, 1],
                    box[2] + local[:, 2], np.full(len(local), 0.5)], 1).astype(np.float32)
    split = tmp_path / "training"
    write_velodyne(split / "velodyne" / "000000.bin", pts)
    write_calib(split / "calib" / "000000.txt", calib)
    (split / "label_2").mkdir()
    (split / "label_2" / "000000.txt").write_text(label)
    db = build_gt_database(tmp_path, ["000000"], class_names=("Car",))
    assert db.num_points.tolist() == [sum(inside)] and db.margin == 0.01
    np.testing.assert_allclose(db.object_points(0), pts[inside], atol=1e-5)
    assert build_gt_database(tmp_path, ["000000"], class_names=("Car",), margin=0.0).num_points.tolist() == [2]
    with pytest.raises(ValueError, match="margin"):
        build_gt_database(tmp_path, ["000000"], margin=-0.01)
    # gt sampling clears the scene under a pasted box with the same margin (OpenPCDet's remove_points_in_boxes3d)
    one = GtDatabase(points=np.zeros((1, 4), np.float32), offsets=np.array([0, 1]), boxes=box[None].astype(np.float32),
                     names=np.array(["Car"]), num_points=np.array([1]), difficulty=np.zeros(1, np.int64),
                     frame_ids=np.array(["a"]), gt_index=np.zeros(1, np.int64), source_ids=np.array(["a"]))
    out, _, _ = GtSampler(one, {"Car": 1}, None, CLASSES)(pts, np.zeros((0, 7), np.float32), np.array([], str),
                                                           np.random.default_rng(0))
    np.testing.assert_array_equal(out[1:], pts[~np.array(inside)])


def test_cached_gt_database_gathered_without_the_margin_is_rebuilt(synth, tmp_path):
    root, _ = synth
    copy = tmp_path / "kitti"
    (copy / "ImageSets").mkdir(parents=True)
    (copy / "ImageSets" / "train.txt").write_text((root / "ImageSets" / "train.txt").read_text())
    (copy / "training").symlink_to(root / "training")
    old = build_gt_database(root, "train", class_names=None, margin=0.0)
    path = copy / "gt_database_train.npz"
    # a file as lidarops wrote them before the margin was recorded: no 'margin' array
    np.savez(path, **{name: getattr(old, name) for name in GtDatabase._FIELDS})
    assert GtDatabase.load(path).margin == 0.0
    ds = KittiDetectionDataset(copy, "train", seed=0)
    db = ds.sampler.database
    assert db.margin == BOX_MARGIN_XY and (db.num_points >= old.num_points).all()
    assert db.num_points.sum() > old.num_points.sum()
    assert GtDatabase.load(path).margin == BOX_MARGIN_XY  # rewritten
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{name: getattr(old, name) for name in GtDatabase._FIELDS}, margin=np.array([0.01, 0.02]))
    with pytest.raises(ValueError, match="margin"):
        GtDatabase.load(bad)


def _sampled_rows(db, boxes):
    return np.array([np.flatnonzero((db.boxes == b).all(1))[0] for b in boxes], np.int64)


@pytest.mark.parametrize("limit_whole_scene", [False, True])
def test_gt_sampling(synth, database, limit_whole_scene):
    root, _ = synth
    db, _ = database
    groups, min_points = {"Car": 15, "Pedestrian": 6, "Cyclist": 4}, {"Car": 12, "Pedestrian": 5, "Cyclist": 5}
    sampler = GtSampler(db, [f"{k}:{v}" for k, v in groups.items()], [f"{k}:{v}" for k, v in min_points.items()],
                        CLASSES, limit_whole_scene=limit_whole_scene)
    every_type = ("Car", "Pedestrian", "Cyclist", "Truck", "Bus", "Barrier", "TrafficCone")
    scene = KittiDetectionDataset(root, ["000001"], training=False, class_names=every_type,
                                  config=DetectionConfig(mask_outside_range=False))[0]
    points, boxes = scene["points"], scene["gt_boxes"][:, :7]
    names = np.array(every_type)[scene["gt_boxes"][:, 7].astype(int) - 1]
    total = 0
    for seed in range(4):
        out_points, out_boxes, out_names = sampler(points, boxes, names, np.random.default_rng(seed))
        m = boxes.shape[0]
        np.testing.assert_array_equal(out_boxes[:m], boxes)
        new = out_boxes[m:]
        rows = _sampled_rows(db, new)
        total += rows.size
        np.testing.assert_array_equal(out_names[m:], db.names[rows])
        for name, group in groups.items():
            count = int(np.sum(db.names[rows] == name))
            assert count <= (group - int(np.sum(names == name)) if limit_whole_scene else group)
        assert (db.num_points[rows] >= np.array([min_points[n] for n in db.names[rows]])).all()
        assert (db.difficulty[rows] != -1).all()
        iou = lidarops.box_iou_bev(torch.from_numpy(new), torch.from_numpy(out_boxes)).numpy()
        iou[np.arange(new.shape[0]), m + np.arange(new.shape[0])] = 0
        assert iou.max(initial=0) == 0  # no overlap with the scene's boxes nor with each other
        n_pasted = int(db.num_points[rows].sum())
        pasted, kept = out_points[:n_pasted], out_points[n_pasted:]
        grown = _xy_grown(new)
        grown[:, 3:6] += 1e-3
        owner = _owner(pasted, grown)
        assert (owner >= 0).all() and np.array_equal(np.bincount(owner, minlength=len(rows)), db.num_points[rows])
        # the scene's points inside the pasted boxes, 1 cm beyond their sides included, are gone
        assert (_owner(kept, _xy_grown(new)) < 0).all()
        assert kept.shape[0] == int((_owner(points, _xy_grown(new)) < 0).sum())
    assert total > 0
    strict = GtSampler(db, {"Car": 50}, {"Car": 10_000}, CLASSES)
    assert strict.pools["Car"].size == 0
    assert strict(points, boxes, names, np.random.default_rng(0))[1].shape == boxes.shape


def test_gt_sampling_drops_drawn_boxes_that_collide():
    # four database objects: a and b overlap each other, c overlaps the scene's box, d is free
    boxes = np.array([[10, 0, -1, 4, 2, 1.5, 0], [11, 0.5, -1, 4, 2, 1.5, 0.3], [20, 5, -1, 4, 2, 1.5, 0],
                      [30, -5, -1, 4, 2, 1.5, 0]], np.float32)
    rel = np.array([[0.5, 0.2, 0.1, 0.3], [-0.5, -0.2, 0.0, 0.6]], np.float32)
    db = GtDatabase(points=np.tile(rel, (4, 1)), offsets=np.arange(0, 10, 2), boxes=boxes, names=np.array(["Car"] * 4),
                    num_points=np.full(4, 2), difficulty=np.zeros(4, np.int64), frame_ids=np.array(["a"] * 4),
                    gt_index=np.arange(4), source_ids=np.array(["a"]))
    scene_boxes = np.array([[21, 5.5, -1, 4, 2, 1.5, 0.2]], np.float32)
    scene_points = np.array([[30, -5, -1, 1], [30.5, -5, -1.2, 1], [0, 0, 0, 1]], np.float32)
    sampler = GtSampler(db, {"Car": 4}, None, CLASSES)
    points, out_boxes, names = sampler(scene_points, scene_boxes, np.array(["Car"]), np.random.default_rng(0))
    np.testing.assert_array_equal(out_boxes, np.concatenate([scene_boxes, boxes[3:]]))
    np.testing.assert_allclose(points, np.concatenate([rel + [30, -5, -1, 0], scene_points[2:]]), atol=1e-6)
    assert names.tolist() == ["Car", "Car"]


def test_training_items_with_gt_sampling_and_determinism(synth, tmp_path):
    root, _ = synth
    ds = KittiDetectionDataset(root, "train", seed=3)
    assert (root / "gt_database_train.npz").is_file() and ds.sampler is not None
    a, b = ds[1], KittiDetectionDataset(root, "train", seed=3)[1]
    assert a["augmentation"]["gt_sampled"] > 0
    for key in ("points", "gt_boxes"):
        np.testing.assert_array_equal(a[key], b[key])
        np.testing.assert_array_equal(a[key], ds[1][key])
    assert a["augmentation"] == b["augmentation"]
    r = DetectionConfig().point_cloud_range
    assert mask_boxes_outside_range(a["gt_boxes"], r).all() and mask_points_by_range(a["points"], r).all()
    assert np.isin(a["gt_boxes"][:, 7], [1, 2, 3]).all()
    ds.set_epoch(1)
    c = ds[1]
    assert c["augmentation"] != a["augmentation"] and c["points"].shape != a["points"].shape
    other_seed = KittiDetectionDataset(root, "train", seed=4)[1]
    assert other_seed["augmentation"] != a["augmentation"]
    # DataLoader workers get the epoch of the iterator's creation; batches as without workers
    ds.set_epoch(5)
    batches = []
    for workers in (0, 2):
        loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=workers, collate_fn=collate_batch)
        batches.append(list(loader))
    for x, y in zip(*batches):
        assert x["frame_id"] == y["frame_id"] and x["augmentation"] == y["augmentation"]
        assert torch.equal(x["points"], y["points"]) and torch.equal(x["gt_boxes"], y["gt_boxes"])


def test_collate_batch(synth):
    root, _ = synth
    ds = KittiDetectionDataset(root, ["000001", "000003"], training=False)
    items = [ds[0], ds[1]]
    empty = dict(items[1], gt_boxes=np.zeros((0, 8), np.float32), frame_id="x")
    batch = collate_batch([items[0], empty, items[1]])
    n = [it["points"].shape[0] for it in (items[0], empty, items[1])]
    assert batch["batch_size"] == 3 and batch["frame_id"] == ["000001", "x", "000003"]
    assert batch["points"].dtype == torch.float32 and batch["points"].shape == (sum(n), 5)
    np.testing.assert_array_equal(batch["points"][:, 0].numpy(), np.repeat([0, 1, 2], n))
    np.testing.assert_array_equal(batch["points"][n[0]:n[0] + n[1], 1:].numpy(), items[1]["points"])
    m = items[0]["gt_boxes"].shape[0]
    assert batch["gt_boxes"].shape == (3, m, 8) and batch["gt_boxes"].dtype == torch.float32
    np.testing.assert_array_equal(batch["gt_boxes"][0].numpy(), items[0]["gt_boxes"])
    assert (batch["gt_boxes"][1] == 0).all() and (batch["gt_boxes"][2, 2:] == 0).all()
    assert len(batch["annos"]) == 3 and isinstance(batch["calib"][2], KittiCalib)


def test_config_from_openpcdet():
    pointpillar = {"CLASS_NAMES": list(CLASSES), "DATA_CONFIG": {
        "POINT_CLOUD_RANGE": [0, -39.68, -3, 69.12, 39.68, 1], "FOV_POINTS_ONLY": True,
        "DATA_PROCESSOR": [{"NAME": "mask_points_and_boxes_outside_range", "REMOVE_OUTSIDE_BOXES": True},
                           {"NAME": "shuffle_points", "SHUFFLE_ENABLED": {"train": True, "test": False}},
                           {"NAME": "transform_points_to_voxels", "VOXEL_SIZE": [0.16, 0.16, 4]}],
        "DATA_AUGMENTOR": {"DISABLE_AUG_LIST": ["placeholder"], "AUG_CONFIG_LIST": [
            {"NAME": "gt_sampling", "USE_ROAD_PLANE": False, "DB_INFO_PATH": ["kitti_dbinfos_train.pkl"],
             "PREPARE": {"filter_by_min_points": ["Car:5", "Pedestrian:5", "Cyclist:5"], "filter_by_difficulty": [-1]},
             "SAMPLE_GROUPS": ["Car:15", "Pedestrian:15", "Cyclist:15"], "NUM_POINT_FEATURES": 4,
             "DATABASE_WITH_FAKELIDAR": False, "REMOVE_EXTRA_WIDTH": [0.0, 0.0, 0.0], "LIMIT_WHOLE_SCENE": False},
            {"NAME": "random_world_flip", "ALONG_AXIS_LIST": ["x"]},
            {"NAME": "random_world_rotation", "WORLD_ROT_ANGLE": [-0.78539816, 0.78539816]},
            {"NAME": "random_world_scaling", "WORLD_SCALE_RANGE": [0.95, 1.05]}]}}}
    cfg = DetectionConfig.from_openpcdet(pointpillar)
    ref = DetectionConfig()
    assert cfg.to_dict() == {**ref.to_dict(), "rotation_range": [-0.78539816, 0.78539816]}
    data = pointpillar["DATA_CONFIG"]
    cfg = DetectionConfig.from_openpcdet({**data, "DATA_PROCESSOR": data["DATA_PROCESSOR"][:1], "DATA_AUGMENTOR": {
        "DISABLE_AUG_LIST": ["gt_sampling"], "AUG_CONFIG_LIST": data["DATA_AUGMENTOR"]["AUG_CONFIG_LIST"][:1] + [
            {"NAME": "random_world_rotation", "WORLD_ROT_ANGLE": 0.5}]}})
    assert cfg.augmentations == ("random_world_rotation",) and cfg.rotation_range == (-0.5, 0.5)
    assert not cfg.shuffle_train and cfg.mask_outside_range
    with pytest.raises(ValueError, match="random_local_rotation"):
        DetectionConfig.from_openpcdet({"DATA_AUGMENTOR": [{"NAME": "random_local_rotation"}]})
    with pytest.raises(ValueError, match="Car:15"):
        DetectionConfig.from_openpcdet({"DATA_AUGMENTOR": [{"NAME": "gt_sampling", "SAMPLE_GROUPS": ["Car15"]}]})
    with pytest.raises(ValueError, match="point_cloud_range"):
        DetectionConfig(point_cloud_range=(0, 0, 0, 1, 1))
