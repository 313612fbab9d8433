"""Fuzz: every file reader of lidarops.data on damaged bytes.

Each test writes a valid file (drawn, or the format's documented example), then a damaged copy of it
(truncated at a random byte, bytes flipped, junk appended, random bytes, an empty file, a text field
replaced by NaN/inf/junk), reads it, and asserts the rule of the suite: a ``ValueError`` (or
``FileNotFoundError``) whose message names the file, never another exception type (a
``UnicodeDecodeError`` is a ValueError but does not count), or a result equal to what an independent
parse of the same bytes gives (NumPy's ``frombuffer`` for the binary scans, a pure-Python parser for
the KITTI text files, pandas / json / h5py / ``np.load`` directly for the container formats).
"""
from __future__ import annotations

import gzip
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from .fuzzing import assert_clear_error, fuzz, mangled, outcome

_F32_MAX = float(np.finfo(np.float32).max)


# ---------------------------------------------------------------------------------------------
# file bytes
# ---------------------------------------------------------------------------------------------
def file_bytes(valid: bytes, text: bool = False) -> st.SearchStrategy:
    """Damaged versions of ``valid``: :func:`fuzzing.mangled` (truncated, flipped, appended, random),
    an empty file, and for text formats lines with a field replaced or non-UTF-8 junk appended."""
    options = [mangled(valid), st.just(b""), st.just(valid)]
    if text:
        junk = st.sampled_from([b"\xff\xfe", b"\x00\x81\n", b"\xc3\x28", "é\n".encode("latin-1"), b"\n\n  \n",
                                b"Car 0 0 0\n", b"nan\n"])
        options.append(junk.map(lambda j: valid + j))
        options.append(_field_replaced(valid))
    return st.one_of(*options)


@st.composite
def _field_replaced(draw, valid: bytes) -> bytes:
    words = valid.split(b" ")
    i = draw(st.integers(0, len(words) - 1))
    tail = b"\n" if words[i].endswith(b"\n") else b""
    words[i] = draw(st.sampled_from([b"nan", b"inf", b"-inf", b"1e39", b"abc", b"", b"0x10", b"1_0", b"\xff", b"0", b"-1.5"])) + tail
    return b" ".join(words)


def _check_error(err, path: Path, what: str) -> None:
    assert not isinstance(err, UnicodeError), f"{what}: {type(err).__name__} reached the caller: {err}"
    assert_clear_error(err, (ValueError, FileNotFoundError), [str(path)], what)


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


_FLOATS32 = st.floats(-200, 200, width=32) | st.sampled_from([0.0, -0.0, 1.5, 255.0])


