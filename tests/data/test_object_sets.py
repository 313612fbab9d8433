"""Object classification sets (lidarops.data.object_sets): deterministic resampling, normalisation and
augmentation, counts per class, the stratified split, the cache, the collate function and ModelNet40."""
from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import torch

from lidarops.data import object_sets
from lidarops.data.frame import CLASSES
from lidarops.data.object_sets import (Augmentation, ObjectClassificationDataset, ObjectSetRecipe, build_object_set,
                                       collate_classification, datasets_from_config, normalize_cloud, resample)
from lidarops.data.objects import ObjectSample, ObjectSet, split_balanced

#: two highway scenes (cars, trucks, barriers, cones) and 40 lock scenes (drones): about a second to simulate
TINY = ObjectSetRecipe({"driving_highway": 2, "drone_lock": 40}, seed=3, min_points=5, test_fraction=0.25)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    cache = tmp_path_factory.mktemp("objects")
    t0 = time.perf_counter()
    objset = build_object_set(TINY, cache)
    return objset, cache, time.perf_counter() - t0


def hand_set(counts=(("Car", 30), ("Pedestrian", 12), ("Drone", 6)), seed=0) -> ObjectSet:
    """Objects of random sizes (3 to 200 points, x, y, z, intensity) without simulating anything."""
    rng = np.random.default_rng(seed)
    samples = []
    for name, n in counts:
        for _ in range(n):
            p = int(rng.integers(3, 200))
            samples.append(ObjectSample(rng.normal(size=(p, 4)).astype(np.float32), CLASSES.index(name),
                                        np.zeros(7, np.float32)))
    train, test = split_balanced(samples, 0.25, seed)
    return ObjectSet(samples, CLASSES, train, test)


# ---------------------------------------------------------------------------------------------------- resampling
@pytest.mark.parametrize("p", [1, 7, 64, 65, 300])
def test_resample_is_deterministic_and_keeps_every_point_it_can(p):
    pts = np.arange(p * 4, dtype=np.float32).reshape(p, 4)
    a = resample(pts, 64, np.random.default_rng((0, 5)))
    b = resample(pts, 64, np.random.default_rng((0, 5)))
    assert a.shape == (64, 4) and np.array_equal(a, b)
    rows = a[:, 0].astype(np.int64) // 4  # which input row each output row is
    assert np.array_equal(a, pts[rows])
    if p >= 64:
        assert len(set(rows.tolist())) == 64 and np.all(np.diff(rows) > 0)  # a subset, in scan order
        if p == 64:
            assert np.array_equal(a, pts)
    else:
        assert np.array_equal(rows[:p], np.arange(p))  # every point once, then the copies
    c = resample(pts, 64, np.random.default_rng((1, 5)))
    assert p <= 1 or p == 64 or not np.array_equal(a, c)  # another seed, another draw


def test_resample_refuses_an_empty_object():
    with pytest.raises(ValueError, match="points is empty"):
        resample(np.zeros((0, 3), np.float32), 8, np.random.default_rng(0))


def test_normalize_modes():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(5.0, 2.0, size=(50, 3)), rng.uniform(size=(50, 1))], 1).astype(np.float32)
    unit = normalize_cloud(pts, "unit_sphere")
    assert np.allclose(unit[:, :3].mean(0), 0, atol=1e-6)
    assert np.linalg.norm(unit[:, :3], axis=1).max() == pytest.approx(1.0, abs=1e-6)
    assert np.array_equal(unit[:, 3], pts[:, 3])  # intensity untouched
    centred = normalize_cloud(pts, "center")
    assert np.allclose(centred[:, :3], pts[:, :3] - pts[:, :3].astype(np.float64).mean(0), atol=1e-5)
    assert np.array_equal(normalize_cloud(pts, "none"), pts)
    assert np.array_equal(normalize_cloud(np.ones((4, 3), np.float32), "unit_sphere"), np.zeros((4, 3)))


# ---------------------------------------------------------------------------------------------------- the Dataset
def test_items_are_deterministic_and_do_not_depend_on_the_split():
    objset = hand_set()
    whole = ObjectClassificationDataset.from_object_set(objset, None, num_points=32, in_channels=4)
    test = ObjectClassificationDataset.from_object_set(objset, "test", num_points=32, in_channels=4)
    again = ObjectClassificationDataset.from_object_set(objset, "test", num_points=32, in_channels=4)
    other = ObjectClassificationDataset.from_object_set(objset, "test", num_points=32, in_channels=4, seed=1)
    for j in range(len(test)):
        item = test[j]
        assert item["points"].shape == (32, 4) and item["points"].dtype == torch.float32
        assert torch.equal(item["points"], again[j]["points"])
        assert torch.equal(item["points"], whole[item["frame_id"]]["points"])  # same object, same cloud
        assert item["label"] == objset.samples[item["frame_id"]].label
    assert any(not torch.equal(test[j]["points"], other[j]["points"]) for j in range(len(test)))
    assert ObjectClassificationDataset.from_object_set(objset, "train", num_points=16)[0]["points"].shape == (16, 3)


