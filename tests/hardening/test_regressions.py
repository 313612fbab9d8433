"""Hardening regression tests, one explicit hand-written input per class of bug. Each
input reproduces a reported bug (a silent wrong answer, an allocation before the refusal, an
unclear error), so each test fails if its guard is removed. The fuzz suite (tests/fuzz) covers the
same ground with generated inputs.
"""
from __future__ import annotations

import gzip
import json
import math
import threading
import time

import numpy as np
import pytest
import torch

import lidarops
from lidarops.ops import ball_query, fps, knn


def _clear_error(excinfo, *names: str) -> str:
    """The message of a plain ValueError (not a subclass such as UnicodeDecodeError) naming all of ``names``."""
    err = excinfo.value
    assert not isinstance(err, UnicodeError), f"a {type(err).__name__} reached the caller: {err}"
    msg = str(err)
    for name in names:
        assert str(name) in msg, f"the error does not name {name!r}: {msg!r}"
    return msg


# ---------------------------------------------------------------------------------------------
# global switches are thread-local
# ---------------------------------------------------------------------------------------------
def test_validation_off_in_one_thread_leaves_it_on_in_another():
    inside, done = threading.Event(), threading.Event()

    def other():
        with lidarops.validation(False):
            inside.set()
            done.wait(10)

    thread = threading.Thread(target=other)
    thread.start()
    try:
        assert inside.wait(10)
        nan_points = torch.tensor([[[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0]]])
        # with a process-wide switch this returns -1 for the NaN neighbour instead of raising
        with pytest.raises(ValueError) as e:
            knn(nan_points, nan_points, 1)
        _clear_error(e, "NaN")
    finally:
        done.set()
        thread.join()


def test_validation_switch_is_off_inside_its_own_thread():
    """The other half: the switch still works where it was entered (else the test above proves nothing)."""
    from lidarops.ops.validation import value_checks_enabled

    result = {}

    def worker():
        with lidarops.validation(False):
            result["inside"] = value_checks_enabled()
        result["after"] = value_checks_enabled()

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert result == {"inside": False, "after": True}
    assert value_checks_enabled()


# ---------------------------------------------------------------------------------------------
# squared distances that overflow float32
# ---------------------------------------------------------------------------------------------
# |x| = 1e20 is finite in float32 but (1e20)^2 = 1e40 is not: computed naively, every distance is +inf
# and the real neighbours come back as -1 ("no neighbour").
_FAR = torch.tensor([[[1e20, 0.0, 0.0], [3e20, 0.0, 0.0], [-6e20, 0.0, 0.0]]], dtype=torch.float32)
_ORIGIN = torch.zeros(1, 1, 3, dtype=torch.float32)


def _raises_naming_or_equals(fn, names, reference):
    try:
        got = fn()
    except ValueError as e:
        assert any(n in str(e) for n in names), f"the error names none of {names}: {e}"
        return
    got = got.tolist() if isinstance(got, torch.Tensor) else got
    assert got == reference, f"got {got}, float64 reference {reference}"


def test_knn_huge_float32_coordinates_raise_or_match_float64():
    # float64 by hand: squared distances 1e40, 9e40, 3.6e41 from the origin: nearest first
    _raises_naming_or_equals(lambda: knn(_ORIGIN, _FAR, 2)[1], ("points",), [[[0, 1]]])


def test_ball_query_huge_float32_coordinates_raise_or_match_float64():
    # radius 2e20: radius^2 = 4e40 > 1e40 (point 0 inside) and < 9e40 (point 1 outside)
    _raises_naming_or_equals(lambda: ball_query(_ORIGIN, _FAR, 2e20, 3)[1], ("points",), [[[0, -1, -1]]])


def test_fps_huge_float32_coordinates_raise_or_match_float64():
    pts = torch.cat([_ORIGIN, _FAR], dim=1)  # 0, 1e20, 3e20, -6e20 on the x axis
    # from point 0, the farthest is -6e20 (index 3); then min distances 1e20 (1) and 3e20 (2): index 2
    _raises_naming_or_equals(lambda: fps(pts, 3, start_idx=0), ("points",), [[0, 3, 2]])


def test_coordinates_just_inside_the_bound_are_accepted_and_exact():
    from lidarops.ops.validation import coordinate_bound

    b = coordinate_bound(torch.float32)
    pts = torch.tensor([[[b, 0.0, 0.0], [-b, 0.0, 0.0], [0.0, b / 2, 0.0]]], dtype=torch.float32)
    dist2, idx = knn(_ORIGIN, pts, 3)
    assert idx.tolist() == [[[2, 0, 1]]]
    assert torch.isfinite(dist2).all()


