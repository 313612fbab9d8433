"""Object classification sets as a torch Dataset: the objects :mod:`lidarops.data.objects` cuts from simulated
scenes (or ModelNet40's shapes), each resampled to a fixed number of points, normalised and optionally
augmented, batched as ``points (B, N, C)`` + ``labels (B,)`` for :class:`lidarops.models.PointNet`.

The flow::

    recipe = ObjectSetRecipe({"driving_city": 400, "driving_highway": 200, "drone_bridge": 200, "drone_lock": 400})
    train = ObjectClassificationDataset.from_recipe(recipe, "train", cache_dir="data/objects", workers=8,
                                                    augment=Augmentation())
    test = ObjectClassificationDataset.from_recipe(recipe, "test", cache_dir="data/objects")
    loader = DataLoader(train, batch_size=32, collate_fn=collate_classification)

1. **Objects** (:func:`build_object_set`): scene ``i`` of each scenario is simulated once (one sweep per scene:
   two sweeps of one scene hold the same objects, which a random split would put on both sides), the points
   inside each labelled box with at least ``min_points`` points become one object in its box frame
   (:func:`~lidarops.data.objects.extract_objects` with :func:`~lidarops.data.objects.canonicalize`: centre at
   the box centre, heading along +x), and :func:`~lidarops.data.objects.split_balanced` splits them, stratified
   by class and point count. The set is cached as ``<cache_dir>/objects_<key>.npz`` (an
   :class:`~lidarops.data.objects.ObjectSet`) with a ``.json`` beside it (recipe, counts, build time); the key
   is a hash of the recipe, so a second run with the same recipe loads it in well under a second.
2. **Resampling** (:func:`resample`, deterministic: a generator seeded by ``(seed, object id)``): an object with
   more points than ``num_points`` keeps a random subset (without replacement, in scan order); one with fewer
   keeps every point once and repeats randomly drawn ones to fill the rest (repeats change neither the max pool
   of PointNet nor the set of points a sampler can pick, unlike padding with zeros).
3. **Normalisation** (:func:`normalize_cloud`): ``"unit_sphere"`` (default, the ModelNet40 convention of
   PointNet and SampleNet) moves the centroid of the object's points to the origin and scales the farthest point
   to radius 1; ``"center"`` only centres (sizes stay in metres); ``"none"`` keeps the box frame. Statistics are
   taken on all of the object's points, before resampling, so they do not depend on ``num_points``.
4. **Augmentation** (training only, :class:`Augmentation`): a small rotation about z, a scaling and a clipped
   Gaussian jitter, from a generator seeded by ``(seed, epoch, object id)``: :meth:`set_epoch`, which
   :func:`lidarops.train.fit` calls, makes every epoch's draw reproducible, resumes and workers included.

ModelNet40 (``ply_data_*.h5``, :class:`~lidarops.data.formats.ModelNet40`) enters the same Dataset through
:meth:`ObjectClassificationDataset.from_modelnet` (x, y, z only; its clouds are already upright and unit-sphere
normalised, so only the resampling, which keeps a random 1,024 of the 2,048 points, and the augmentation act).
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from lidarops.data._checks import integer, real
from lidarops.data.frame import CLASSES
from lidarops.data.objects import ObjectSample, ObjectSet, extract_objects, split_balanced

__all__ = ["ObjectSetRecipe", "Augmentation", "ObjectClassificationDataset", "build_object_set", "resample",
           "normalize_cloud", "collate_classification", "datasets_from_config", "without_single_object_batches",
           "NORMALIZE_MODES", "SCENE_CLASSES"]

NORMALIZE_MODES = ("unit_sphere", "center", "none")

#: The classes each scenario places (its default object counts, :mod:`lidarops.data.scenarios`).
SCENE_CLASSES: dict[str, tuple[str, ...]] = {
    "driving_city": ("Car", "Pedestrian", "Cyclist", "Truck", "Bus", "Barrier", "TrafficCone"),
    "driving_highway": ("Car", "Truck", "Bus", "Barrier", "TrafficCone"),
    "drone_bridge": ("Drone",),
    "drone_lock": ("Drone",),
}

# bump when the way objects are cut changes: caches of older builds are then rebuilt, not reused
_BUILD_VERSION = 1


# ------------------------------------------------------------------------------------------------ the recipe
@dataclass
class ObjectSetRecipe:
    """Which simulated scenes an object set is cut from (what its cache key hashes).

    Attributes (the YAML key under ``DATA_CONFIG.OBJECT_SET`` in brackets):
        scenarios (dict[str, int]): [SCENES] scenes per scenario (one sweep each), e.g.
            ``{"driving_city": 400, "drone_lock": 400}``; see :data:`SCENE_CLASSES` for what each gives.
        seed (int): [SEED] scene ``i`` of a scenario is ``SyntheticFrames(scenario, seed=seed)[i]``; also
            seeds the split.
        min_points (int): [MIN_POINTS] objects with fewer points are left out (>= 1).
        test_fraction (float): [TEST_FRACTION] share of each class (and point-count bin) in the test split.
        margin (float): [MARGIN] grow the boxes by this many metres when cutting.
        fov_deg (float or None): [FOV_DEG] keep only the frames' forward field of view (e.g. 90, KITTI-like).
        realism (str, dict[str, str] or None): [REALISM] the simulator's realism profile the scenes are made
            with (:mod:`lidarops.data.realism`): one profile for every scenario (``"kitti"``), or one per scenario
            (``{"driving_city": "kitti", "drone_lock": "avia"}``; a scenario left out is ray-cast, one that is
            not among ``scenarios`` is not used); None: every scene ray-cast.
    """

    scenarios: dict[str, int] = field(default_factory=lambda: {"driving_city": 400, "driving_highway": 200,
                                                               "drone_bridge": 200, "drone_lock": 400})
    seed: int = 0
    min_points: int = 10
    test_fraction: float = 0.2
    margin: float = 0.0
    fov_deg: float | None = None
    realism: str | dict[str, str] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.scenarios, Mapping) or not self.scenarios:
            raise ValueError(f"scenarios must be a non-empty mapping scenario -> number of scenes, got {self.scenarios!r}")
        unknown = sorted(k for k in self.scenarios if k not in SCENE_CLASSES)
        if unknown:
            raise ValueError(f"scenarios: unknown scenario(s) {unknown}; choose from {sorted(SCENE_CLASSES)}")
        self.scenarios = {k: integer(v, f"scenarios[{k!r}]", 0, 10**7) for k, v in self.scenarios.items()}
        if not sum(self.scenarios.values()):
            raise ValueError(f"scenarios must ask for at least one scene, got {self.scenarios}")
        self.seed = integer(self.seed, "seed", 0, 2**31 - 1)
        self.min_points = integer(self.min_points, "min_points", 1)
        self.test_fraction = real(self.test_fraction, "test_fraction", 0, 1, lo_open=True, hi_open=True)
        self.margin = real(self.margin, "margin", 0, 10)
        if self.fov_deg is not None:
            self.fov_deg = real(self.fov_deg, "fov_deg", 0, 360, lo_open=True)
        self.realism = _realism_of_recipe(self.realism, self.scenarios)

    def profile(self, scenario: str) -> str | None:
        """The realism profile the scenes of ``scenario`` are made with (None: ray-cast)."""
        if isinstance(self.realism, Mapping):
            return self.realism.get(scenario)
        return self.realism

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ObjectSetRecipe":
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"ObjectSetRecipe has no fields {unknown}; known: {sorted(known)}")
        return cls(**dict(d))

    @classmethod
    def from_openpcdet(cls, block: Mapping[str, Any]) -> "ObjectSetRecipe":
        """From ``DATA_CONFIG.OBJECT_SET`` (keys SCENES, SEED, MIN_POINTS, TEST_FRACTION, MARGIN, FOV_DEG,
        REALISM)."""
        keys = {"SCENES": "scenarios", "SEED": "seed", "MIN_POINTS": "min_points", "TEST_FRACTION": "test_fraction",
                "MARGIN": "margin", "FOV_DEG": "fov_deg", "REALISM": "realism"}
        if not isinstance(block, Mapping):
            raise ValueError(f"DATA_CONFIG.OBJECT_SET must be a mapping, got {block!r}")
        unknown = sorted(set(block) - set(keys))
        if unknown:
            raise ValueError(f"DATA_CONFIG.OBJECT_SET: unknown keys {unknown}; known: {sorted(keys)}")
        return cls(**{keys[k]: v for k, v in block.items()})

    def key(self) -> str:
        """12 hex digits naming the cached set (a hash of the recipe and the build version)."""
        fields = self.to_dict()
        if fields["realism"] is None:  # sets built before the field existed keep their key
            del fields["realism"]
        text = json.dumps({"build": _BUILD_VERSION, **fields}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


def _realism_of_recipe(realism, scenarios: Mapping[str, int]):
    """``realism`` checked: None, one profile name, or a mapping of the recipe's scenarios to profile names."""
    from lidarops.data.realism import make_realism

    if realism is None:
        return None
    if isinstance(realism, str):
        make_realism(realism)
        return realism
    if not isinstance(realism, Mapping):
        raise ValueError(f"realism must be None, a profile name or a mapping scenario -> profile name, got {realism!r}")
    unknown = sorted(k for k in realism if k not in SCENE_CLASSES)
    if unknown:
        raise ValueError(f"realism: unknown scenario(s) {unknown}; choose from {sorted(SCENE_CLASSES)}")
    out = {}
    for name, profile in realism.items():
        if profile is None or name not in scenarios:  # a config's mapping outlives a --set of fewer SCENES
            continue
        if not isinstance(profile, str):
            raise ValueError(f"realism[{name!r}] must be a profile name, got {profile!r}")
        make_realism(profile)
        out[name] = profile
    return out or None