def test_augmentation_is_seeded_by_the_epoch_and_only_where_asked():
    objset = hand_set()
    aug = ObjectClassificationDataset.from_object_set(objset, "train", num_points=32, augment=Augmentation())
    plain = ObjectClassificationDataset.from_object_set(objset, "train", num_points=32)
    first = aug[0]["points"]
    assert torch.equal(first, aug[0]["points"]) and not torch.equal(first, plain[0]["points"])
    aug.set_epoch(1)
    assert not torch.equal(first, aug[0]["points"])
    aug.set_epoch(0)
    assert torch.equal(first, aug[0]["points"])
    plain.set_epoch(3)
    assert torch.equal(plain[0]["points"], ObjectClassificationDataset.from_object_set(objset, "train",
                                                                                        num_points=32)[0]["points"])
    # rotation about z only: without scale and jitter, heights and radii about z are kept
    rot = Augmentation(rot_z_deg=30, scale_range=(1.0, 1.0), jitter_sigma=0.0)
    pts = plain.cloud(0)
    out = rot(pts, np.random.default_rng(0))
    assert np.allclose(out[:, 2], pts[:, 2]) and np.allclose(np.hypot(out[:, 0], out[:, 1]),
                                                             np.hypot(pts[:, 0], pts[:, 1]), atol=1e-6)
    angle = np.degrees(np.arctan2(out[:, 1], out[:, 0]) - np.arctan2(pts[:, 1], pts[:, 0]))
    angle = (angle + 180) % 360 - 180
    assert np.ptp(angle) < 1e-3 and 0 < abs(angle[0]) <= 30


def test_counts_per_class_and_class_subsets():
    objset = hand_set()
    ds = ObjectClassificationDataset.from_object_set(objset, None)
    assert ds.class_counts() == {**{n: 0 for n in CLASSES}, "Car": 30, "Pedestrian": 12, "Drone": 6}
    sub = ObjectClassificationDataset.from_object_set(objset, None, class_names=["Drone", "Car"])
    assert sub.class_names == ("Drone", "Car") and sub.class_counts() == {"Drone": 6, "Car": 30}
    for j in range(len(sub)):  # renumbered in the order asked
        assert sub.class_names[sub[j]["label"]] == CLASSES[objset.samples[sub[j]["frame_id"]].label]
    with pytest.raises(ValueError, match="class_names must be distinct names of the set's classes"):
        ObjectClassificationDataset.from_object_set(objset, None, class_names=["Car", "Tram"])


@pytest.mark.parametrize("kwargs, match", [
    (dict(num_points=0), "num_points must be an int"), (dict(num_points=2.5), "num_points must be an int"),
    (dict(in_channels=5), r"clouds\[0\] must be a floating"), (dict(in_channels=2), "in_channels must be an int"),
    (dict(normalize="box"), "normalize must be one of"), (dict(seed=-1), "seed must be an int"),
    (dict(augment={"rot_z_deg": 5}), "augment must be an Augmentation"),
])
def test_bad_dataset_arguments_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ObjectClassificationDataset.from_object_set(hand_set(), None, **kwargs)


def test_bad_split_and_recipe_values_name_the_argument():
    with pytest.raises(ValueError, match="split must be 'train', 'test' or None"):
        ObjectClassificationDataset.from_object_set(hand_set(), "val")
    for kwargs, match in ((dict(scenarios={"driving_town": 3}), "unknown scenario"),
                          (dict(scenarios={"drone_lock": -1}), r"scenarios\['drone_lock'\]"),
                          (dict(scenarios={"drone_lock": 0}), "at least one scene"),
                          (dict(min_points=0), "min_points"), (dict(test_fraction=1.0), "test_fraction"),
                          (dict(fov_deg=0), "fov_deg")):
        with pytest.raises(ValueError, match=match):
            ObjectSetRecipe(**kwargs)
    with pytest.raises(ValueError, match=r"OBJECT_SET: unknown keys \['SCENE'\]"):
        ObjectSetRecipe.from_openpcdet({"SCENE": {"drone_lock": 2}})


