"""Tests of the dataset formats, object sets and torch datasets (lidarops.data.formats/objects/datasets)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from lidarops.data import CLASSES, Frame
from lidarops.data.formats import (
    ConcatFrames,
    KittiCalib,
    KittiDataset,
    KittiLabels,
    camera_to_lidar_boxes,
    detect_format,
    forward_fov_mask,
    kitti_fov_mask,
    lidar_to_camera_boxes,
    open_frames,
    read_calib,
    read_frame,
    read_label,
    read_nuscenes_bin,
    read_velodyne,
    write_calib,
    write_kitti_frame,
    write_label,
    write_nuscenes_bin,
    write_velodyne,
)
from lidarops.data.objects import ObjectSet, canonicalize, extract_objects, split_balanced
from lidarops.data.synthetic import Simulator, SyntheticFrames


def random_calib(rng: np.random.Generator) -> KittiCalib:
    """A calibration with a few degrees of random rotation away from the ideal LiDAR->camera axes."""
    def rot(axis, angle):
        c, s = np.cos(angle), np.sin(angle)
        m = np.eye(3)
        i, j = [(1, 2), (0, 2), (0, 1)][axis]
        m[i, i] = m[j, j] = c
        m[i, j], m[j, i] = -s, s
        return m

    ideal = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    r = rot(0, rng.normal(0, 0.03)) @ rot(1, rng.normal(0, 0.03)) @ rot(2, rng.normal(0, 0.03)) @ ideal
    tr = np.concatenate([r, rng.normal(0, 0.2, (3, 1))], axis=1)
    calib = KittiCalib.default()
    return KittiCalib(calib.P.copy(), rot(1, rng.normal(0, 0.01)), tr)


@pytest.fixture(scope="module")
def city_frames():
    """Two simulated frames, materialised once (a list is a valid frame source)."""
    source = SyntheticFrames("driving_city", num_frames=2, seed=4, object_counts={"Car": 20, "Pedestrian": 8})
    return [source[i] for i in range(len(source))]


# ----------------------------------------------------------------------------- KITTI
def test_kitti_box_conversion_round_trip_exact():
    rng = np.random.default_rng(0)
    boxes = np.concatenate([rng.uniform([-50, -40, -3], [70, 40, 2], (200, 3)), rng.uniform(0.3, 12, (200, 3)),
                            rng.uniform(-np.pi, np.pi, (200, 1))], axis=1)
    for calib in (KittiCalib.default(), random_calib(rng)):
        loc, dims, ry = lidar_to_camera_boxes(boxes, calib)
        back = camera_to_lidar_boxes(loc, dims, ry, calib)
        assert np.allclose(back[:, :6], boxes[:, :6], atol=1e-5)
        assert np.allclose(np.angle(np.exp(1j * (back[:, 6] - boxes[:, 6]))), 0, atol=1e-5)


def test_kitti_box_conversion_known_values():
    calib = KittiCalib(KittiCalib.default().P, np.eye(3), np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0.0]]))
    # a car 10 m ahead, 2 m to the left, heading forward (+x)
    loc, dims, ry = lidar_to_camera_boxes(np.array([[10.0, 2.0, -0.8, 4.0, 1.6, 1.5, 0.0]]), calib)
    assert np.allclose(loc, [[-2.0, 0.8 + 0.75, 10.0]])  # camera: x right, y down (bottom centre), z forward
    assert np.allclose(dims, [[1.5, 1.6, 4.0]])  # h, w, l
    assert ry[0] == pytest.approx(-np.pi / 2)  # KITTI: -pi/2 = facing along the camera z axis


def test_kitti_files_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 20, (1000, 4)).astype(np.float32)
    write_velodyne(tmp_path / "v.bin", pts)
    assert np.array_equal(read_velodyne(tmp_path / "v.bin"), pts)
    calib = random_calib(rng)
    write_calib(tmp_path / "c.txt", calib)
    c2 = read_calib(tmp_path / "c.txt")
    assert np.allclose(c2.P, calib.P, rtol=1e-11) and np.allclose(c2.R0_rect, calib.R0_rect, rtol=1e-11)
    assert np.allclose(c2.Tr_velo_to_cam, calib.Tr_velo_to_cam, rtol=1e-11, atol=1e-14)
    labels = KittiLabels(["Car", "Pedestrian"], np.array([0.0, 0.3], np.float32), np.array([0, 2]),
                         np.array([0.1, -1.2], np.float32), np.array([[1, 2, 3, 4], [5, 6, 7, 8]], np.float32),
                         np.array([[1.5, 1.6, 3.9], [1.7, 0.6, 0.8]]), np.array([[1.0, 1.7, 20.0], [-3.0, 1.6, 8.0]]),
                         np.array([0.5, -2.0]), np.array([0.9, 0.4], np.float32))
    write_label(tmp_path / "l.txt", labels)
    back = read_label(tmp_path / "l.txt")
    assert back.names == labels.names and np.array_equal(back.occluded, labels.occluded)
    for name in ("truncated", "alpha", "bbox", "dimensions", "location", "rotation_y", "score"):
        assert np.allclose(getattr(back, name), getattr(labels, name), atol=1e-5), name
    # 15-field files (no score) read too
    (tmp_path / "l15.txt").write_text("Van 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n")
    assert read_label(tmp_path / "l15.txt").score is None


def test_kitti_frame_write_read(tmp_path, city_frames):
    frame = city_frames[0]
    write_kitti_frame(tmp_path, frame, frame_id=7, camera_fov_only=False, min_points=0)
    ds = KittiDataset(tmp_path)
    assert len(ds) == 1 and ds.ids == ["000007"]
    back = ds[0]
    assert np.array_equal(back.points, frame.points)
    assert np.allclose(back.boxes[:, :6], frame.boxes[:, :6], atol=1e-5)
    assert np.allclose(np.angle(np.exp(1j * (back.boxes[:, 6] - frame.boxes[:, 6]))), 0, atol=1e-5)
    assert np.array_equal(back.labels, frame.labels)
    assert np.array_equal(back.num_points_in_box, frame.num_points_in_box)
    # the same through the other entry points
    assert detect_format(tmp_path) == "kitti"
    assert np.array_equal(read_frame(tmp_path / "training" / "velodyne" / "000007.bin").boxes, back.boxes)


def test_kitti_labels_only_in_camera_view(tmp_path, city_frames):
    frame = city_frames[1]
    write_kitti_frame(tmp_path, frame, frame_id=0)
    back = KittiDataset(tmp_path / "training")[0]
    calib = back.meta["calib"]
    uv, depth = calib.lidar_to_image(back.boxes[:, :3].astype(np.float64))
    assert np.all(depth > 0) and np.all((uv[:, 0] >= 0) & (uv[:, 0] < 1242))
    assert np.all(back.num_points_in_box >= 1)
    assert 0 < back.num_boxes < frame.num_boxes
    kitti = back.meta["kitti"]
    assert np.all(kitti.bbox[:, 2] > kitti.bbox[:, 0]) and set(np.unique(kitti.occluded)) <= {0, 1, 2}


def test_kitti_fov_masks():
    calib = KittiCalib.default()
    pts = np.array([[10.0, 0, 0], [-10.0, 0, 0], [10.0, 20.0, 0], [30.0, 5.0, -1.0], [5.0, -4.0, 0], [0.5, 0, 0]])
    assert kitti_fov_mask(pts, calib).tolist() == [True, False, False, True, True, False]
    assert forward_fov_mask(pts, 90.0).tolist() == [True, False, False, True, True, True]


def test_kitti_unknown_types_and_dontcare(tmp_path):
    split = tmp_path / "training"
    write_velodyne(split / "velodyne" / "000000.bin", np.zeros((5, 4), np.float32))
    write_calib(split / "calib" / "000000.txt", KittiCalib.default())
    (split / "label_2").mkdir()
    (split / "label_2" / "000000.txt").write_text(
        "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"
        "Van 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 3.65 1.71 46.70 -1.59\n"
        "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n")
    assert KittiDataset(tmp_path)[0].labels.tolist() == [CLASSES.index("Car")]
    assert KittiDataset(tmp_path, unknown="keep")[0].labels.tolist() == [CLASSES.index("Car"), -1]


def test_kitti_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.bin"):
        read_velodyne(tmp_path / "nope.bin")
    (tmp_path / "bad.bin").write_bytes(b"\x00" * 10)
    with pytest.raises(ValueError, match=r"bad\.bin.*16 bytes"):
        read_velodyne(tmp_path / "bad.bin")
    (tmp_path / "bad.txt").write_text("Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70\n")
    with pytest.raises(ValueError, match=r"bad\.txt:1: expected 15 or 16 fields, got 14"):
        read_label(tmp_path / "bad.txt")
    (tmp_path / "nan.txt").write_text("Car 0.00 0 x 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1\n")
    with pytest.raises(ValueError, match=r"nan\.txt:1: non-numeric"):
        read_label(tmp_path / "nan.txt")
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(ValueError, match=r"calib\.txt.*P2"):
        read_calib(tmp_path / "calib.txt")
    (tmp_path / "calib2.txt").write_text("P2: 1 2 3\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 1 2 3 4 5 6 7 8 9 10 11 12\n")
    with pytest.raises(ValueError, match="P2 has 3 values"):
        read_calib(tmp_path / "calib2.txt")
    with pytest.raises(FileNotFoundError, match="velodyne"):
        KittiDataset(tmp_path)
    with pytest.raises(FileNotFoundError):
        KittiDataset(tmp_path / "missing")


# ----------------------------------------------------------------------------- PandaSet
@pytest.fixture(scope="module")
def drone_sequence(tmp_path_factory):
    pytest.importorskip("pandas")
    from lidarops.data.formats.pandaset import write_pandaset_sequence

    sim = Simulator("drone_bridge", seed=3, object_counts={"Drone": 2})
    frames = [sim.sweep(i) for i in range(3)]
    world = [sim.points_to_world(f.points, f.t) for f in frames]
    seq = tmp_path_factory.mktemp("pandaset") / "017"
    write_pandaset_sequence(seq, frames, world_xyz=world)
    return seq, frames, world


def test_pandaset_round_trip(drone_sequence):
    from lidarops.data.formats.pandaset import PandaSetSequence

    seq, frames, world = drone_sequence
    ds = PandaSetSequence(seq)
    assert len(ds) == 3
    for i, frame in enumerate(frames):
        back = ds[i]
        assert np.array_equal(back.t, frame.t)
        assert np.allclose(back.sensor_pose, frame.sensor_pose, atol=1e-9)
        assert back.timestamp == frame.timestamp
        # world coordinates are written exactly (each point with its own pose)
        w = PandaSetSequence(seq, coordinates="world")[i]
        assert np.allclose(w.points[:, :3], world[i], atol=1e-4)
        # in the LiDAR frame: the exact world points seen from the frame's reference pose
        pose = frame.sensor_pose
        expected = (world[i] - pose[:3, 3]) @ pose[:3, :3]
        assert np.allclose(back.points[:, :3], expected, atol=1e-4)
        assert np.allclose(back.points[:, 3], frame.points[:, 3], atol=1e-6)
        assert np.array_equal(back.labels, frame.labels) and np.array_equal(back.object_ids, frame.object_ids)
        assert np.allclose(back.boxes[:, :6], frame.boxes[:, :6], atol=1e-4)
        assert np.allclose(np.angle(np.exp(1j * (back.boxes[:, 6] - frame.boxes[:, 6]))), 0, atol=1e-5)


def test_pandaset_follows_devkit_conventions(drone_sequence):
    import pandas as pd

    from lidarops.data.formats.pandaset import PandaSetSequence, world_to_ego

    seq, frames, _ = drone_sequence
    df = pd.read_pickle(seq / "lidar" / "01.pkl.gz")
    assert list(df.columns) == ["x", "y", "z", "i", "t", "d"]
    assert df["i"].max() <= 255 and df["i"].max() > 1.0
    poses = json.loads((seq / "lidar" / "poses.json").read_text())
    ego = world_to_ego(df[["x", "y", "z"]].to_numpy(), poses[1])  # devkit: x right, y forward
    ours = PandaSetSequence(seq)[1].points[:, :3]
    assert np.allclose(ours[:, 0], ego[:, 1], atol=1e-4) and np.allclose(ours[:, 1], -ego[:, 0], atol=1e-4)
    cub = pd.read_pickle(seq / "annotations" / "cuboids" / "01.pkl.gz")
    # dimensions.y is the length (our dx)
    assert np.allclose(cub["dimensions.y"].to_numpy(), frames[1].boxes[:, 3], atol=1e-6)
    assert set(cub["label"]) == {"Drone"}


def test_pandaset_errors(tmp_path, drone_sequence):
    pytest.importorskip("pandas")
    from lidarops.data.formats.pandaset import PandaSetSequence

    with pytest.raises(FileNotFoundError):
        PandaSetSequence(tmp_path / "nothing")
    (tmp_path / "seq" / "lidar").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="no lidar"):
        PandaSetSequence(tmp_path / "seq")
    (tmp_path / "seq" / "lidar" / "00.pkl.gz").write_bytes(b"not gzip at all")
    (tmp_path / "seq" / "lidar" / "poses.json").write_text(json.dumps([{"position": {"x": 0, "y": 0, "z": 0},
                                                                       "heading": {"w": 1, "x": 0, "y": 0, "z": 0}}]))
    with pytest.raises(ValueError, match=r"00\.pkl\.gz.*gzip"):
        PandaSetSequence(tmp_path / "seq")[0]
    import pandas as pd

    pd.DataFrame({"x": [1.0], "y": [2.0]}).to_pickle(tmp_path / "seq" / "lidar" / "00.pkl.gz", compression="gzip")
    with pytest.raises(ValueError, match=r"missing column"):
        PandaSetSequence(tmp_path / "seq")[0]
    (tmp_path / "seq" / "lidar" / "poses.json").write_text("{broken")
    with pytest.raises(ValueError, match=r"poses\.json.*JSON"):
        PandaSetSequence(tmp_path / "seq")


# ----------------------------------------------------------------------------- nuScenes
def test_nuscenes_read_write(tmp_path):
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.normal(0, 10, (500, 3)), rng.uniform(0, 255, (500, 1))], axis=1).astype(np.float32)
    ring = rng.integers(0, 32, 500)
    path = tmp_path / "samples" / "LIDAR_TOP" / "n008-2018-08-01-15-16-36-0400__LIDAR_TOP__1533151603547590.pcd.bin"
    write_nuscenes_bin(path, pts, ring)
    f = read_nuscenes_bin(path)
    assert np.array_equal(f.points, pts) and np.array_equal(f.ring, ring)
    assert f.timestamp == pytest.approx(1533151603.547590)
    fx = read_nuscenes_bin(path, x_forward=True, normalize_intensity=True)
    assert np.allclose(fx.points[:, 0], pts[:, 1]) and np.allclose(fx.points[:, 1], -pts[:, 0])
    assert fx.points[:, 3].max() <= 1.0
    assert detect_format(path) == "nuscenes" and detect_format(path.parent) == "nuscenes_dir"
    assert len(open_frames(path.parent)) == 1
    (tmp_path / "bad.pcd.bin").write_bytes(b"\x00" * 24)
    with pytest.raises(ValueError, match=r"bad\.pcd\.bin.*20 bytes"):
        read_nuscenes_bin(tmp_path / "bad.pcd.bin")
    with pytest.raises(FileNotFoundError):
        read_nuscenes_bin(tmp_path / "missing.pcd.bin")


# ----------------------------------------------------------------------------- ModelNet40
def test_modelnet_h5(tmp_path):
    h5py = pytest.importorskip("h5py")
    from lidarops.data.formats import ModelNet40, read_modelnet_h5

    rng = np.random.default_rng(3)
    data = rng.normal(size=(6, 128, 3)).astype(np.float32)
    label = np.array([[0], [7], [39], [7], [1], [2]], np.uint8)
    for name, sl in (("ply_data_train0.h5", slice(0, 4)), ("ply_data_test0.h5", slice(4, 6))):
        with h5py.File(tmp_path / name, "w") as f:
            f.create_dataset("data", data=data[sl])
            f.create_dataset("label", data=label[sl])
    pts, lab = read_modelnet_h5(tmp_path / "ply_data_train0.h5")
    assert np.array_equal(pts, data[:4]) and lab.tolist() == [0, 7, 39, 7]
    mn = ModelNet40(tmp_path, split="test")
    assert len(mn) == 2 and mn[1][1] == 2 and mn.class_names[7] == "car"
    (tmp_path / "shape_names.txt").write_text("\n".join(f"c{i}" for i in range(40)))
    assert ModelNet40(tmp_path).class_names[39] == "c39"
    with h5py.File(tmp_path / "nolabel.h5", "w") as f:
        f.create_dataset("data", data=data)
    with pytest.raises(ValueError, match=r"nolabel\.h5.*label"):
        read_modelnet_h5(tmp_path / "nolabel.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(ValueError, match=r"text\.h5.*HDF5"):
        read_modelnet_h5(tmp_path / "text.h5")
    with pytest.raises(FileNotFoundError):
        ModelNet40(tmp_path / "none")


# ----------------------------------------------------------------------------- detection
def test_detect_format_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        detect_format(tmp_path / "missing")
    (tmp_path / "x.xyz").write_text("1 2 3")
    with pytest.raises(ValueError, match="unrecognised"):
        detect_format(tmp_path / "x.xyz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="not a KITTI"):
        open_frames(tmp_path / "empty")
    with pytest.raises(IndexError):
        read_frame("synthetic:drone_lock", 5, num_frames=2)


def test_concat_frames():
    a = SyntheticFrames("drone_lock", num_frames=2, seed=1)
    b = SyntheticFrames("drone_lock", num_frames=1, seed=2)
    c = ConcatFrames([a, b])
    assert len(c) == 3 and np.array_equal(c[2].points, b[0].points) and np.array_equal(c[1].points, a[1].points)


# ----------------------------------------------------------------------------- objects
def test_extract_objects_and_balanced_split(city_frames):
    frames = [city_frames[i] for i in range(len(city_frames))]
    samples = extract_objects(frames, min_points=5, canonical=True)
    expected = sum(int((f.num_points_in_box >= 5).sum()) for f in frames)
    assert len(samples) == expected and expected > 10
    for s in samples:
        assert s.num_points >= 5
        half = s.box[3:6] / 2 + 1e-4
        assert np.all(np.abs(s.points[:, :3]) <= half)  # canonical: inside the box centred at 0
    raw = extract_objects(frames[:1], min_points=5, canonical=False)
    assert np.allclose(canonicalize(raw[0].points, raw[0].box), samples[0].points, atol=1e-5)
    train, test = split_balanced(samples, test_fraction=0.3, seed=0)
    assert len(np.intersect1d(train, test)) == 0 and len(train) + len(test) == len(samples)
    assert 0.15 < len(test) / len(samples) < 0.45
    labels = np.array([s.label for s in samples])
    for lab in np.unique(labels):
        if (labels == lab).sum() >= 5:
            assert (labels[test] == lab).sum() >= 1 and (labels[train] == lab).sum() >= 1


def test_object_set_save_load(tmp_path, city_frames):
    objset = ObjectSet.from_frames([city_frames[0]], min_points=3)
    path = objset.save(tmp_path / "objects.npz")
    back = ObjectSet.load(path)
    assert len(back) == len(objset) and back.class_names == objset.class_names
    assert np.array_equal(back.train_index, objset.train_index)
    for a, b in zip(objset.samples, back.samples):
        assert np.array_equal(a.points, b.points) and a.label == b.label
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not an object set"):
        ObjectSet.load(tmp_path / "other.npz")


# ----------------------------------------------------------------------------- torch datasets
def test_detection_dataset_same_interface_synthetic_and_kitti(tmp_path, city_frames):
    """Simulator and KITTI folder give the same items, in OpenPCDet's batch dialect (1-based class ids)."""
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    from lidarops.data import CLASSES
    from lidarops.data.datasets import DetectionDataset, collate_batch

    for i in range(2):
        write_kitti_frame(tmp_path, city_frames[i], frame_id=i, camera_fov_only=False, min_points=0)
    synthetic = DetectionDataset(city_frames)
    disk = DetectionDataset(tmp_path)
    assert len(synthetic) == len(disk) == 2
    a, b = synthetic[1], disk[1]
    assert set(b) <= set(a) and "t" in a and "t" not in b
    assert torch.equal(a["points"], b["points"]) and torch.equal(a["gt_boxes"][:, 7], b["gt_boxes"][:, 7])
    assert torch.allclose(a["gt_boxes"][:, :6], b["gt_boxes"][:, :6], atol=1e-5)
    # class ids are 1-based into the source's classes: the frame's 0-based labels + 1, names preserved
    f = city_frames[1]
    assert a["gt_boxes"][:, 7].long().tolist() == (f.labels + 1).tolist()
    assert [CLASSES[int(k) - 1] for k in a["gt_boxes"][:, 7]] == [f.class_names[k] for k in f.labels]
    batch = next(iter(DataLoader(disk, batch_size=2, collate_fn=collate_batch)))
    assert batch["points"].shape == (sum(len(city_frames[i].points) for i in range(2)), 5)
    assert batch["points"][:, 0].unique().tolist() == [0.0, 1.0] and batch["batch_size"] == 2
    assert batch["gt_boxes"].shape[0] == 2 and batch["gt_boxes"].shape[2] == 8
    real = batch["gt_boxes"][..., 7] > 0  # padding rows have class id 0
    assert int(real.sum()) == sum(len(disk[i]["gt_boxes"]) for i in range(2))
    assert batch["frame_id"] == [0, 1]
    filtered = DetectionDataset("synthetic:drone_lock", min_points=1, num_frames=1, seed=3)[0]
    assert torch.all(filtered["num_points_in_box"] >= 1)
    # a model's class list: other classes are left out, ids follow the given order
    cars = DetectionDataset(city_frames, class_names=("Pedestrian", "Car"))[1]
    expect = [("Pedestrian", "Car").index(f.class_names[k]) + 1 for k in f.labels if f.class_names[k] in ("Pedestrian", "Car")]
    assert cars["gt_boxes"][:, 7].long().tolist() == expect


