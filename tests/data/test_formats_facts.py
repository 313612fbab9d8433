"""The dataset readers and writers against facts that do not come from lidarops.

tests/data/test_formats.py checks readers against lidarops' own writers, so a mistake made the same
way on both sides passes it: KITTI dimensions written *and* read as ``l w h``, or a PandaSet yaw
written 90 degrees off with the reader compensating, both passed the whole suite. Here every
expected value comes from the formats' own documentation, written out by hand:

- KITTI (object devkit readme): a label line is ``type truncated occluded alpha left top right
  bottom h w l x y z rotation_y [score]``; ``(x, y, z)`` is the bottom centre of the box in the
  rectified camera frame (x right, y down, z forward); the devkit's ``computeBox3D`` puts the length
  ``l`` along ``(cos ry, 0, -sin ry)`` and the height ``h`` upwards (-y) from the location. The line
  used is one of KITTI's training labels. Velodyne scans are little-endian float32 ``x, y, z, r``
  records. The LiDAR box is the conversion of common tool chains (OpenPCDet): centre = bottom centre
  mapped to the LiDAR frame and lifted by ``h / 2``, ``dx, dy, dz = l, w, h``,
  ``yaw = -rotation_y - pi / 2``.
- PandaSet (devkit, ``pandaset.annotations.Cuboids.data``): ``yaw`` is the rotation about the world z
  axis, 0 pointing the length side along world ``(0, 1, 0)`` and pi/2 along ``(-1, 0, 0)``;
  ``position.x/y/z`` is the centre in world coordinates; ``dimensions.x`` is the width (left to
  right), ``dimensions.y`` the length (front to back), ``dimensions.z`` the height. Poses are
  world <- LiDAR, position plus a ``(w, x, y, z)`` quaternion; the devkit's ``lidar_points_to_ego``
  applies the inverse pose, and its LiDAR frame has x right, y forward, z up (OpenPCDet's
  ``pandaset_dataset.py`` turns it into x forward, y left by ``(y, -x, z)``).
"""
from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from lidarops.data import Frame
from lidarops.data.formats import (
    KittiCalib,
    KittiDataset,
    camera_to_lidar_boxes,
    lidar_to_camera_boxes,
    read_kitti_frame,
    read_label,
    read_velodyne,
    write_kitti_frame,
    write_label,
    write_velodyne,
)

# one line of KITTI's training labels (training/label_2/000001.txt holds lines of this form)
KITTI_LINE = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"
H, W, L = 1.65, 1.67, 3.64
LOCATION = np.array([-0.65, 1.71, 46.70])
RY = -1.59

# KITTI's calibration of the 2011_09_26 drives, as KITTI's calib/*.txt files write it
KITTI_CALIB_TEXT = """\
P0: 7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
P1: 7.215377e+02 0.000000e+00 6.095593e+02 -3.875744e+02 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
P2: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
P3: 7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 1.728540e+02 2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03
R0_rect: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
Tr_velo_to_cam: 7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 7.280733e-04 -9.998902e-01 -7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01
Tr_imu_to_velo: 9.999976e-01 7.553071e-04 -2.035826e-03 -8.086759e-01 -7.854027e-04 9.998898e-01 -1.482298e-02 3.195559e-01 2.024406e-03 1.482454e-02 9.998881e-01 -7.997231e-01
"""
R0_RECT = np.array([[9.999239e-01, 9.837760e-03, -7.445048e-03], [-9.869795e-03, 9.999421e-01, -4.278459e-03],
                    [7.402527e-03, 4.351614e-03, 9.999631e-01]])