@pytest.mark.parametrize("n, batch, world", [(9, 4, 1), (8, 4, 1), (17, 4, 2), (19, 3, 3), (33, 32, 1)])
def test_no_epoch_ends_with_a_batch_of_one_object(n, batch, world):
    from lidarops.train.data import EpochLoader

    rng = np.random.default_rng(0)
    ds = ObjectClassificationDataset([rng.normal(size=(5, 3)).astype(np.float32) for _ in range(n)], [0] * n, ["x"],
                                     num_points=4, recipe={"source": "test"})
    out = object_sets.without_single_object_batches(ds, batch, world)
    assert len(out) in (n, n - world) and (len(out) == n) == (math.ceil(n / world) % batch != 1)
    for rank in range(world):  # what the trainer deals out
        _, lengths = EpochLoader(out, batch, None, 0, 0, rank, world).epoch(0)
        assert min(lengths) >= 2, lengths
    if len(out) < n:
        assert out.recipe == {"source": "test", "subset": n - world}
        assert torch.equal(out[0]["points"], ds[0]["points"]) and out.ids.tolist() == list(range(n - world))
    with pytest.raises(ValueError, match="batch_size must be an int >= 2"):
        object_sets.without_single_object_batches(ds, 1)


def test_collate():
    ds = ObjectClassificationDataset.from_object_set(hand_set(), "test", num_points=16, in_channels=4)
    batch = collate_classification([ds[i] for i in range(3)])
    assert batch["points"].shape == (3, 16, 4) and batch["labels"].dtype == torch.int64
    assert batch["gt_label"] == batch["labels"].tolist() and batch["batch_size"] == 3
    assert batch["frame_id"] == [int(i) for i in ds.ids[:3]]
    with pytest.raises(ValueError, match="different shapes"):
        collate_classification([ds[0], {"points": torch.zeros(8, 4), "label": 0}])


# ---------------------------------------------------------------------------------------------------- simulated sets
def test_a_simulated_set_holds_its_scenarios_classes_split_by_class(tiny):
    objset, cache, _ = tiny
    labels = np.array([s.label for s in objset.samples])
    names = {CLASSES[k] for k in labels}
    assert "Drone" in names and "Car" in names and names <= set(object_sets.SCENE_CLASSES["driving_highway"]) | {"Drone"}
    assert min(s.num_points for s in objset.samples) >= TINY.min_points
    train, test = objset.train_index, objset.test_index
    assert len(np.intersect1d(train, test)) == 0 and len(train) + len(test) == len(objset)
    for k in np.unique(labels):  # stratified: each class near its share (split_balanced rounds per bin)
        n, n_test = int((labels == k).sum()), int((labels[test] == k).sum())
        if n >= 8:
            assert abs(n_test - TINY.test_fraction * n) <= 0.1 * n + 2, (CLASSES[k], n, n_test)
    info = json.loads((cache / f"objects_{TINY.key()}.json").read_text())
    assert info["counts"] == {n: int((labels == k).sum()) for k, n in enumerate(CLASSES)}
    assert sum(info["test_counts"].values()) == len(test) and info["recipe"] == TINY.to_dict()
    assert info["scenario_ranges"]["driving_highway"][0] == 0
    assert info["scenario_ranges"]["drone_lock"][1] == len(objset)


def test_the_cache_round_trips_without_simulating(tiny, monkeypatch):
    objset, cache, _ = tiny

    def no_simulation(*args):
        raise AssertionError("the cached set was simulated again")

    monkeypatch.setattr(object_sets, "_objects_of_scenes", no_simulation)
    t0 = time.perf_counter()
    again = build_object_set(TINY, cache)
    assert time.perf_counter() - t0 < 1.0
    assert len(again) == len(objset)
    assert np.array_equal(again.train_index, objset.train_index) and np.array_equal(again.test_index, objset.test_index)
    for a, b in zip(again.samples, objset.samples):
        assert a.label == b.label and np.array_equal(a.points, b.points) and np.array_equal(a.box, b.box)
    other = ObjectSetRecipe(**{**TINY.to_dict(), "min_points": 6})
    assert other.key() != TINY.key()
    with pytest.raises(AssertionError, match="simulated again"):
        build_object_set(other, cache)  # another recipe is another set