def test_collate_detection_keeps_the_old_format_with_a_warning(city_frames):
    """lidarops 0.1's collate (batch_index, boxes, 0-based labels padded with -1) for one release."""
    torch = pytest.importorskip("torch")
    from lidarops.data.datasets import DetectionDataset, collate_detection

    items = [DetectionDataset(city_frames)[i] for i in range(2)]
    with pytest.warns(DeprecationWarning, match="collate_batch"):
        old = collate_detection(items)
    assert old["points"].shape[1] == 4 and old["batch_index"].tolist().count(1) == len(city_frames[1].points)
    n0 = len(city_frames[0].labels)
    assert old["labels"][0, :n0].tolist() == city_frames[0].labels.tolist()
    assert (old["labels"][0, n0:] == -1).all() and old["num_boxes"].tolist() == [n0, len(city_frames[1].labels)]
    assert torch.equal(old["boxes"][1, :len(city_frames[1].labels)], torch.from_numpy(city_frames[1].boxes))


def test_object_dataset_from_frames_and_modelnet(tmp_path, city_frames):
    torch = pytest.importorskip("torch")
    h5py = pytest.importorskip("h5py")
    from lidarops.data.datasets import ObjectDataset, collate_objects

    ds = ObjectDataset(city_frames, min_points=5, num_points=64, split="train")
    objset = ObjectSet.from_frames(city_frames, min_points=5)
    test = ObjectDataset(objset, num_points=64, split="test")
    assert len(ds) > 0 and len(test) > 0 and len(ds) + len(test) == len(objset)
    pts, label = ds[0]
    assert pts.shape == (64, 4) and pts.dtype == torch.float32 and 0 <= label < len(CLASSES)
    assert torch.equal(ObjectDataset(objset, num_points=64, split="train")[0][0], pts)
    batch = collate_objects([ObjectDataset(objset)[i] for i in range(3)])
    assert batch["labels"].shape == (3,)
    with h5py.File(tmp_path / "ply_data_train0.h5", "w") as f:
        f.create_dataset("data", data=np.zeros((3, 32, 3), np.float32))
        f.create_dataset("label", data=np.array([[4], [5], [6]], np.uint8))
    mn = ObjectDataset(tmp_path / "ply_data_train0.h5")
    assert len(mn) == 3 and mn[2][1] == 6 and mn[0][0].shape == (32, 3)


def test_stream_dataset_simulator_and_pandaset(drone_sequence):
    pytest.importorskip("torch")
    from lidarops.data.datasets import StreamDataset

    sim = Simulator("drone_bridge", seed=3, object_counts={"Drone": 2})
    ds = StreamDataset(sim, slice_duration=0.01)
    assert len(ds) == 10
    pts = np.concatenate([ds[i]["points"].numpy() for i in range(len(ds))])
    assert np.array_equal(pts, sim.sweep(0).points)
    seq, frames, _ = drone_sequence
    disk = StreamDataset(seq, slice_duration=0.01)
    assert len(disk) == 30
    t = np.concatenate([disk[i]["t"].numpy() for i in range(len(disk))])
    assert np.array_equal(t, np.concatenate([f.t for f in frames]))
    for i in (0, 15, 29):
        item = disk[i]
        assert np.all((item["t"].numpy() >= item["t0"]) & (item["t"].numpy() < item["t1"]))
    with pytest.raises(ValueError, match="timestamps"):
        StreamDataset(_NoTime())


class _NoTime:
    def __len__(self):
        return 1

    def __getitem__(self, i):
        return Frame(points=np.zeros((3, 4), np.float32))