# ---------------------------------------------------------------------------------------------
# sizes that cannot be meant are refused before anything is allocated
# ---------------------------------------------------------------------------------------------
_K = 2**31


@pytest.mark.parametrize("op", ["knn", "ball_query", "fps"])
def test_huge_k_is_refused_before_allocating(op):
    pts = torch.zeros(1, 1, 3)
    call = {"knn": lambda: knn(pts, pts, _K), "ball_query": lambda: ball_query(pts, pts, 1.0, _K),
            "fps": lambda: fps(pts, _K)}[op]
    start = time.perf_counter()
    with pytest.raises(ValueError) as e:
        call()
    # allocating the (1, 1, 2^31) padded outputs first would take seconds and 16 GB (or MemoryError)
    assert time.perf_counter() - start < 1.0
    _clear_error(e, "k")


def test_int64_sparse_indices_beyond_int32_raise_instead_of_wrapping():
    from lidarops.sparse import SparseConvTensor

    feats = torch.ones(1, 2)
    for bad in ([0, 2**32 + 1, 0], [2**32, 1, 1], [0, 1, -(2**32) + 2]):  # wrap to 1, batch 0, 2
        with pytest.raises(ValueError) as e:
            SparseConvTensor(feats, torch.tensor([bad], dtype=torch.int64), [4, 4], 1)
        _clear_error(e, "indices")
    ok = SparseConvTensor(feats, torch.tensor([[0, 3, 2]], dtype=torch.int64), [4, 4], 1)
    assert ok.indices.dtype == torch.int32 and ok.indices.tolist() == [[0, 3, 2]]


def test_float_spatial_shape_is_refused_not_truncated():
    from lidarops.sparse import SparseConvTensor

    with pytest.raises(ValueError) as e:
        SparseConvTensor(torch.ones(1, 1), torch.zeros(1, 3, dtype=torch.int32), [10.7, 4], 1)
    _clear_error(e, "spatial_shape")


def test_torch_cluster_fps_nan_ratio_names_ratio():
    from lidarops.compat import torch_cluster

    src = torch.rand(8, 3)
    for ratio in (float("nan"), torch.tensor(float("nan"))):
        with pytest.raises(ValueError) as e:
            torch_cluster.fps(src, ratio=ratio, random_start=False)
        _clear_error(e, "ratio")


# ---------------------------------------------------------------------------------------------
# readers: truncated and junk files name the file
# ---------------------------------------------------------------------------------------------
def test_kitti_velodyne_truncated_names_the_file(tmp_path):
    from lidarops.data.formats import read_velodyne

    path = tmp_path / "000000.bin"
    path.write_bytes(np.arange(8, dtype=np.float32).tobytes() + b"\x00")  # 33 bytes: 2 points and 1 byte
    with pytest.raises(ValueError) as e:
        read_velodyne(path)
    _clear_error(e, path, "16")
    path.write_bytes(np.arange(8, dtype=np.float32).tobytes())
    assert read_velodyne(path).tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]]


def test_nuscenes_bin_truncated_names_the_file(tmp_path):
    from lidarops.data.formats import read_nuscenes_bin

    path = tmp_path / "n015__LIDAR_TOP__1532402927647951.pcd.bin"
    path.write_bytes(np.zeros(8, np.float32).tobytes())  # 32 bytes: a KITTI scan of 2 points, not 20-byte records
    with pytest.raises(ValueError) as e:
        read_nuscenes_bin(path)
    _clear_error(e, path, "20")
    path.write_bytes(np.array([1, 2, 3, 4, 7], np.float32).tobytes())
    frame = read_nuscenes_bin(path)
    assert frame.points.tolist() == [[1, 2, 3, 4]] and frame.ring.tolist() == [7]


_LABEL_LINE = b"Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"


@pytest.mark.parametrize("junk", [b"\xff\xfe\x00\x81", b"\x89PNG\r\n\x1a\n"])
def test_kitti_label_binary_junk_names_the_file(tmp_path, junk):
    from lidarops.data.formats import read_label

    path = tmp_path / "000000.txt"
    path.write_bytes(_LABEL_LINE + junk)
    with pytest.raises(ValueError) as e:
        read_label(path)
    _clear_error(e, path)