# ---------------------------------------------------------------------------------------------
# KITTI velodyne and nuScenes scans: headerless float32 records
# ---------------------------------------------------------------------------------------------
@fuzz
@given(data=st.data())
def test_kitti_velodyne(tmp_path, data):
    from lidarops.data.formats import read_velodyne

    n = data.draw(st.integers(0, 6), "points")
    valid = np.array(data.draw(st.lists(_FLOATS32, min_size=4 * n, max_size=4 * n)), np.float32).tobytes()
    raw = data.draw(file_bytes(valid), "bytes")
    path = _write(tmp_path, "velodyne/000000.bin", raw)
    got, err = outcome(read_velodyne, path)
    ref = np.frombuffer(raw[: len(raw) // 16 * 16], np.float32).reshape(-1, 4)
    if len(raw) % 16 or not np.isfinite(ref).all():
        return _check_error(err, path, f"read_velodyne({len(raw)} bytes)")
    assert err is None, f"read_velodyne: a valid scan of {len(raw)} bytes raised {type(err).__name__}: {err}"
    assert got.dtype == np.float32 and np.array_equal(got, ref, equal_nan=False)


@fuzz
@given(data=st.data())
def test_png_size(tmp_path, data):
    """``png_size`` (the image size the camera-view crop uses): the header's width and height, or None for
    anything that is not a readable PNG header, never an exception; checked against struct's parse."""
    import struct
    import zlib

    from lidarops.data.formats.kitti import png_size

    w, h = data.draw(st.integers(0, 2**31 - 1), "width"), data.draw(st.integers(0, 2**31 - 1), "height")
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    valid = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    raw = data.draw(file_bytes(valid), "bytes")
    path = _write(tmp_path, "image_2/000000.png", raw)
    got, err = outcome(png_size, path)
    assert err is None, f"png_size({len(raw)} bytes) raised {type(err).__name__}: {err}"
    ok = len(raw) >= 24 and raw[:8] == b"\x89PNG\r\n\x1a\n" and raw[12:16] == b"IHDR"
    assert got == (struct.unpack(">II", raw[16:24]) if ok else None)
    assert png_size(tmp_path / "missing.png") is None


@fuzz
@given(data=st.data())
def test_nuscenes_bin(tmp_path, data):
    from lidarops.data.formats import read_nuscenes_bin

    n = data.draw(st.integers(0, 5), "points")
    rows = [data.draw(st.lists(_FLOATS32, min_size=4, max_size=4)) + [float(data.draw(st.integers(0, 63)))]
            for _ in range(n)]
    valid = np.array(rows, np.float32).reshape(n, 5).tobytes()
    raw = data.draw(file_bytes(valid), "bytes")
    path = _write(tmp_path, "n008-2018__LIDAR_TOP__1533151603547590.pcd.bin", raw)
    got, err = outcome(read_nuscenes_bin, path)
    ref = np.frombuffer(raw[: len(raw) // 20 * 20], np.float32).reshape(-1, 5)
    ring = ref[:, 4]
    if len(raw) % 20 or not np.isfinite(ref).all() or not ((ring == np.round(ring)) & (ring >= 0) & (ring <= 32767)).all():
        return _check_error(err, path, f"read_nuscenes_bin({len(raw)} bytes)")
    assert err is None, f"read_nuscenes_bin: a valid scan of {len(raw)} bytes raised {type(err).__name__}: {err}"
    assert np.array_equal(got.points, ref[:, :4]) and np.array_equal(got.ring, ring.astype(np.int16))
    assert got.timestamp == 1533151603.547590


# ---------------------------------------------------------------------------------------------
# KITTI label and calib: text
# ---------------------------------------------------------------------------------------------
# from the KITTI object devkit's readme (label_2 of training frame 000000 and 000008): h w l, then the
# bottom centre x y z in the rectified camera frame
_LABEL = (b"Pedestrian 0.00 0 -0.20 712.40 143.00 810.73 307.92 1.89 0.48 1.20 1.84 1.47 8.41 0.01\n"
          b"Car 0.88 3 -0.69 0.00 192.37 402.31 374.00 1.60 1.57 3.23 -2.70 1.74 3.68 -1.29\n"
          b"DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n")


def _label_reference(raw: bytes):
    """Pure-Python parse of a label_2 file: None when the format refuses it."""
    try:
        text = raw.decode("utf-8-sig")  # a leading byte-order mark is not part of the first name
    except UnicodeDecodeError:
        return None
    rows = []
    for line in text.splitlines():
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            return None
        try:
            nums = [float(f) for f in fields[1:]]
        except ValueError:
            return None
        if not all(abs(v) <= _F32_MAX for v in nums) or nums[1] not in (-1, 0, 1, 2, 3):
            return None
        if fields[0] != "DontCare" and not all(v > 0 for v in nums[7:10]):
            return None  # an object with a zero or negative size
        rows.append((fields[0], nums))
    if len({len(r[1]) for r in rows}) > 1:
        return None
    return rows


@fuzz
@given(data=st.data())
def test_kitti_label(tmp_path, data):
    from lidarops.data.formats import read_label

    raw = data.draw(file_bytes(_LABEL, text=True), "bytes")
    raw = data.draw(st.sampled_from([raw, b"\xef\xbb\xbf" + raw, raw.replace(b"\n", b"\r\n")]), "bom or crlf")
    path = _write(tmp_path, "label_2/000000.txt", raw)
    got, err = outcome(read_label, path)
    ref = _label_reference(raw)
    if ref is None:
        return _check_error(err, path, f"read_label({raw[:60]!r}...)")
    assert err is None, f"read_label: a valid file raised {type(err).__name__}: {err}"
    assert got.names == [name for name, _ in ref]
    for i, (_, nums) in enumerate(ref):
        assert got.occluded[i] == nums[1]
        assert got.dimensions[i].tolist() == nums[7:10], "dimensions are h, w, l in the file's order"
        assert got.location[i].tolist() == nums[10:13] and got.rotation_y[i] == nums[13]
        assert got.bbox[i].tolist() == nums[3:7], "read in float64, as KITTI's evaluator reads them"
        assert got.truncated[i] == nums[0] and got.alpha[i] == nums[2]
        assert (got.score is None) == (len(nums) == 14)


def _calib_text() -> bytes:
    """A KITTI object calib file written by hand (the values of training frame 000000), not by write_calib."""
    p = "7.215377e+02 0.000000e+00 6.095593e+02 {} 0.000000e+00 7.215377e+02 1.728540e+02 {} 0 0 1 {}"
    return ("P0: " + p.format(0, 0, 0) + "\nP1: " + p.format(-3.875744e+02, 0, 0)
            + "\nP2: " + p.format(4.485728e+01, 2.163791e-01, 2.745884e-03)
            + "\nP3: " + p.format(-3.395242e+02, 2.199936e+00, 2.729905e-03)
            + "\nR0_rect: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 "
              "7.402527e-03 4.351614e-03 9.999631e-01"
            + "\nTr_velo_to_cam: 7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 "
              "7.280733e-04 -9.998902e-01 -7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01"
            + "\nTr_imu_to_velo: 9.999976e-01 7.553071e-04 -2.035826e-03 -8.086759e-01 -7.854027e-04 "
              "9.998898e-01 -1.482298e-02 3.195559e-01 2.024406e-03 1.482454e-02 9.998881e-01 -7.997231e-01\n"
            ).encode()


_CALIB = _calib_text()
_CALIB_SIZES = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12, "Tr_imu_to_velo": 12}


def _calib_reference(raw: bytes):
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    values = {}
    for line in text.splitlines():
        if not line.strip():
            continue
        if ":" not in line:
            return None
        key, rest = line.split(":", 1)
        key = key.strip()
        if key in values:
            return None
        try:
            values[key] = [float(v) for v in rest.split()]
        except ValueError:
            return None
        if not all(math.isfinite(v) for v in values[key]):
            return None
    values.setdefault("R0_rect", values.get("R_rect"))
    values.setdefault("Tr_velo_to_cam", values.get("Tr_velo_cam"))
    if any(values.get(k) is None for k in ("P2", "R0_rect", "Tr_velo_to_cam")):
        return None
    if any(k in values and values[k] is not None and len(values[k]) != n for k, n in _CALIB_SIZES.items()):
        return None
    m = np.eye(4)
    m[:3, :] = np.array(values["Tr_velo_to_cam"]).reshape(3, 4)
    r = np.eye(4)
    r[:3, :3] = np.array(values["R0_rect"]).reshape(3, 3)
    if not np.linalg.cond(r @ m) < 1e12:
        return None
    return values


@fuzz
@given(data=st.data())
def test_kitti_calib(tmp_path, data):
    from lidarops.data.formats import read_calib

    raw = data.draw(file_bytes(_CALIB, text=True), "bytes")
    path = _write(tmp_path, "calib/000000.txt", raw)
    got, err = outcome(read_calib, path)
    ref = _calib_reference(raw)
    if ref is None:
        return _check_error(err, path, f"read_calib({raw[:60]!r}...)")
    assert err is None, f"read_calib: a valid file raised {type(err).__name__}: {err}"
    assert got.P2.ravel().tolist() == ref["P2"]
    assert got.R0_rect.ravel().tolist() == ref["R0_rect"]
    assert got.Tr_velo_to_cam.ravel().tolist() == ref["Tr_velo_to_cam"]


# ---------------------------------------------------------------------------------------------
# PandaSet: gzip-pickled DataFrames and JSON
# ---------------------------------------------------------------------------------------------
def _pickle_gz(df) -> bytes:
    buf = io.BytesIO()
    with gzip.GzipFile(fileobj=buf, mode="wb", mtime=0) as f:
        df.to_pickle(f, compression=None)
    return buf.getvalue()


_POSE = {"position": {"x": 1.0, "y": -2.0, "z": 0.5}, "heading": {"w": 0.9238795, "x": 0.0, "y": 0.0, "z": 0.3826834}}


def _quat_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _pandaset_files(pd):
    lidar = pd.DataFrame({"x": [1.0, 2.0, -3.0], "y": [0.0, 1.0, 4.0], "z": [0.5, 0.5, 1.0],
                          "i": [10.0, 20.0, 255.0], "t": [0.0, 0.01, 0.02], "d": [0, 0, 1]})
    cuboids = pd.DataFrame({"uuid": ["7", "8"], "label": ["Car", "Pedestrian"], "yaw": [0.0, 1.0],
                            "position.x": [5.0, 6.0], "position.y": [0.0, 2.0], "position.z": [0.0, 0.5],
                            "dimensions.x": [2.0, 0.6], "dimensions.y": [4.0, 0.8], "dimensions.z": [1.5, 1.8]})
    return {"lidar/00.pkl.gz": _pickle_gz(lidar), "annotations/cuboids/00.pkl.gz": _pickle_gz(cuboids),
            "lidar/poses.json": json.dumps([_POSE]).encode(), "lidar/timestamps.json": b"[1557540000.5]"}


def _pandaset_reference(pd, files: dict):
    """The frame as the PandaSet devkit defines it, from pandas/json directly: (xyz, intensity, boxes
    xyz + dims, timestamp), or None when a file is malformed."""
    try:
        # decompressed whole first (CRC checked): a damaged stream unpickled as it is read can build a
        # DataFrame of billions of rows, which touching a column turns into an out-of-memory kill
        lidar = pd.read_pickle(io.BytesIO(gzip.decompress(files["lidar/00.pkl.gz"])), compression=None)
        cub = pd.read_pickle(io.BytesIO(gzip.decompress(files["annotations/cuboids/00.pkl.gz"])), compression=None)
        poses = json.loads(files["lidar/poses.json"].decode("utf-8"))
        stamps = json.loads(files["lidar/timestamps.json"].decode("utf-8"))
        pose = poses[0]
        q = [float(pose["heading"][k]) for k in "wxyz"]
        t = np.array([float(pose["position"][k]) for k in "xyz"])
        xyz = lidar[["x", "y", "z"]].to_numpy(np.float64)
        intensity = lidar["i"].to_numpy(np.float64)
        lidar[["t", "d"]].to_numpy(np.float64)
        centre = cub[["position.x", "position.y", "position.z"]].to_numpy(np.float64)
        dims = cub[["dimensions.x", "dimensions.y", "dimensions.z"]].to_numpy(np.float64)
        cub[["yaw"]].to_numpy(np.float64)
        stamp = float(stamps[0])
    except Exception:  # noqa: BLE001  (any failure of the reference parse: the file is malformed)
        return None
    if not isinstance(poses, list) or not isinstance(stamps, list) or not any(q) or not np.isfinite(q + list(t)).all():
        return None
    if not (np.isfinite(xyz).all() and np.isfinite(intensity).all() and np.isfinite(centre).all()
            and np.isfinite(dims).all() and (dims >= 0).all() and not math.isinf(stamp)):
        return None
    rot = _quat_matrix(q)
    ego = (xyz - t) @ rot  # PandaSet LiDAR frame: x right, y forward
    ours = np.stack([ego[:, 1], -ego[:, 0], ego[:, 2]], axis=1)  # lidarops: x forward, y left
    c_ego = (centre - t) @ rot
    if not (np.abs(ours) <= _F32_MAX).all() or not (np.abs(intensity / 255) <= _F32_MAX).all():
        return None
    return ours, intensity / 255.0, np.stack([c_ego[:, 1], -c_ego[:, 0], c_ego[:, 2]], axis=1), dims, stamp


@pytest.mark.parametrize("which", ["lidar/00.pkl.gz", "annotations/cuboids/00.pkl.gz", "lidar/poses.json",
                                   "lidar/timestamps.json"])
@fuzz
@given(data=st.data())
def test_pandaset_sequence(tmp_path, which, data):
    pd = pytest.importorskip("pandas")
    from lidarops.data.formats import PandaSetSequence

    files = _pandaset_files(pd)
    files[which] = data.draw(file_bytes(files[which], text=which.endswith(".json")), "bytes")
    seq = tmp_path / "seq"
    for name, raw in files.items():
        _write(seq, name, raw)
    got, err = outcome(lambda: PandaSetSequence(seq, unknown="keep")[0])
    ref = _pandaset_reference(pd, files)
    if ref is None:
        return _check_error(err, seq / which, f"PandaSetSequence with a damaged {which}")
    if err is not None:  # the reader may refuse more than the reference checks, but only naming the file
        return _check_error(err, seq / which, f"PandaSetSequence with a damaged {which}")
    xyz, intensity, centre, dims, stamp = ref
    assert np.allclose(got.points[:, :3], xyz.astype(np.float32), rtol=1e-6, atol=1e-5), (got.points, xyz)
    assert np.array_equal(got.points[:, 3], intensity.astype(np.float32))
    assert np.allclose(got.boxes[:, :3], centre.astype(np.float32), rtol=1e-6, atol=1e-5)
    # PandaSet dimensions.x is the width, dimensions.y the length: lidarops boxes are (dx=l, dy=w, dz=h)
    assert np.array_equal(got.boxes[:, 3:6], dims[:, [1, 0, 2]].astype(np.float32))
    assert got.timestamp == stamp or (math.isnan(got.timestamp) and math.isnan(stamp))


# ---------------------------------------------------------------------------------------------
# ModelNet40 HDF5 and lidarops' own .npz archives
# ---------------------------------------------------------------------------------------------
_MODELNET_VALID: dict = {}


def _modelnet_valid(tmp: Path) -> bytes:
    if "bytes" not in _MODELNET_VALID:
        from lidarops.data.formats import write_modelnet_h5

        path = write_modelnet_h5(tmp / "valid.h5", np.arange(2 * 5 * 3, dtype=np.float32).reshape(2, 5, 3) / 7,
                                 np.array([3, 39]))
        _MODELNET_VALID["bytes"] = path.read_bytes()
    return _MODELNET_VALID["bytes"]


@fuzz
@given(data=st.data())
def test_modelnet_h5(tmp_path, data):
    h5py = pytest.importorskip("h5py")
    from lidarops.data.formats import read_modelnet_h5

    raw = data.draw(file_bytes(_modelnet_valid(tmp_path)), "bytes")
    path = _write(tmp_path, "ply_data_train0.h5", raw)
    got, err = outcome(read_modelnet_h5, path)
    if err is not None:
        return _check_error(err, path, f"read_modelnet_h5({len(raw)} bytes)")
    with h5py.File(path, "r") as f:  # what h5py itself reads from the accepted file
        data_ref, label_ref = np.asarray(f["data"][...], np.float64), np.asarray(f["label"][...]).reshape(-1)
    points, labels = got
    assert np.isfinite(points).all() and (labels >= 0).all()
    assert np.array_equal(points, data_ref[:, :, :3].astype(np.float32)) and np.array_equal(labels, label_ref)


@fuzz
@given(data=st.data())
def test_object_set_npz(tmp_path, data):
    from lidarops.data.objects import ObjectSample, ObjectSet

    n = data.draw(st.integers(0, 3), "objects")
    samples = [ObjectSample(np.full((k + 1, 4), k, np.float32), k % 2, np.zeros(7, np.float32), k, k) for k in range(n)]
    valid_path = ObjectSet(samples, ("Car", "Pedestrian"), np.arange(n), np.zeros(0, np.int64)).save(tmp_path / "v.npz")
    raw = data.draw(file_bytes(valid_path.read_bytes()), "bytes")
    path = _write(tmp_path, "objects.npz", raw)
    got, err = outcome(ObjectSet.load, path)
    if err is not None:
        return _check_error(err, path, f"ObjectSet.load({len(raw)} bytes)")
    with np.load(path) as z:  # the accepted archive as NumPy reads it
        sizes, points, labels = z["sizes"], z["points"], z["labels"]
    assert len(got) == sizes.shape[0] == labels.shape[0]
    assert np.array_equal(np.concatenate([s.points for s in got.samples] or [np.zeros((0, 4), np.float32)]), points)
    assert [s.label for s in got.samples] == labels.tolist()


@fuzz
@given(data=st.data())
def test_gt_database_npz(tmp_path, data):
    from lidarops.data.augment import GtDatabase

    db = GtDatabase(points=np.arange(12, dtype=np.float32).reshape(3, 4), offsets=np.array([0, 1, 3]),
                    boxes=np.ones((2, 7), np.float32), names=np.array(["Car", "Cyclist"]), num_points=np.array([1, 2]),
                    difficulty=np.array([0, 1]), frame_ids=np.array(["000000", "000001"]), gt_index=np.array([0, 0]),
                    source_ids=np.array(["000000", "000001"]))
    raw = data.draw(file_bytes(db.save(tmp_path / "v.npz").read_bytes()), "bytes")
    path = _write(tmp_path, "gt_database_train.npz", raw)
    got, err = outcome(GtDatabase.load, path)
    if err is not None:
        return _check_error(err, path, f"GtDatabase.load({len(raw)} bytes)")
    with np.load(path) as z:
        assert np.array_equal(got.points, z["points"]) and np.array_equal(got.offsets, z["offsets"])
    for i in range(len(got)):  # every object's points lie inside the array (offsets checked)
        assert got.object_points(i).shape == (int(got.offsets[i + 1] - got.offsets[i]), 4)


@fuzz
@given(data=st.data())
def test_kitti_image_set_and_recipe(tmp_path, data):
    """The text files around a KITTI folder: ``ImageSets/<name>.txt`` and ``recipe.json``."""
    from lidarops.data.detection import KittiDetectionDataset
    from lidarops.data.formats import write_velodyne

    root = tmp_path / "kitti"
    write_velodyne(root / "training" / "velodyne" / "000000.bin", np.zeros((1, 4)))
    ids = data.draw(file_bytes(b"000000\n", text=True), "image set")
    recipe = data.draw(file_bytes(b'{"format": "kitti", "frames": 1}\n', text=True), "recipe")
    _write(root, "ImageSets/train.txt", ids)
    _write(root, "recipe.json", recipe)
    got, err = outcome(KittiDetectionDataset, root, split="train", training=False)
    try:
        id_list = [line.strip() for line in ids.decode("utf-8").splitlines() if line.strip()]
        ids_ok = all(i and "/" not in i and "\\" not in i and "\0" not in i and i not in (".", "..") for i in id_list)
    except UnicodeDecodeError:
        ids_ok = False
    if not ids_ok:
        return _check_error(err, root / "ImageSets" / "train.txt", "KittiDetectionDataset with a damaged image set")
    try:
        ref = json.loads(recipe.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        ref = None
    if not isinstance(ref, dict):
        return _check_error(err, root / "recipe.json", "KittiDetectionDataset with a damaged recipe.json")
    assert err is None, f"a valid folder raised {type(err).__name__}: {err}"
    assert got.ids == id_list and got.recipe == ref