TR_VELO_TO_CAM = np.array([[7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
                           [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
                           [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01]])


def _rect_to_velo(xyz: np.ndarray) -> np.ndarray:
    """Solve ``R0_rect @ (Tr[:, :3] @ p + Tr[:, 3]) = xyz`` for p (no matrix inverse shared with lidarops)."""
    cam = np.linalg.solve(R0_RECT, np.asarray(xyz, dtype=np.float64).T)
    return np.linalg.solve(TR_VELO_TO_CAM[:, :3], cam - TR_VELO_TO_CAM[:, 3:]).T


def _velo_to_rect(p: np.ndarray) -> np.ndarray:
    return (R0_RECT @ (TR_VELO_TO_CAM[:, :3] @ np.asarray(p, dtype=np.float64).T + TR_VELO_TO_CAM[:, 3:])).T


def _devkit_corners(location, h, w, l, ry) -> np.ndarray:
    """KITTI devkit computeBox3D: (8, 3) corners in the rectified camera frame."""
    R = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    x = [l / 2, l / 2, -l / 2, -l / 2, l / 2, l / 2, -l / 2, -l / 2]
    y = [0, 0, 0, 0, -h, -h, -h, -h]
    z = [w / 2, -w / 2, -w / 2, w / 2, w / 2, -w / 2, -w / 2, w / 2]
    return (R @ np.array([x, y, z])).T + np.asarray(location)


def _lidar_box_corners(box) -> np.ndarray:
    """(8, 3) corners of a LiDAR box x, y, z, dx, dy, dz, yaw (dx along the heading), by hand."""
    x, y, z, dx, dy, dz, yaw = (float(v) for v in box)
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for sx, sy, sz in [(a, b, e) for a in (1, -1) for b in (1, -1) for e in (1, -1)]:
        lx, ly = sx * dx / 2, sy * dy / 2
        out.append((x + c * lx - s * ly, y + s * lx + c * ly, z + sz * dz / 2))
    return np.array(out)


def _same_corner_sets(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    """Every corner of a within atol of some corner of b and vice versa."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return bool((d.min(1) <= atol).all() and (d.min(0) <= atol).all())


def _angle_diff(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2 * math.pi))


def _write_kitti_by_hand(split_dir, frame_id: str, points: np.ndarray, label_text: str) -> None:
    (split_dir / "velodyne").mkdir(parents=True)
    (split_dir / "label_2").mkdir()
    (split_dir / "calib").mkdir()
    (split_dir / "velodyne" / f"{frame_id}.bin").write_bytes(
        b"".join(struct.pack("<4f", *row) for row in points))
    (split_dir / "label_2" / f"{frame_id}.txt").write_text(label_text)
    (split_dir / "calib" / f"{frame_id}.txt").write_text(KITTI_CALIB_TEXT)


# ----------------------------------------------------------------------------- KITTI
def test_kitti_label_line_read_field_by_field(tmp_path):
    (tmp_path / "000001.txt").write_text(KITTI_LINE + "\n")
    labels = read_label(tmp_path / "000001.txt")
    assert labels.names == ["Car"] and labels.score is None
    assert labels.truncated[0] == pytest.approx(0.0)
    assert labels.occluded[0] == 0
    assert labels.alpha[0] == pytest.approx(-1.58)
    np.testing.assert_allclose(labels.bbox[0], [587.01, 173.33, 614.12, 200.12], rtol=1e-6)
    # the readme: dimensions are height, width, length, in that order on the line
    np.testing.assert_allclose(labels.dimensions[0], [H, W, L], rtol=0, atol=1e-12)
    np.testing.assert_allclose(labels.location[0], LOCATION, rtol=0, atol=1e-12)
    assert labels.rotation_y[0] == pytest.approx(RY, abs=1e-12)


def test_kitti_calib_file_read_as_written_by_kitti(tmp_path):
    (tmp_path / "000001.txt").write_text(KITTI_CALIB_TEXT)
    from lidarops.data.formats import read_calib

    calib = read_calib(tmp_path / "000001.txt")
    np.testing.assert_allclose(calib.R0_rect, R0_RECT, rtol=0, atol=1e-15)
    np.testing.assert_allclose(calib.Tr_velo_to_cam, TR_VELO_TO_CAM, rtol=0, atol=1e-15)
    assert calib.P2[0, 3] == pytest.approx(44.85728) and calib.P[3][0, 3] == pytest.approx(-339.5242)
    # lidarops' default calibration is this drive's
    default = KittiCalib.default()
    np.testing.assert_allclose(default.R0_rect, R0_RECT, atol=1e-9)
    np.testing.assert_allclose(default.Tr_velo_to_cam, TR_VELO_TO_CAM, atol=1e-9)


def _expected_lidar_box() -> np.ndarray:
    bottom = _rect_to_velo(LOCATION[None])[0]
    # by hand: the LiDAR frame is the camera's axes turned (x = z_cam, y = -x_cam, z = -y_cam), 0.27 m
    # behind and 8 cm above it, pitched by Tr[2, 2] = 0.0148 rad and R0_rect[1, 2] = -0.0043 rad, which
    # at 46.7 m ahead lifts the bottom centre by (0.0148 - 0.0044) * 46.7 = 0.49 m
    x_cam, y_cam, z_cam = LOCATION
    assert abs(bottom[0] - (z_cam + 0.27)) < 0.05 and abs(bottom[1] - -x_cam) < 0.05
    assert abs(bottom[2] - (-(y_cam + 0.0044 * z_cam + 0.076) + 0.0148 * (z_cam + 0.27))) < 0.02
    yaw = -RY - math.pi / 2
    return np.array([bottom[0], bottom[1], bottom[2] + H / 2, L, W, H, yaw])


def test_kitti_label_line_converts_to_the_lidar_box_by_hand():
    expected = _expected_lidar_box()
    box = camera_to_lidar_boxes(LOCATION[None], np.array([[H, W, L]]), np.array([RY]), KittiCalib.default())[0]
    np.testing.assert_allclose(box[:3], expected[:3], rtol=0, atol=1e-6)
    assert (box[3], box[4], box[5]) == pytest.approx((L, W, H), abs=1e-12)  # dx = l along the heading, dz = h
    assert _angle_diff(box[6], expected[6]) < 1e-9
    # the same box as the devkit draws it: its corners, mapped to the camera frame, are computeBox3D's
    # (within the 4 cm that the calibration's 1-degree tilt moves the corners of a box kept upright in the
    # LiDAR frame; swapping l and h, or turning the box by 90 degrees, moves them by a metre)
    cam_corners = _velo_to_rect(_lidar_box_corners(box))
    assert _same_corner_sets(cam_corners, _devkit_corners(LOCATION, H, W, L, RY), atol=0.05)
    # the heading: the devkit's length axis (cos ry, 0, -sin ry) seen in the LiDAR frame
    axis = _rect_to_velo(np.array([[math.cos(RY), 0.0, -math.sin(RY)]])) - _rect_to_velo(np.zeros((1, 3)))
    assert _angle_diff(box[6], math.atan2(axis[0, 1], axis[0, 0])) < 0.02


def test_kitti_frame_from_files_written_by_hand(tmp_path):
    points = np.array([[1.5, -2.25, 0.125, 0.5], [46.9, 0.6, -0.5, 0.0], [-0.0, 1e-30, 3.4e38, 1.0]], np.float32)
    split = tmp_path / "training"
    _write_kitti_by_hand(split, "000001", points, KITTI_LINE + "\n")
    for frame in (KittiDataset(tmp_path)[0], read_kitti_frame(split / "velodyne" / "000001.bin")):
        assert np.array_equal(frame.points, points) and frame.points.dtype == np.float32
        assert frame.boxes.shape == (1, 7)
        expected = _expected_lidar_box()
        np.testing.assert_allclose(frame.boxes[0, :6], expected[:6], rtol=0, atol=1e-5)
        assert _angle_diff(float(frame.boxes[0, 6]), expected[6]) < 1e-6
        # the box holds the point 46.9, 0.6, -0.5 (its centre region)
        assert frame.num_points_in_box.tolist() == [1]


def test_kitti_velodyne_bytes_by_hand(tmp_path):
    records = [(1.0, -2.0, 0.5, 0.25), (-0.0, 1e-30, 3.4e38, 1.0), (123.456, -78.9, -1.73, 0.0)]
    raw = b"".join(struct.pack("<ffff", *r) for r in records)
    (tmp_path / "scan.bin").write_bytes(raw)
    got = read_velodyne(tmp_path / "scan.bin")
    assert got.shape == (3, 4) and got.dtype == np.float32
    for row, rec in zip(got.tolist(), records):
        assert row == [struct.unpack("<f", struct.pack("<f", v))[0] for v in rec]
    # and the writer writes exactly these bytes
    write_velodyne(tmp_path / "back.bin", np.array(records, np.float32))
    assert (tmp_path / "back.bin").read_bytes() == raw
    (tmp_path / "empty.bin").write_bytes(b"")
    assert read_velodyne(tmp_path / "empty.bin").shape == (0, 4)


def test_kitti_writer_puts_h_w_l_and_the_bottom_centre_on_the_line(tmp_path):
    box = _expected_lidar_box()
    loc, dims, ry = lidar_to_camera_boxes(box[None], KittiCalib.default())
    np.testing.assert_allclose(dims[0], [H, W, L], atol=1e-12)
    np.testing.assert_allclose(loc[0], LOCATION, atol=1e-6)
    assert _angle_diff(float(ry[0]), RY) < 1e-9
    # a whole frame written by lidarops, its label line read by hand (split on spaces, the readme's order)
    frame = Frame(points=np.array([[box[0], box[1], box[2], 0.5]], np.float32), boxes=box[None].astype(np.float32),
                  labels=np.array([0]))
    write_kitti_frame(tmp_path, frame, frame_id=1, camera_fov_only=False, min_points=0)
    fields = (tmp_path / "training" / "label_2" / "000001.txt").read_text().split()
    assert len(fields) == 15 and fields[0] == "Car"
    h, w, l = (float(v) for v in fields[8:11])
    assert (h, w, l) == pytest.approx((H, W, L), abs=1e-5)
    np.testing.assert_allclose([float(v) for v in fields[11:14]], LOCATION, atol=1e-4)
    assert _angle_diff(float(fields[14]), RY) < 1e-5
    # the bbox fields lie in the image, left < right, top < bottom (P2 projection of the box)
    left, top, right, bottom = (float(v) for v in fields[4:8])
    assert 0 <= left < right <= 1242 and 0 <= top < bottom <= 375
    # and the scan's bytes are float32 x, y, z, r records
    raw = (tmp_path / "training" / "velodyne" / "000001.bin").read_bytes()
    assert struct.unpack("<4f", raw) == tuple(np.float32(v) for v in frame.points[0])
    # write_label itself: the dimensions go out in the readme's order too
    labels = _read_label_text(tmp_path, KITTI_LINE)
    write_label(tmp_path / "again.txt", labels, decimals=2)
    assert (tmp_path / "again.txt").read_text().split()[8:11] == ["1.65", "1.67", "3.64"]


def _read_label_text(tmp_path, text: str):
    (tmp_path / "in.txt").write_text(text + "\n")
    return read_label(tmp_path / "in.txt")


# ----------------------------------------------------------------------------- PandaSet
def _rot_z(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _quat_wxyz_to_matrix(q) -> np.ndarray:
    """The rotation of a unit quaternion (w, x, y, z): scipy's, not lidarops'."""
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w]).as_matrix()


# a pose with a yaw and a small roll, so that the world and LiDAR z axes differ a little
POSE_YAW, POSE_ROLL = 0.7, 0.02
POSE_POSITION = np.array([5.0, 15.0, 2.0])


def _pose_quaternion() -> tuple[float, float, float, float]:
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    x, y, z, w = Rotation.from_euler("zx", [POSE_YAW, POSE_ROLL]).as_quat()
    return float(w), float(x), float(y), float(z)


# two cuboids, world coordinates, devkit columns: yaw, centre, width (x), length (y), height (z)
CUBOIDS = [
    {"label": "Car", "yaw": 0.3, "position": (10.0, 20.0, 1.0), "dims": (2.0, 4.5, 1.6)},
    {"label": "Pedestrian", "yaw": -2.5, "position": (3.0, 25.0, 0.8), "dims": (0.6, 0.9, 1.8)},
]


def _write_pandaset_by_hand(seq_dir) -> None:
    pd = pytest.importorskip("pandas")
    (seq_dir / "lidar").mkdir(parents=True)
    (seq_dir / "annotations" / "cuboids").mkdir(parents=True)
    w, x, y, z = _pose_quaternion()
    pose = {"position": dict(zip("xyz", POSE_POSITION.tolist())), "heading": {"w": w, "x": x, "y": y, "z": z}}
    (seq_dir / "lidar" / "poses.json").write_text(json.dumps([pose]))
    (seq_dir / "lidar" / "timestamps.json").write_text(json.dumps([1557540000.5]))
    R = _quat_wxyz_to_matrix((w, x, y, z))
    # points given in the devkit's LiDAR frame (x right, y forward), stored in world coordinates
    ego = np.array([[0.0, 10.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    world = ego @ R.T + POSE_POSITION
    pd.DataFrame({"x": world[:, 0], "y": world[:, 1], "z": world[:, 2], "i": [255.0, 0.0, 51.0],
                  "t": [1557540000.45, 1557540000.5, 1557540000.55], "d": [0, 0, 1]}).to_pickle(
        seq_dir / "lidar" / "00.pkl.gz", compression="gzip")
    pd.DataFrame({
        "uuid": ["7", "8"], "label": [c["label"] for c in CUBOIDS], "yaw": [c["yaw"] for c in CUBOIDS],
        "stationary": [False, True], "camera_used": [-1, -1],
        "position.x": [c["position"][0] for c in CUBOIDS], "position.y": [c["position"][1] for c in CUBOIDS],
        "position.z": [c["position"][2] for c in CUBOIDS],
        "dimensions.x": [c["dims"][0] for c in CUBOIDS], "dimensions.y": [c["dims"][1] for c in CUBOIDS],
        "dimensions.z": [c["dims"][2] for c in CUBOIDS],
        "cuboids.sibling_id": ["-", "-"], "cuboids.sensor_id": [-1, -1],
    }).to_pickle(seq_dir / "annotations" / "cuboids" / "00.pkl.gz", compression="gzip")


def _devkit_world_corners(c: dict) -> np.ndarray:
    """(8, 3) world corners of a devkit cuboid: width (dimensions.x) and length (dimensions.y) turned by
    yaw about world z, so that at yaw 0 the length lies along world y."""
    width, length, height = c["dims"]
    R = _rot_z(c["yaw"])
    local = np.array([[sx * width / 2, sy * length / 2, sz * height / 2]
                      for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
    return local @ R.T + np.asarray(c["position"])


def _world_to_ours(xyz: np.ndarray) -> np.ndarray:
    """World -> devkit LiDAR frame (inverse pose) -> x forward, y left (OpenPCDet's (y, -x, z))."""
    R = _quat_wxyz_to_matrix(_pose_quaternion())
    ego = (np.asarray(xyz, dtype=np.float64) - POSE_POSITION) @ R
    return np.stack([ego[:, 1], -ego[:, 0], ego[:, 2]], 1)


def test_pandaset_reader_against_the_devkit_convention(tmp_path):
    from lidarops.data.formats import PandaSetSequence

    seq = tmp_path / "001"
    _write_pandaset_by_hand(seq)
    frame = PandaSetSequence(seq)[0]
    # points: 10 m ahead, 3 m to the right, 1 m up in the devkit's LiDAR frame
    np.testing.assert_allclose(frame.points[:, :3], [[10.0, 0.0, 0.0], [0.0, -3.0, 0.0], [0.0, 0.0, 1.0]],
                               atol=1e-5)
    np.testing.assert_allclose(frame.points[:, 3], [1.0, 0.0, 0.2], atol=1e-7)
    assert frame.labels.shape == (2,) and frame.boxes.shape == (2, 7)
    for box, c in zip(frame.boxes.astype(np.float64), CUBOIDS):
        width, length, height = c["dims"]
        assert (box[3], box[4], box[5]) == pytest.approx((length, width, height), abs=1e-6)  # dx = length
        np.testing.assert_allclose(box[:3], _world_to_ours(np.array([c["position"]]))[0], atol=1e-5)
        # heading: the devkit's length direction (-sin yaw, cos yaw, 0) in world, seen in our frame
        d = np.array([[-math.sin(c["yaw"]), math.cos(c["yaw"]), 0.0]])
        dir_ours = _world_to_ours(d + POSE_POSITION)[0] - _world_to_ours(POSE_POSITION[None])[0]
        assert _angle_diff(box[6], math.atan2(dir_ours[1], dir_ours[0])) < 1e-3, c["label"]
        # the same box: the devkit's corners seen from the sensor (within the roll's few cm)
        assert _same_corner_sets(_lidar_box_corners(box), _world_to_ours(_devkit_world_corners(c)), atol=0.1)
    # world coordinates: centres as written, the yaw of the length axis from world +x
    world = PandaSetSequence(seq, coordinates="world")[0]
    for box, c in zip(world.boxes.astype(np.float64), CUBOIDS):
        np.testing.assert_allclose(box[:3], c["position"], atol=1e-5)
        assert _angle_diff(box[6], c["yaw"] + math.pi / 2) < 1e-6
        assert _same_corner_sets(_lidar_box_corners(box), _devkit_world_corners(c), atol=1e-4)


def test_pandaset_writer_against_the_devkit_convention(tmp_path):
    pd = pytest.importorskip("pandas")
    from lidarops.data.formats import write_pandaset_sequence

    # a sensor pose (world <- our LiDAR frame: x forward, y left) and two boxes in that frame
    sensor_pose = np.eye(4)
    sensor_pose[:3, :3] = _rot_z(1.1)
    sensor_pose[:3, 3] = [-4.0, 7.0, 1.5]
    boxes = np.array([[12.0, -3.0, 0.2, 4.2, 1.9, 1.5, 0.4], [6.0, 5.0, 0.0, 0.8, 0.6, 1.7, -2.0]], np.float32)
    points = np.array([[10.0, 0.0, 0.0, 1.0], [0.0, -3.0, 0.0, 0.0]], np.float32)
    frame = Frame(points=points, t=np.array([0.0, 0.05]), boxes=boxes, labels=np.array([0, 1]),
                  sensor_pose=sensor_pose, timestamp=0.05, object_ids=np.array([3, 4]))
    seq = tmp_path / "002"
    write_pandaset_sequence(seq, [frame])
    cub = pd.read_pickle(seq / "annotations" / "cuboids" / "00.pkl.gz")
    b64 = boxes.astype(np.float64)
    centres_world = b64[:, :3] @ sensor_pose[:3, :3].T + sensor_pose[:3, 3]
    np.testing.assert_allclose(cub[["position.x", "position.y", "position.z"]].to_numpy(), centres_world, atol=1e-5)
    np.testing.assert_allclose(cub["dimensions.y"].to_numpy(), b64[:, 3], atol=1e-6)  # length
    np.testing.assert_allclose(cub["dimensions.x"].to_numpy(), b64[:, 4], atol=1e-6)  # width
    np.testing.assert_allclose(cub["dimensions.z"].to_numpy(), b64[:, 5], atol=1e-6)
    for yaw_ps, box in zip(cub["yaw"].to_numpy(), b64):
        heading_world = sensor_pose[:3, :3] @ np.array([math.cos(box[6]), math.sin(box[6]), 0.0])
        # the devkit: yaw 0 = length along world (0, 1, 0), pi/2 = along (-1, 0, 0)
        devkit_dir = np.array([-math.sin(yaw_ps), math.cos(yaw_ps)])
        assert np.allclose(devkit_dir, heading_world[:2], atol=1e-6), (yaw_ps, heading_world)
    # the pose file: the devkit's lidar_points_to_ego (inverse pose) puts a point 10 m ahead of the sensor
    # at (0, 10, 0) (its LiDAR frame: x right, y forward)
    pose = json.loads((seq / "lidar" / "poses.json").read_text())[0]
    h, p = pose["heading"], pose["position"]
    R = _quat_wxyz_to_matrix((h["w"], h["x"], h["y"], h["z"]))
    t = np.array([p["x"], p["y"], p["z"]])
    df = pd.read_pickle(seq / "lidar" / "00.pkl.gz")
    ego = (df[["x", "y", "z"]].to_numpy() - t) @ R
    np.testing.assert_allclose(ego, [[0.0, 10.0, 0.0], [3.0, 0.0, 0.0]], atol=1e-5)
    np.testing.assert_allclose(df["i"].to_numpy(), [255.0, 0.0])