def test_kitti_calib_binary_junk_names_the_file(tmp_path):
    from lidarops.data.formats import read_calib

    path = tmp_path / "000000.txt"
    path.write_bytes(b"P2: " + b"1 " * 12 + b"\nR0_rect: \xc3\x28\xa0\xa1\n")
    with pytest.raises(ValueError) as e:
        read_calib(path)
    _clear_error(e, path)


def test_kitti_image_set_binary_junk_names_the_file(tmp_path):
    from lidarops.data.formats import KittiDataset

    (tmp_path / "training" / "velodyne").mkdir(parents=True)
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "train.txt").write_bytes(b"000000\n\xff\xff\n")
    with pytest.raises(ValueError) as e:
        KittiDataset(tmp_path, image_set="train")
    _clear_error(e, tmp_path / "ImageSets" / "train.txt")


def _pandaset_sequence(root):
    """A one-frame sequence written by hand with pandas (the devkit's layout), not with our writer."""
    pd = pytest.importorskip("pandas")
    lidar = root / "lidar"
    (root / "annotations" / "cuboids").mkdir(parents=True)
    lidar.mkdir()
    pd.DataFrame({"x": [1.0, 2.0], "y": [0.0, 1.0], "z": [0.5, 0.5], "i": [10.0, 20.0], "t": [0.0, 0.01],
                  "d": [0, 0]}).to_pickle(lidar / "00.pkl.gz", compression="gzip")
    pd.DataFrame({"uuid": ["7"], "label": ["Car"], "yaw": [0.0], "position.x": [5.0], "position.y": [0.0],
                  "position.z": [0.0], "dimensions.x": [2.0], "dimensions.y": [4.0], "dimensions.z": [1.5]}
                 ).to_pickle(root / "annotations" / "cuboids" / "00.pkl.gz", compression="gzip")
    (lidar / "poses.json").write_text(json.dumps([{"position": {"x": 0, "y": 0, "z": 0},
                                                   "heading": {"w": 1, "x": 0, "y": 0, "z": 0}}]))
    (lidar / "timestamps.json").write_text("[1.5]")
    return {"lidar": lidar / "00.pkl.gz", "cuboids": root / "annotations" / "cuboids" / "00.pkl.gz",
            "poses": lidar / "poses.json", "timestamps": lidar / "timestamps.json"}