def test_a_realism_recipe_cuts_the_profiles_scenes_per_scenario():
    from lidarops.data.objects import extract_objects
    from lidarops.data.synthetic import SyntheticFrames

    recipe = ObjectSetRecipe({"driving_highway": 2, "drone_lock": 3}, seed=3, min_points=5,
                             realism={"driving_highway": "kitti", "drone_bridge": "avia"})
    # drone_bridge is not among the scenes: dropped, so the recipe (and its key) is that of highway scenes alone
    assert recipe.realism == {"driving_highway": "kitti"}
    assert recipe.profile("driving_highway") == "kitti" and recipe.profile("drone_lock") is None
    objset = build_object_set(recipe)
    want = []
    for name, profile in (("driving_highway", "kitti"), ("drone_lock", None)):
        frames = SyntheticFrames(name, num_frames=recipe.scenarios[name], seed=3, realism=profile)
        want += extract_objects((frames[i] for i in range(len(frames))), min_points=5, canonical=True)
    assert len(objset) == len(want) > 0
    for a, b in zip(objset.samples, want):
        assert a.label == b.label and np.array_equal(a.points, b.points)
    # the profile changes the returns: a ray-cast set of the same scenes holds other points
    plain = build_object_set(ObjectSetRecipe({"driving_highway": 2}, seed=3, min_points=5))
    kitti = build_object_set(ObjectSetRecipe({"driving_highway": 2}, seed=3, min_points=5, realism="kitti"))
    assert sum(s.num_points for s in plain.samples) != sum(s.num_points for s in kitti.samples)
    keys = {ObjectSetRecipe({"driving_highway": 2}, realism=r).key() for r in (None, "kitti", "kitti_dr")}
    assert len(keys) == 3
    assert ObjectSetRecipe({"driving_highway": 2}, realism={"drone_lock": "avia"}).realism is None
    cfg = ObjectSetRecipe.from_openpcdet({"SCENES": {"drone_lock": 2}, "REALISM": {"drone_lock": "avia"}})
    assert cfg.profile("drone_lock") == "avia"


@pytest.mark.parametrize("realism, match", [("kitty", "realism must be None"), ({"driving_town": "kitti"}, "unknown scenario"),
                                            ({"drone_lock": 3}, r"realism\['drone_lock'\] must be a profile name"),
                                            ({"drone_lock": "avai"}, "realism must be None"), (["kitti"], "mapping")])
def test_bad_recipe_realism_names_the_field(realism, match):
    with pytest.raises(ValueError, match=match):
        ObjectSetRecipe({"drone_lock": 2}, realism=realism)


@pytest.mark.slow
def test_worker_processes_build_the_same_set(tiny, tmp_path):
    objset, _, _ = tiny
    par = build_object_set(TINY, None, workers=2)
    assert [s.label for s in par.samples] == [s.label for s in objset.samples]
    assert all(np.array_equal(a.points, b.points) for a, b in zip(par.samples, objset.samples))
    assert np.array_equal(par.test_index, objset.test_index)


def test_datasets_from_the_shipped_config_shape(tiny):
    from lidarops.config import load_config

    objset, cache, _ = tiny
    cfg = load_config("configs/casnet/pointnet_objects.yaml")
    cfg["DATA_CONFIG"]["OBJECT_SET"] = {"SCENES": TINY.scenarios, "SEED": 3, "MIN_POINTS": 5, "TEST_FRACTION": 0.25}
    cfg["DATA_CONFIG"]["POINT_FEATURE_ENCODING"]["used_feature_list"] = ["x", "y", "z", "intensity"]
    train, test, collate = datasets_from_config(cfg, data_path=cache)
    assert len(train) == len(objset.train_index) and len(test) == len(objset.test_index)
    assert train.augment is not None and test.augment is None and train.class_names == CLASSES
    assert train[0]["points"].shape == (1024, 4) and train.recipe["key"] == TINY.key()
    batch = collate([test[i] for i in range(2)])
    assert batch["points"].shape == (2, 1024, 4)


# ---------------------------------------------------------------------------------------------------- ModelNet40
def test_modelnet40_enters_the_same_dataset(tmp_path):
    pytest.importorskip("h5py")
    from lidarops.data.formats.modelnet import write_modelnet_h5

    rng = np.random.default_rng(0)
    for split, n in (("train", 6), ("test", 3)):
        write_modelnet_h5(tmp_path / f"ply_data_{split}0.h5", rng.normal(size=(n, 2048, 3)), np.arange(n) % 2)
    (tmp_path / "shape_names.txt").write_text("airplane\nbathtub\n")
    ds = ObjectClassificationDataset.from_modelnet(tmp_path, "train", num_points=1024, augment=Augmentation())
    assert len(ds) == 6 and ds.class_names == ("airplane", "bathtub") and ds.class_counts() == {"airplane": 3,
                                                                                                 "bathtub": 3}
    item = ds[1]
    assert item["points"].shape == (1024, 3) and item["label"] == 1 and ds.recipe["source"] == "modelnet40"
    with pytest.raises(ValueError, match="in_channels must be 3 for ModelNet40"):
        ObjectClassificationDataset.from_modelnet(tmp_path, "train", in_channels=4)
    cfg = {"CLASS_NAMES": ["airplane", "bathtub"],
           "DATA_CONFIG": {"DATASET": "ModelNet40", "DATA_PATH": str(tmp_path), "NUM_POINTS": 512}}
    train, test, collate = datasets_from_config(cfg)
    assert (len(train), len(test)) == (6, 3) and collate([test[0], test[1]])["points"].shape == (2, 512, 3)