# ------------------------------------------------------------------------------------------------ building
def _objects_of_scenes(scenario: str, seed: int, start: int, stop: int, min_points: int, margin: float,
                       fov_deg: float | None, realism: str | None = None) -> list[ObjectSample]:
    """The objects of scenes ``[start, stop)`` of one scenario (a worker's task: module level, picklable)."""
    from lidarops.data.synthetic import SyntheticFrames

    frames = SyntheticFrames(scenario, num_frames=stop, seed=seed, fov_deg=fov_deg, realism=realism)
    return extract_objects((frames[i] for i in range(start, stop)), min_points=min_points, canonical=True,
                           margin=margin)


def build_object_set(recipe: ObjectSetRecipe | Mapping, cache_dir: str | os.PathLike | None = None,
                     workers: int = 0, log: Callable[[str], None] | None = None) -> ObjectSet:
    """The object set of ``recipe``: loaded from ``cache_dir`` when built before, else simulated, cut, split
    (and saved there).

    Args:
        recipe: an :class:`ObjectSetRecipe` or a dict of its fields.
        cache_dir: folder of ``objects_<key>.npz`` and ``.json``; None builds without caching.
        workers (int): processes simulating scenes (0: this process). The result does not depend on it. The
            processes are spawned (as ``lidarops data synth`` does): a script that asks for them runs its code
            under ``if __name__ == "__main__":``.
        log: called with one line when building starts and ends (e.g. ``print``).

    Returns:
        ObjectSet: samples in scenario order then scene order, labels indexing :data:`lidarops.data.CLASSES`,
        ``train_index`` / ``test_index`` from :func:`~lidarops.data.objects.split_balanced`.
    """
    recipe = recipe if isinstance(recipe, ObjectSetRecipe) else ObjectSetRecipe.from_dict(recipe)
    workers = integer(workers, "workers", 0, 1024)
    path = Path(cache_dir) / f"objects_{recipe.key()}.npz" if cache_dir is not None else None
    if path is not None and path.is_file():
        return ObjectSet.load(path)
    t0 = time.perf_counter()
    tasks = []
    for name, n in recipe.scenarios.items():
        step = max(1, math.ceil(n / (4 * workers))) if workers else max(n, 1)
        tasks += [(name, recipe.seed, a, min(a + step, n), recipe.min_points, recipe.margin, recipe.fov_deg,
                   recipe.profile(name)) for a in range(0, n, step)]
    if log:
        scenes = ", ".join(f"{k} {v}" + (f" [{recipe.profile(k)}]" if recipe.profile(k) else "")
                           for k, v in recipe.scenarios.items())
        log(f"object set {recipe.key()}: simulating {sum(recipe.scenarios.values())} scenes ({scenes}) with "
            f"{workers or 1} process(es)")
    if workers:
        # spawn: forking a process that holds torch's thread pools can hang the children
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            parts = list(pool.map(_objects_of_scenes, *zip(*tasks)))
    else:
        parts = [_objects_of_scenes(*t) for t in tasks]
    samples = [s for part in parts for s in part]
    ranges, start = {}, 0
    for name in recipe.scenarios:
        count = sum(len(p) for p, t in zip(parts, tasks) if t[0] == name)
        ranges[name] = [start, start + count]
        start += count
    if samples:
        train, test = split_balanced(samples, recipe.test_fraction, recipe.seed)
    else:
        train = test = np.zeros(0, np.int64)
    objset = ObjectSet(samples, CLASSES, train, test)
    seconds = time.perf_counter() - t0
    if log:
        log(f"object set {recipe.key()}: {len(samples)} objects in {seconds:.1f} s ({_counts_text(objset)})")
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")  # atomic: a killed build leaves no half file
        try:
            objset.save(tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        info = {"key": recipe.key(), "recipe": recipe.to_dict(), "build_version": _BUILD_VERSION,
                "build_seconds": round(seconds, 2), "workers": workers, "num_objects": len(samples),
                "class_names": list(CLASSES), "counts": _counts(objset, None),
                "train_counts": _counts(objset, objset.train_index), "test_counts": _counts(objset, objset.test_index),
                "scenario_ranges": ranges}
        path.with_suffix(".json").write_text(json.dumps(info, indent=2) + "\n")
    return objset


def _counts(objset: ObjectSet, index: np.ndarray | None) -> dict[str, int]:
    labels = np.array([s.label for s in objset.samples], np.int64)
    if index is not None:
        labels = labels[index]
    return {name: int((labels == k).sum()) for k, name in enumerate(objset.class_names)}


def _counts_text(objset: ObjectSet) -> str:
    return ", ".join(f"{k} {v}" for k, v in _counts(objset, None).items() if v)


# ------------------------------------------------------------------------------------------------ per cloud
def resample(points: np.ndarray, num_points: int, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``num_points`` rows of ``points``: a random subset in the original order when there are more,
    every row once then rows drawn with replacement when there are fewer (the copies are appended).

    Args:
        points (ndarray[P, C]): P >= 1.
        num_points (int): >= 1.
        rng (Generator): the source of randomness (seed it for a deterministic result).
    """
    p = points.shape[0]
    if p == 0:
        raise ValueError("points is empty: an object needs at least one point to be resampled")
    if p >= num_points:
        return points[np.sort(rng.choice(p, size=num_points, replace=False))]
    return np.concatenate([points, points[rng.integers(0, p, size=num_points - p)]])


def normalize_cloud(points: np.ndarray, mode: str = "unit_sphere") -> np.ndarray:
    """``points`` (ndarray float32[P, C]) with x, y, z centred at their centroid (``"center"``) and scaled so the
    farthest point lies at radius 1 (``"unit_sphere"``; a cloud of one location stays at the origin), or
    unchanged (``"none"``); other columns are kept. Returns a new float32 array."""
    out = np.array(points, dtype=np.float32, copy=True)
    if mode == "none" or out.shape[0] == 0:
        return out
    xyz = out[:, :3].astype(np.float64)
    xyz -= xyz.mean(axis=0)
    if mode == "unit_sphere":
        radius = float(np.sqrt((xyz ** 2).sum(axis=1)).max())
        if radius > 0:
            xyz /= radius
    out[:, :3] = xyz
    return out


@dataclass
class Augmentation:
    """Training augmentation of one normalised cloud (x, y, z; other columns untouched), in this order:

    Attributes (YAML keys under ``DATA_CONFIG.AUGMENT``):
        rot_z_deg (float): [ROT_Z_DEG] rotation about z, uniform in ``[-rot_z_deg, rot_z_deg]`` degrees. Ours:
            small (10), since the heading is canonical; PointNet rotates ModelNet shapes by any angle.
        scale_range (tuple[float, float]): [SCALE_RANGE] one uniform factor for x, y, z (PointNet++'s 0.8-1.25).
        jitter_sigma, jitter_clip (float): [JITTER_SIGMA, JITTER_CLIP] Gaussian noise per coordinate, clipped
            (PointNet's 0.01 and 0.05).
    """

    rot_z_deg: float = 10.0
    scale_range: tuple[float, float] = (0.8, 1.25)
    jitter_sigma: float = 0.01
    jitter_clip: float = 0.05

    def __post_init__(self) -> None:
        self.rot_z_deg = real(self.rot_z_deg, "rot_z_deg", 0, 180)
        try:
            lo, hi = self.scale_range
        except (TypeError, ValueError):
            raise ValueError(f"scale_range must be two numbers (low, high), got {self.scale_range!r}") from None
        lo, hi = real(lo, "scale_range[0]", 0, 100, lo_open=True), real(hi, "scale_range[1]", 0, 100, lo_open=True)
        if lo > hi:
            raise ValueError(f"scale_range must be (low, high) with low <= high, got {self.scale_range!r}")
        self.scale_range = (lo, hi)
        self.jitter_sigma = real(self.jitter_sigma, "jitter_sigma", 0, 10)
        self.jitter_clip = real(self.jitter_clip, "jitter_clip", 0, 10)

    @classmethod
    def from_openpcdet(cls, block: Mapping[str, Any] | None) -> "Augmentation | None":
        """From ``DATA_CONFIG.AUGMENT`` (None or ``{}``: no augmentation)."""
        if not block:
            return None
        keys = {"ROT_Z_DEG": "rot_z_deg", "SCALE_RANGE": "scale_range", "JITTER_SIGMA": "jitter_sigma",
                "JITTER_CLIP": "jitter_clip"}
        if not isinstance(block, Mapping):
            raise ValueError(f"DATA_CONFIG.AUGMENT must be a mapping, got {block!r}")
        unknown = sorted(set(block) - set(keys))
        if unknown:
            raise ValueError(f"DATA_CONFIG.AUGMENT: unknown keys {unknown}; known: {sorted(keys)}")
        return cls(**{keys[k]: (tuple(v) if k == "SCALE_RANGE" and isinstance(v, list) else v)
                      for k, v in block.items()})

    def __call__(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = np.array(points, dtype=np.float32, copy=True)
        a = np.radians(rng.uniform(-self.rot_z_deg, self.rot_z_deg))
        c, s = np.cos(a), np.sin(a)
        x, y = out[:, 0].copy(), out[:, 1].copy()
        out[:, 0], out[:, 1] = c * x - s * y, s * x + c * y
        out[:, :3] *= rng.uniform(*self.scale_range)
        if self.jitter_sigma > 0:
            noise = rng.normal(0.0, self.jitter_sigma, size=(out.shape[0], 3))
            out[:, :3] += np.clip(noise, -self.jitter_clip, self.jitter_clip)
        return out


# ------------------------------------------------------------------------------------------------ the Dataset
class ObjectClassificationDataset(Dataset):
    """Fixed-size object clouds with class labels.

    Items are dicts ``{"points": Tensor float32[num_points, in_channels], "label": int, "frame_id": int}``
    (``frame_id``: the object's id in its source set, which also seeds its resampling); batch them with
    :func:`collate_classification`.

    Args:
        clouds (sequence of ndarray[P_i, >= in_channels]): the objects (x, y, z first), P_i >= 1.
        labels (sequence of int): 0-based into ``class_names``.
        class_names (sequence of str): the classes, in label order.
        ids (sequence of int or None): each object's id in its source (default 0, 1, ...).
        num_points (int): points per item (1,024 or 2,048 in the papers).
        in_channels (int): columns kept: 3 (x, y, z) or more (4: intensity too).
        normalize (str): one of :data:`NORMALIZE_MODES`.
        augment (Augmentation or None): training augmentation (None: off, for test sets).
        seed (int): seeds resampling (``(seed, id)``) and augmentation (``(seed, epoch, id)``).
        recipe (dict or None): where the clouds came from (a plain dict, written into checkpoints).
    """

    def __init__(self, clouds: Sequence[np.ndarray], labels: Sequence[int], class_names: Sequence[str],
                 ids: Sequence[int] | None = None, num_points: int = 1024, in_channels: int = 3,
                 normalize: str = "unit_sphere", augment: Augmentation | None = None, seed: int = 0,
                 recipe: Mapping[str, Any] | None = None) -> None:
        self.num_points = integer(num_points, "num_points", 1, 1 << 20)
        self.in_channels = integer(in_channels, "in_channels", 3, 1024)
        self.seed = integer(seed, "seed", 0, 2**63 - 1)
        if normalize not in NORMALIZE_MODES:
            raise ValueError(f"normalize must be one of {NORMALIZE_MODES}, got {normalize!r}")
        self.normalize = normalize
        if augment is not None and not isinstance(augment, Augmentation):
            raise ValueError(f"augment must be an Augmentation or None, got {type(augment).__name__}")
        self.augment = augment
        if isinstance(class_names, str) or not class_names or not all(isinstance(n, str) for n in class_names):
            raise ValueError(f"class_names must be a non-empty list of names, got {class_names!r}")
        self.class_names = tuple(class_names)
        self.clouds = list(clouds)
        self.labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        self.ids = np.arange(len(self.clouds), dtype=np.int64) if ids is None else np.asarray(ids, np.int64).reshape(-1)
        if len(self.labels) != len(self.clouds) or len(self.ids) != len(self.clouds):
            raise ValueError(f"clouds, labels and ids must have one entry per object, got {len(self.clouds)}, "
                             f"{len(self.labels)} and {len(self.ids)}")
        bad = np.flatnonzero((self.labels < 0) | (self.labels >= len(self.class_names)))
        if bad.size:
            raise ValueError(f"labels must be in [0, {len(self.class_names)}) (class_names {list(self.class_names)}); "
                             f"label {int(self.labels[bad[0]])} at object {int(bad[0])}")
        for i, c in enumerate(self.clouds):
            if not isinstance(c, np.ndarray) or c.ndim != 2 or c.shape[0] < 1 or c.shape[1] < self.in_channels \
                    or c.dtype.kind != "f":
                what = f"shape {c.shape}, dtype {c.dtype}" if isinstance(c, np.ndarray) else type(c).__name__
                raise ValueError(f"clouds[{i}] must be a floating (P >= 1, >= in_channels = {self.in_channels}) array, "
                                 f"got {what}")
        self.recipe = dict(recipe) if recipe is not None else None
        self.epoch = 0

    # ---- sources
    @classmethod
    def from_object_set(cls, objset: ObjectSet, split: str | None = None, class_names: Sequence[str] | None = None,
                        **kwargs: Any) -> "ObjectClassificationDataset":
        """The objects of an :class:`~lidarops.data.objects.ObjectSet` (its ``"train"`` or ``"test"`` split, or
        all with None). With ``class_names`` (a subset of the set's classes, in the order wanted), labels are
        renumbered in that order and objects of other classes left out. ``kwargs`` go to the constructor."""
        if split is None:
            index = np.arange(len(objset), dtype=np.int64)
        elif split in ("train", "test"):
            index = np.asarray(objset.train_index if split == "train" else objset.test_index, np.int64)
        else:
            raise ValueError(f"split must be 'train', 'test' or None, got {split!r}")
        source = tuple(objset.class_names)
        names = source if class_names is None else tuple(class_names)
        unknown = [n for n in names if n not in source]
        if unknown or isinstance(class_names, str) or len(set(names)) != len(names):
            raise ValueError(f"class_names must be distinct names of the set's classes {list(source)}, got "
                             f"{list(names) if not isinstance(class_names, str) else class_names!r}")
        remap = np.array([names.index(n) if n in names else -1 for n in source], np.int64)
        labels = remap[np.array([objset.samples[i].label for i in index], np.int64)] if len(index) else \
            np.zeros(0, np.int64)
        keep = index[labels >= 0]
        return cls([objset.samples[i].points for i in keep], labels[labels >= 0], names, ids=keep, **kwargs)

    @classmethod
    def from_recipe(cls, recipe: ObjectSetRecipe | Mapping, split: str | None = None,
                    cache_dir: str | os.PathLike | None = None, workers: int = 0,
                    class_names: Sequence[str] | None = None, log: Callable[[str], None] | None = None,
                    **kwargs: Any) -> "ObjectClassificationDataset":
        """The objects of simulated scenes (:func:`build_object_set`, cached in ``cache_dir``)."""
        recipe = recipe if isinstance(recipe, ObjectSetRecipe) else ObjectSetRecipe.from_dict(recipe)
        return cls._of_recipe(build_object_set(recipe, cache_dir, workers, log), recipe, split, class_names, **kwargs)

    @classmethod
    def _of_recipe(cls, objset: ObjectSet, recipe: ObjectSetRecipe, split: str | None,
                   class_names: Sequence[str] | None, **kwargs: Any) -> "ObjectClassificationDataset":
        ds = cls.from_object_set(objset, split, class_names, **kwargs)
        ds.recipe = {"source": "simulator", "key": recipe.key(), "split": split, **recipe.to_dict(),
                     **ds._sample_recipe()}
        return ds

    @classmethod
    def from_modelnet(cls, path: str | os.PathLike, split: str = "train", **kwargs: Any) -> "ObjectClassificationDataset":
        """ModelNet40 shapes (a ``ply_data_*.h5`` file or a folder of them, :class:`~lidarops.data.formats.ModelNet40`);
        ``in_channels`` must be 3 (x, y, z)."""
        from lidarops.data.formats.modelnet import ModelNet40

        if kwargs.get("in_channels", 3) != 3:
            raise ValueError(f"in_channels must be 3 for ModelNet40 (x, y, z only), got {kwargs['in_channels']!r}")
        shapes = ModelNet40(path, split=split)
        ds = cls(list(shapes.points), shapes.labels, shapes.class_names, **kwargs)
        ds.recipe = {"source": "modelnet40", "path": str(path), "split": split, **ds._sample_recipe()}
        return ds

    def _sample_recipe(self) -> dict[str, Any]:
        aug = asdict(self.augment) if self.augment is not None else None
        if aug is not None:
            aug["scale_range"] = list(aug["scale_range"])
        return {"num_points": self.num_points, "in_channels": self.in_channels, "normalize": self.normalize,
                "augment": aug, "sample_seed": self.seed, "class_names": list(self.class_names)}

    # ---- the Dataset
    def set_epoch(self, epoch: int) -> None:
        """The epoch whose augmentation :meth:`__getitem__` draws (the trainer calls it before each epoch)."""
        self.epoch = integer(epoch, "epoch", 0)

    def __len__(self) -> int:
        return len(self.clouds)

    def cloud(self, i: int, epoch: int | None = None) -> np.ndarray:
        """Object ``i`` resampled, normalised and (with ``augment``) augmented: float32[num_points, in_channels]."""
        oid = int(self.ids[i])
        pts = normalize_cloud(self.clouds[i][:, :self.in_channels], self.normalize)
        pts = resample(pts, self.num_points, np.random.default_rng((self.seed, oid)))
        if self.augment is not None:
            pts = self.augment(pts, np.random.default_rng((self.seed, self.epoch if epoch is None else epoch, oid)))
        return np.ascontiguousarray(pts, dtype=np.float32)

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"object {i} out of range ({len(self)} objects)")
        i %= len(self)
        return {"points": torch.from_numpy(self.cloud(i)), "label": int(self.labels[i]), "frame_id": int(self.ids[i])}

    def subset(self, index: Sequence[int] | np.ndarray) -> "ObjectClassificationDataset":
        """The objects at positions ``index`` of this dataset, with the same settings (an object keeps its id,
        hence its cloud) and the recipe noting the subset's size."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        if index.size and not (((index >= 0) & (index < len(self))).all()):
            raise ValueError(f"index must hold positions in [0, {len(self)}), got {index[:8].tolist()}")
        ds = copy.copy(self)
        ds.clouds = [self.clouds[i] for i in index]
        ds.labels, ds.ids = self.labels[index], self.ids[index]
        ds.recipe = {**self.recipe, "subset": int(index.size)} if self.recipe is not None else None
        return ds

    def class_counts(self) -> dict[str, int]:
        """Objects per class."""
        return {name: int((self.labels == k).sum()) for k, name in enumerate(self.class_names)}

    def __repr__(self) -> str:
        counts = ", ".join(f"{k} {v}" for k, v in self.class_counts().items() if v)
        return f"ObjectClassificationDataset({len(self)} objects x {self.num_points} points: {counts})"


def without_single_object_batches(dataset: ObjectClassificationDataset, batch_size: int,
                                  world_size: int = 1) -> ObjectClassificationDataset:
    """``dataset``, or all of it but its last ``world_size`` objects when :func:`lidarops.train.fit` would
    otherwise end each epoch with a batch of one object on a process (``DistributedSampler`` deals
    ``ceil(len / world_size)`` objects to each, in batches of ``batch_size``, the last one short): PointNet's
    BatchNorm cannot train on one object. The trainer keeps every last batch (no ``drop_last``)."""
    batch_size = integer(batch_size, "batch_size", 2)
    world_size = integer(world_size, "world_size", 1)
    n = len(dataset)
    if math.ceil(n / world_size) % batch_size != 1 or n <= world_size:
        return dataset
    return dataset.subset(np.arange(n - world_size))


def collate_classification(items: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Batches items of :class:`ObjectClassificationDataset`.

    Returns:
        dict: ``points (Tensor float32[B, N, C])``, ``labels (Tensor int64[B])``, ``batch_size`` (int), and the
        per-object lists ``frame_id`` and ``gt_label`` (the labels again, as ints: what the trainer hands to an
        evaluator as each object's metadata, e.g. :class:`lidarops.eval.classification.ClassificationEvaluator`).
    """
    items = list(items)
    if not items:
        raise ValueError("items is empty: a batch needs at least one object")
    sizes = {tuple(it["points"].shape) for it in items}
    if len(sizes) != 1:
        raise ValueError(f"items hold clouds of different shapes {sorted(sizes)}: resample them to one num_points")
    labels = [int(it["label"]) for it in items]
    return {"points": torch.stack([torch.as_tensor(it["points"], dtype=torch.float32) for it in items]),
            "labels": torch.tensor(labels, dtype=torch.int64), "batch_size": len(items),
            "frame_id": [it.get("frame_id") for it in items], "gt_label": labels}


# ------------------------------------------------------------------------------------------------ from a config
def datasets_from_config(cfg: Mapping[str, Any], data_path: str | os.PathLike | None = None, workers: int = 0,
                         log: Callable[[str], None] | None = None, batch_size: int | None = None,
                         world_size: int = 1):
    """The training set (augmented), the test set and the collate function a whole config describes.

    ``DATA_CONFIG`` keys: ``DATASET`` (``SimObjects``: objects of simulated scenes, cached in ``DATA_PATH``; or
    ``ModelNet40``: the ``ply_data_*.h5`` in ``DATA_PATH``), ``DATA_PATH`` (``data_path`` wins), ``OBJECT_SET``
    (:meth:`ObjectSetRecipe.from_openpcdet`), ``NUM_POINTS``, ``NORMALIZE``, ``SAMPLE_SEED``, ``AUGMENT``
    (:meth:`Augmentation.from_openpcdet`), ``POINT_FEATURE_ENCODING.used_feature_list`` (x, y, z[, intensity]);
    ``CLASS_NAMES`` the classes in label order. With ``batch_size`` (per process) and ``world_size``, the
    training set is trimmed by :func:`without_single_object_batches`.

    Returns:
        (train set, test set, :func:`collate_classification`).
    """
    data = cfg.get("DATA_CONFIG") if isinstance(cfg, Mapping) else None
    if not isinstance(data, Mapping):
        raise ValueError("the config has no DATA_CONFIG mapping")
    used = (data.get("POINT_FEATURE_ENCODING") or {}).get("used_feature_list", ["x", "y", "z"])
    if not isinstance(used, list) or used[:3] != ["x", "y", "z"] or not set(used[3:]) <= {"intensity"} \
            or len(set(used)) != len(used):
        raise ValueError(f"DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list must be [x, y, z] or "
                         f"[x, y, z, intensity], got {used!r}")
    common = dict(num_points=data.get("NUM_POINTS", 1024), in_channels=len(used),
                  normalize=data.get("NORMALIZE", "unit_sphere"), seed=data.get("SAMPLE_SEED", 0))
    augment = Augmentation.from_openpcdet(data.get("AUGMENT"))
    path = data_path if data_path is not None else data.get("DATA_PATH")
    kind = data.get("DATASET", "SimObjects")
    names = cfg.get("CLASS_NAMES")
    if kind == "ModelNet40":
        if path is None:
            raise ValueError("DATA_CONFIG.DATA_PATH (or data_path) must name the ModelNet40 folder")
        train = ObjectClassificationDataset.from_modelnet(path, "train", augment=augment, **common)
        test = ObjectClassificationDataset.from_modelnet(path, "test", **common)
        if names is not None and list(names) != list(train.class_names):
            raise ValueError(f"CLASS_NAMES must be ModelNet40's classes in label order ({len(train.class_names)}), "
                             f"got {list(names)[:5]}...")
    elif kind == "SimObjects":
        recipe = ObjectSetRecipe.from_openpcdet(data.get("OBJECT_SET", {}))
        objset = build_object_set(recipe, path, workers, log)
        train = ObjectClassificationDataset._of_recipe(objset, recipe, "train", names, augment=augment, **common)
        test = ObjectClassificationDataset._of_recipe(objset, recipe, "test", names, **common)
    else:
        raise ValueError(f"DATA_CONFIG.DATASET must be 'SimObjects' or 'ModelNet40', got {kind!r}")
    if batch_size is not None:
        trimmed = without_single_object_batches(train, batch_size, world_size)
        if log and len(trimmed) != len(train):
            log(f"left out the last {len(train) - len(trimmed)} training object(s): no batch of one object")
        train = trimmed
    return train, test, collate_classification