@pytest.mark.parametrize("which", ["lidar", "cuboids", "poses", "timestamps"])
@pytest.mark.parametrize("damage", ["truncated", "junk"])
def test_pandaset_malformed_files_name_the_file(tmp_path, which, damage):
    from lidarops.data.formats import PandaSetSequence

    files = _pandaset_sequence(tmp_path)
    seq = PandaSetSequence(tmp_path)
    frame = seq[0]
    # the valid sequence reads (PandaSet's x right, y forward -> lidarops' x forward, y left)
    assert frame.points[:, :3].tolist() == [[0.0, -1.0, 0.5], [1.0, -2.0, 0.5]]
    data = files[which].read_bytes()
    files[which].write_bytes(data[:len(data) // 2] if damage == "truncated" else b"\xff\x00junk" + data[::3])
    with pytest.raises(ValueError) as e:
        PandaSetSequence(tmp_path)[0]
    _clear_error(e, files[which])


def test_pandaset_flipped_payload_byte_is_an_error_not_other_values(tmp_path):
    """A damaged byte inside a gzip member: only the CRC at the member's end shows it. Unpickled as the
    stream is read, the pickle ends before the CRC is reached and the damaged values come back (or a
    damaged row count turns into an out-of-memory kill when a column is touched)."""
    pd = pytest.importorskip("pandas")
    from lidarops.data.formats import PandaSetSequence

    files = _pandaset_sequence(tmp_path)
    raw_pickle = gzip.decompress(files["lidar"].read_bytes())
    stored = gzip.compress(raw_pickle, compresslevel=0, mtime=0)  # stored blocks: the payload is verbatim
    x_values = np.array([1.0, 2.0], np.float64).tobytes()
    at = stored.find(x_values)
    assert at > 0, "the x column's bytes are not in the stored stream"
    damaged = bytearray(stored)
    damaged[at + 8 + 6] ^= 0x10  # an exponent bit of x[1]: 2.0 becomes 4.0, which pandas alone returns
    files["lidar"].write_bytes(bytes(damaged))
    with pytest.raises(ValueError) as e:
        PandaSetSequence(tmp_path)[0]
    _clear_error(e, files["lidar"])


def test_pandaset_coordinates_beyond_float32_name_the_file(tmp_path):
    pd = pytest.importorskip("pandas")
    from lidarops.data.formats import PandaSetSequence

    files = _pandaset_sequence(tmp_path)
    pd.DataFrame({"x": [1e39], "y": [0.0], "z": [0.0], "i": [1.0], "t": [0.0], "d": [0]}).to_pickle(
        files["lidar"], compression="gzip")  # finite in float64, +inf once stored as float32
    with pytest.raises(ValueError) as e:
        PandaSetSequence(tmp_path)[0]
    _clear_error(e, files["lidar"], "float32")


def test_modelnet_truncated_or_junk_h5_names_the_file(tmp_path):
    pytest.importorskip("h5py")
    from lidarops.data.formats import ModelNet40, read_modelnet_h5, write_modelnet_h5

    path = write_modelnet_h5(tmp_path / "ply_data_train0.h5", np.zeros((2, 4, 3)), np.array([1, 2]))
    data = path.read_bytes()
    for damaged in (data[:len(data) // 2], data[:600], b"\x89HDF\r\n\x1a\n" + b"\x00" * 64):
        path.write_bytes(damaged)
        with pytest.raises(ValueError) as e:
            read_modelnet_h5(path)
        _clear_error(e, path)
    path.write_bytes(data)
    (tmp_path / "shape_names.txt").write_bytes(b"airplane\n\xff\xfe\n")
    with pytest.raises(ValueError) as e:
        ModelNet40(tmp_path)
    _clear_error(e, tmp_path / "shape_names.txt")
    (tmp_path / "shape_names.txt").write_text("airplane\nbathtub\n")  # label 2 has no name
    with pytest.raises(ValueError) as e:
        ModelNet40(tmp_path)
    _clear_error(e, path, "label 2")


def test_modelnet_nan_points_name_the_file(tmp_path):
    pytest.importorskip("h5py")
    from lidarops.data.formats import read_modelnet_h5, write_modelnet_h5

    pts = np.zeros((2, 4, 3))
    pts[1, 2, 0] = np.nan
    path = write_modelnet_h5(tmp_path / "m.h5", pts, np.array([0, 1]))
    with pytest.raises(ValueError) as e:
        read_modelnet_h5(path)
    _clear_error(e, path, "shape 1")


def test_object_set_truncated_names_the_file(tmp_path):
    from lidarops.data.objects import ObjectSample, ObjectSet

    s = ObjectSet([ObjectSample(np.ones((3, 4), np.float32), 0, np.zeros(7, np.float32), 0, 0)], ("Car",),
                  np.array([0]), np.zeros(0, np.int64))
    path = tmp_path / "objects.npz"
    s.save(path)
    data = path.read_bytes()
    back = ObjectSet.load(path)
    assert back.samples[0].points.tolist() == [[1.0] * 4] * 3
    central = data.index(b"PK\x01\x02")  # the first central-directory entry
    encrypted, newer = bytearray(data), bytearray(data)
    encrypted[central + 8] |= 1  # its "encrypted" flag: zipfile raises RuntimeError
    newer[central + 6] = 0x40  # "needs zip version 6.4": zipfile raises NotImplementedError
    for damaged in (data[: len(data) // 2], data[:40], b"PK\x03\x04" + bytes(60), b"", bytes(encrypted), bytes(newer)):
        path.write_bytes(damaged)
        with pytest.raises(ValueError) as e:
            ObjectSet.load(path)
        _clear_error(e, path)


def test_gt_database_truncated_or_inconsistent_names_the_file(tmp_path):
    from lidarops.data.augment import GtDatabase

    db = GtDatabase(points=np.ones((3, 4), np.float32), offsets=np.array([0, 3]), boxes=np.zeros((1, 7), np.float32),
                    names=np.array(["Car"]), num_points=np.array([3]), difficulty=np.array([0]),
                    frame_ids=np.array(["000000"]), gt_index=np.array([0]), source_ids=np.array(["000000"]))
    path = db.save(tmp_path / "gt.npz")
    data = path.read_bytes()
    assert GtDatabase.load(path).object_points(0).shape == (3, 4)
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError) as e:
        GtDatabase.load(path)
    _clear_error(e, path)
    db.offsets = np.array([0, 5])  # 5 points claimed, 3 stored: object_points would read short
    db.save(path)
    with pytest.raises(ValueError) as e:
        GtDatabase.load(path)
    _clear_error(e, path, "offsets")


def test_detection_recipe_junk_names_the_file(tmp_path):
    from lidarops.data.detection import KittiDetectionDataset
    from lidarops.data.formats import write_velodyne

    write_velodyne(tmp_path / "training" / "velodyne" / "000000.bin", np.zeros((1, 4)))
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "train.txt").write_text("000000\n")
    for junk in (b"{\"format\": \"kitti\"", b"\xff\xfe{}", b"[1, 2]"):
        (tmp_path / "recipe.json").write_bytes(junk)
        with pytest.raises(ValueError) as e:
            KittiDetectionDataset(tmp_path, split="train", training=False)
        _clear_error(e, tmp_path / "recipe.json")


# ---------------------------------------------------------------------------------------------
# the simulator: nonsensical arguments name the argument and what was expected
# ---------------------------------------------------------------------------------------------
NAN, INF = float("nan"), float("inf")


def _sim():
    from lidarops.data.synthetic import Simulator

    return Simulator("driving_city", seed=0, object_counts="empty")


def _bad_simulator_calls():
    from lidarops.data import sensors
    from lidarops.data.datasets import StreamDataset
    from lidarops.data.scene import build_scenario
    from lidarops.data.synthetic import Simulator, SyntheticFrames

    sim = lambda **kw: Simulator(**{"object_counts": "empty", **kw})  # noqa: E731
    return [
        # (label, call, the argument the message must name)
        ("seed=nan", lambda: sim(seed=NAN), "seed"),
        ("seed=1.5", lambda: sim(seed=1.5), "seed"),
        ("seed=True", lambda: sim(seed=True), "seed"),
        ("seed=-1", lambda: sim(seed=-1), "seed"),
        ("scenario=unknown", lambda: sim(scenario="driving_moon"), "driving_city"),
        ("scenario=3", lambda: sim(scenario=3), "scenario"),
        ("block_duration=nan", lambda: sim(block_duration=NAN), "block_duration"),
        ("block_duration=-0.02", lambda: sim(block_duration=-0.02), "block_duration"),
        ("block_duration=inf", lambda: sim(block_duration=INF), "block_duration"),
        ("block_duration=1e-9", lambda: sim(block_duration=1e-9), "block_duration"),
        ("cache_blocks=-1", lambda: sim(cache_blocks=-1), "cache_blocks"),
        ("cache_blocks=2.5", lambda: sim(cache_blocks=2.5), "cache_blocks"),
        ("ego_speed=nan", lambda: sim(ego_speed=NAN), "ego_speed"),
        ("ego_speed=-3", lambda: sim(ego_speed=-3.0), "ego_speed"),
        ("object_counts nan", lambda: Simulator(object_counts={"Car": NAN}), "Car"),
        ("object_counts True", lambda: Simulator(object_counts={"Car": True}), "Car"),
        ("object_counts 2.5", lambda: Simulator(object_counts={"Car": 2.5}), "Car"),
        ("object_counts (5, 1)", lambda: Simulator(object_counts={"Car": (5, 1)}), "Car"),
        ("build_scenario seed", lambda: build_scenario("driving_city", seed=NAN), "seed"),
        ("stream t0=nan", lambda: _sim().stream(NAN, 0.01), "t0"),
        ("stream t1=inf", lambda: _sim().stream(0.0, INF), "t1"),
        ("stream t0=-1", lambda: _sim().stream(-1.0, 0.01), "t0"),
        ("stream t1<t0", lambda: _sim().stream(0.02, 0.01), "t1"),
        ("stream t0='0'", lambda: _sim().stream("0", 0.01), "t0"),
        ("slices dt=nan", lambda: list(_sim().slices(0.0, 0.01, NAN)), "dt"),
        ("slices dt=0", lambda: list(_sim().slices(0.0, 0.01, 0.0)), "dt"),
        ("slices dt=-0.01", lambda: list(_sim().slices(0.0, 0.01, -0.01)), "dt"),
        ("slices t1=nan", lambda: list(_sim().slices(0.0, NAN)), "t1"),
        ("slices t1<t0", lambda: list(_sim().slices(0.02, 0.01)), "t1"),
        ("sweep 1.7", lambda: _sim().sweep(1.7), "i"),
        ("sweep True", lambda: _sim().sweep(True), "i"),
        ("sweep nan", lambda: _sim().sweep(NAN), "i"),
        ("sweep -1", lambda: _sim().sweep(-1), "i"),
        ("sweep 10**30", lambda: _sim().sweep(10**30), "i"),
        ("frames n=-1", lambda: list(_sim().frames(-1)), "n"),
        ("frames n=1.5", lambda: list(_sim().frames(1.5)), "n"),
        ("frame_span nan", lambda: _sim().frame_span(NAN), "i"),
        ("object_boxes_at nan", lambda: _sim().object_boxes_at(NAN), "t"),
        ("sensor_pose inf", lambda: _sim().sensor_pose(np.array([0.0, INF])), "t"),
        ("SyntheticFrames num_frames=2.5", lambda: SyntheticFrames(num_frames=2.5), "num_frames"),
        ("SyntheticFrames seed=nan", lambda: SyntheticFrames(seed=NAN), "seed"),
        ("SyntheticFrames frames_per_scene=0", lambda: SyntheticFrames(frames_per_scene=0), "frames_per_scene"),
        ("SyntheticFrames fov_deg=nan", lambda: SyntheticFrames(fov_deg=NAN), "fov_deg"),
        ("SyntheticFrames scenario", lambda: SyntheticFrames("nope"), "scenario"),
        ("StreamDataset slice_duration=nan", lambda: StreamDataset(_sim(), slice_duration=NAN), "slice_duration"),
        ("StreamDataset t0=inf", lambda: StreamDataset(_sim(), t0=INF), "t0"),
        ("StreamDataset num_slices=1.5", lambda: StreamDataset(_sim(), num_slices=1.5), "num_slices"),
        ("hdl64 rotation_hz=nan", lambda: sensors.hdl64(rotation_hz=NAN), "rotation_hz"),
        ("hdl64 rotation_hz=0", lambda: sensors.hdl64(rotation_hz=0), "rotation_hz"),
        ("hdl64 columns_per_rev=0", lambda: sensors.hdl64(columns_per_rev=0), "columns_per_rev"),
        ("hdl64 max_range=nan", lambda: sensors.hdl64(max_range=NAN), "max_range"),
        ("hdl64 min_range>max_range", lambda: sensors.hdl64(min_range=200.0), "min_range"),
        ("hdl64 dropout=2", lambda: sensors.hdl64(dropout=2.0), "dropout"),
        ("hdl64 range_noise_std=-1", lambda: sensors.hdl64(range_noise_std=-1.0), "range_noise_std"),
        ("hdl64 elevation nan", lambda: sensors.hdl64(elevations_deg=(1.0, NAN)), "elevations_deg"),
        ("avia points_per_s=nan", lambda: sensors.avia(points_per_s=NAN), "points_per_s"),
        ("avia channels=0", lambda: sensors.avia(channels=0), "channels"),
        ("avia frame_period=-1", lambda: sensors.avia(frame_period=-1.0), "frame_period"),
        ("avia fov_h_deg=inf", lambda: sensors.avia(fov_h_deg=INF), "fov_h_deg"),
        ("avia prism_hz nan", lambda: sensors.avia(prism_hz=(NAN, 1.0)), "prism_hz"),
        ("replace dropout=nan", lambda: sensors.hdl64().replace(dropout=NAN), "dropout"),
    ]


_CASES = _bad_simulator_calls()


@pytest.mark.parametrize("label, call, name", _CASES, ids=[c[0] for c in _CASES])
def test_simulator_refuses_nonsense_naming_the_argument(label, call, name):
    with pytest.raises(ValueError) as e:
        call()
    msg = _clear_error(e, name)
    assert "must" in msg or "choose one of" in msg, f"{label}: the message does not say what was expected: {msg!r}"


def test_simulator_valid_arguments_still_work():
    """The guards let the documented inputs through: NumPy ints for seeds and indices, 0-length spans."""
    sim = _sim()
    points, t = sim.stream(np.float64(0.0), 0.002)
    assert points.shape[0] == t.shape[0] > 0 and (np.diff(t) >= 0).all() and t.min() >= 0 and t.max() < 0.002
    empty, t_empty = sim.stream(0.005, 0.005)
    assert empty.shape == (0, 4) and t_empty.shape == (0,)
    parts = list(sim.slices(0.0, 0.002, 0.001))
    assert len(parts) == 2 and np.array_equal(np.concatenate([p for p, _ in parts]), points)
    assert sim.frame_span(np.int64(2)) == pytest.approx((0.2, 0.3))
