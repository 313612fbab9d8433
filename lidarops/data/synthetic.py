"""Synthetic LiDAR: a scene simulator with per-point timestamps (NumPy; rays are cast by the native kernel
when the extension is built, see :mod:`lidarops.data._raycast`).

Example:
    >>> from lidarops.data.synthetic import Simulator
    >>> sim = Simulator("driving_city", seed=3, object_counts={"Car": 35})
    >>> frame = sim.sweep(0)                 # one 100 ms sweep of the HDL-64
    >>> points, t = sim.stream(0.0, 0.01)    # the first 10 ms, in time order

How it works: the sensor's firings are grouped in fixed blocks of ``block_duration`` seconds (20 ms
for spinning sensors, 50 ms for Risley sensors by default).  A block is a pure function of ``(scenario, seed, sensor, block index)``: its rays get the
sensor pose and the object poses at their own timestamps (motion distortion), are cast against the
scene (:mod:`lidarops.data._raycast`), and noise, dropout and intensity come from a generator seeded
by the block index.  ``sweep`` and ``stream`` only cut and concatenate blocks, so any span gives the
same points as the sweeps covering it, and ``stream(a, c)`` equals ``stream(a, b)`` followed by
``stream(b, c)``.

Points are returned in the sensor frame *at their own firing time* (as a real sensor reports them);
boxes of a :class:`~lidarops.data.frame.Frame` are in the sensor frame at the frame's reference time
(the middle of the sweep: the moment a spinning sensor faces forward).
"""
from __future__ import annotations

from collections import OrderedDict
from fractions import Fraction
from typing import Iterator

import numpy as np

from lidarops.data._checks import integer, real
from lidarops.data._raycast import cast_rays
from lidarops.data.frame import CLASSES, Frame
from lidarops.data.geometry import count_points_in_boxes, pose_matrix, wrap_angle
from lidarops.data.realism import Realism, make_realism
from lidarops.data.scenarios import CLUTTERED_SCENARIOS, SCENARIOS, SENSOR_HEIGHT, build_scenario
from lidarops.data.scene import SURFACE_KINDS, SURFACE_NONE, BoxSet, Scenario, _rng
from lidarops.data.shapes import _trace
from lidarops.data.sensors import LidarSensor, RisleyLidar, SpinningLidar, avia, hdl64, make_sensor, pandar64

__all__ = [
    "Simulator",
    "SyntheticFrames",
    "Frame",
    "CLASSES",
    "SCENARIOS",
    "SURFACE_KINDS",
    "SpinningLidar",
    "RisleyLidar",
    "hdl64",
    "pandar64",
    "avia",
    "crop_forward",
]


def crop_forward(frame: Frame, fov_deg: float = 90.0) -> Frame:
    """KITTI-like forward crop of a frame (see :meth:`Frame.crop_forward`)."""
    return frame.crop_forward(fov_deg)


#: Latest time (s) the simulator generates: a day and more of simulated time, far below where firing
#: indices (``t * firing_rate``) would leave int64 or lose their exactness in float64.
MAX_TIME = 1e6
#: Longest span of one :meth:`Simulator.stream` call (s): it is simulated and held at once.
MAX_STREAM_SPAN = 10.0


def _time(value, name: str) -> float:
    return real(value, name, 0, MAX_TIME, unit=" s")


def _times(t, name: str) -> np.ndarray:
    """float64 times, all finite (NaN would give a NaN pose and silently empty casts)."""
    try:
        arr = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers (s), got {t!r}") from None
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite times (s), got a NaN or infinite value")
    return arr


def _rotate_per_firing(rot: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``einsum("kij,krj->kri", rot, dirs)``: the rays of each firing turned by that firing's rotation.

    Written out as products and sums, 4-5x faster than ``einsum`` for these shapes; the terms are added
    in the order ``(j=0 + j=2) + j=1`` in which NumPy's einsum reduces a length-3 axis (its SIMD
    horizontal sum), so the result is bit for bit the einsum's (checked on NumPy 2.4, x86-64 AVX2).

    Args:
        rot (ndarray float64[K, 3, 3]), dirs (ndarray float64[K, R, 3]).

    Returns:
        ndarray float64[K, R, 3].
    """
    out = np.empty(dirs.shape)
    # component-major views [3, R, K]: the firing axis innermost (K is long, R is a handful of channels for
    # a Risley sensor), and each firing's matrix entry broadcasts along it
    d, o = dirs.transpose(2, 1, 0), out.transpose(2, 1, 0)
    for i in range(3):
        r = rot[:, i, :]
        np.multiply(r[:, 0], d[0], out=o[i])
        o[i] += r[:, 2] * d[2]
        o[i] += r[:, 1] * d[1]
    return out


class Simulator:
    """A LiDAR sensor moving through a procedurally generated scene.

    Args:
        scenario (str): ``"driving_city"``, ``"driving_highway"``, ``"drone_bridge"`` or ``"drone_lock"``.
        seed (int): everything (scene, objects, noise) is a function of this seed.
        sensor (str or LidarSensor or None): sensor preset name or object; ``None`` takes the scenario's
            default (``hdl64`` for driving, ``avia`` for drones).
        object_counts: objects per class: ``None`` (scenario defaults), ``"empty"``, ``"dense"``, a dict
            ``{class: int | (low, high) | callable(rng) -> int}``, or a callable ``rng -> dict``; see
            :func:`lidarops.data.scene.sample_object_counts`.
        block_duration (float or None): time granularity of the deterministic generation (s); default
            20 ms for spinning sensors and 50 ms for Risley sensors.  Results depend on it (it seeds the
            noise), not on how spans are requested.
        cache_blocks (int): how many generated blocks to keep in memory.
        realism (str or Realism or None): a real sensor's intensity response and real vehicles' surfaces
            applied to the returns (:mod:`lidarops.data.realism`; ``"kitti"``, ``"kitti_dr"``); ``None`` (default):
            as cast.
        **scenario_options: passed to the scenario builder (``ego_speed=...`` for driving scenes).

    Attributes:
        scenario (Scenario): the scene.
        sensor (LidarSensor): the sensor.
    """

    def __init__(self, scenario: str = "driving_city", seed: int = 0, sensor: "str | LidarSensor | None" = None,
                 object_counts=None, block_duration: float | None = None, cache_blocks: int = 48,
                 realism: "str | Realism | None" = None, **scenario_options) -> None:
        self._init_args = dict(scenario=scenario, seed=seed, sensor=sensor, object_counts=object_counts,
                               block_duration=block_duration, cache_blocks=cache_blocks, realism=realism,
                               **scenario_options)
        if not isinstance(scenario, str) or scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {scenario!r}: scenario must be one of {sorted(SCENARIOS)}")
        self.seed = integer(seed, "seed", 0)
        cache_blocks = integer(cache_blocks, "cache_blocks", 0)
        self.realism = make_realism(realism)
        self._intensity_scale = 1.0
        if self.realism is not None and scenario in CLUTTERED_SCENARIOS and "street_clutter" not in scenario_options:
            scenario_options = {**scenario_options, "street_clutter": self.realism.street_clutter}
        for option in ("low_clutter", "roadside_structures", "ground_slope", "ground_slope_bias"):
            if self.realism is not None and getattr(self.realism, option) and scenario in CLUTTERED_SCENARIOS \
                    and option not in scenario_options:
                scenario_options = {**scenario_options, option: getattr(self.realism, option)}
        if self.realism is not None:  # the scene's domain randomisation, from a stream of its own
            lift, self._intensity_scale = self.realism.scene_draws(_rng(self.seed, scenario, "realism", "scene"))
            if lift and scenario in CLUTTERED_SCENARIOS and "sensor_height" not in scenario_options:
                scenario_options = {**scenario_options, "sensor_height": SENSOR_HEIGHT + lift}
            for option in ("pedestrian_groups", "crossing_pedestrians", "crossing_groups", "crossing_cyclists",
                           "parking_lots", "open_ground"):
                if getattr(self.realism, option) and scenario == "driving_city" and option not in scenario_options:
                    scenario_options = {**scenario_options, option: getattr(self.realism, option)}
        self.scenario: Scenario = build_scenario(scenario, self.seed, object_counts=object_counts, **scenario_options)
        self.sensor: LidarSensor = make_sensor(sensor if sensor is not None else self.scenario.default_sensor)
        if self.realism is not None:  # the scene's sensor under the profile's domain randomisation
            self.sensor = self.realism.scene_sensor(_rng(self.seed, scenario, "realism", "sensor"), self.sensor)
        if block_duration is None:  # batch sizes that run fastest: spinning 20 ms (72 deg of azimuth), Risley 50 ms
            block_duration = 0.05 if isinstance(self.sensor, RisleyLidar) else 0.02
        # a block is generated whole: more than a second of rays at once is a memory blow-up, not a setting
        self.block_duration = real(block_duration, "block_duration", 0, 1, lo_open=True, unit=" s")
        if self.block_duration * self.sensor.firing_rate < 1:
            raise ValueError(f"block_duration must hold at least one firing (>= {1 / self.sensor.firing_rate:g} s "
                             f"for {self.sensor.name}), got {self.block_duration!r}")
        self._rate = self.sensor.firing_rate_fraction()
        self._rate_float = float(self.sensor.firing_rate)
        per_block = self._rate * Fraction(repr(self.block_duration)).limit_denominator(10**6)
        self._block_num, self._block_den = per_block.numerator, per_block.denominator
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._boxes_of: tuple | None = None  # (static primitives, their boxes + the objects)
        self._cache_blocks = int(cache_blocks)
        if self.realism is not None:  # its own random streams: frames without it stay what they were
            name = self.scenario.name
            self._beam_gain = self.realism.beam_gains(_rng(self.seed, name, "realism", "beams", self.sensor.name), 1024)
            n_obj = len(self.scenario.objects)
            labels = self.scenario.object_labels
            self._vehicle = np.isin(labels, [CLASSES.index(c) for c in self.realism.vehicle_classes if c in CLASSES])
            shaped = [c for c in self.realism.shaped_classes if c in CLASSES]
            self._shape_of = np.array([shaped.index(CLASSES[k]) if 0 <= k < len(CLASSES) and CLASSES[k] in shaped else -1
                                       for k in labels], np.int64).reshape(-1)
            self._shape_names = shaped
            self._shape_u = _rng(self.seed, name, "realism", "shape").random((n_obj, 4))
            # a pedestrian's legs, coat and shoulders (its shape's u[:, 1:]) vary by the profile's pedestrian_build
            self._shape_u[labels == CLASSES.index("Pedestrian"), 1:] *= self.realism.pedestrian_build
            self._dark = _rng(self.seed, name, "realism", "paint").random(n_obj) < self.realism.dark_paint
            self._rotors = (labels == CLASSES.index("Drone")) & ("Drone" in shaped) & (self.realism.rotor_keep < 1)
            # how far each side of a vehicle's label (length, width) sits inside its body
            self._label_inset = (self.realism.label_tightness * self._vehicle[:, None]
                                 * _rng(self.seed, name, "realism", "labels").random((n_obj, 2))
                                 if self.realism.label_tightness else None)

    def __getstate__(self) -> dict:
        # the scene holds closures (tile and material functions): pickle the arguments, rebuild on load
        return dict(self._init_args)

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state)

    # ------------------------------------------------------------------ time <-> firing index
    @property
    def frame_period(self) -> float:
        """Seconds per frame (sweep or integration window)."""
        return self.sensor.frame_period

    def firing_time(self, k: np.ndarray | int) -> np.ndarray | float:
        """Time (s) of firing ``k``."""
        return np.asarray(k, dtype=np.int64) / self._rate_float

    def _first_firing_at_or_after(self, t: float) -> int:
        k = int(np.ceil(t * self._rate_float))
        while k > 0 and (k - 1) / self._rate_float >= t:
            k -= 1
        while k / self._rate_float < t:
            k += 1
        return k

    def _block_start(self, b: int) -> int:
        return -((-b * self._block_num) // self._block_den)

    def _block_of(self, k: int) -> int:
        return (k * self._block_den) // self._block_num

    def _frame_index(self, i, name: str = "i") -> int:
        return integer(i, name, 0, int(MAX_TIME / self.frame_period))

    def frame_span(self, i: int) -> tuple[float, float]:
        """Start and end time of frame ``i`` (end exclusive)."""
        i = self._frame_index(i)
        fpf = self.sensor.firings_per_frame
        return float(self.firing_time(i * fpf)), float(self.firing_time((i + 1) * fpf))

    # ------------------------------------------------------------------ poses and boxes
    def sensor_pose(self, t: np.ndarray | float) -> np.ndarray:
        """World-from-sensor transforms.

        Args:
            t (float or ndarray float64[K]): times (s).

        Returns:
            ndarray float64[4, 4] or [K, 4, 4].
        """
        rot, pos = self.scenario.ego.pose(_times(t, "t"))
        return pose_matrix(rot, pos)

    def points_to_world(self, points: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Moves points from the sensor frame at their own time to the world frame.

        Args:
            points (ndarray[N, >=3]): sensor-frame points.
            t (ndarray float64[N]): their timestamps.

        Returns:
            ndarray float64[N, 3].
        """
        rot, pos = self.scenario.ego.pose(_times(t, "t"))
        xyz = np.asarray(points, dtype=np.float64)[:, :3]
        return np.einsum("nij,nj->ni", rot, xyz) + pos

    def object_boxes_at(self, t: float, object_index: np.ndarray | None = None, frame: str = "world") -> np.ndarray:
        """Boxes of the labelled objects at time ``t``.

        Args:
            t (float): time (s).
            object_index (ndarray int[K] or None): which objects (default all).
            frame (str): ``"world"`` or ``"sensor"`` (the sensor frame at ``t``).

        Returns:
            ndarray float64[K, 7].
        """
        t = real(t, "t", unit=" of seconds")
        boxes = self.scenario.objects.at(t)
        if object_index is not None:
            boxes = boxes[np.asarray(object_index, dtype=np.int64)]
        if frame == "world":
            return boxes
        if frame != "sensor":
            raise ValueError(f"frame must be 'world' or 'sensor', not {frame!r}")
        pose = self.sensor_pose(float(t))
        out = boxes.copy()
        out[:, :3] = (boxes[:, :3] - pose[:3, 3]) @ pose[:3, :3]
        out[:, 6] = wrap_angle(boxes[:, 6] - np.arctan2(pose[1, 0], pose[0, 0]))
        return out

    # ------------------------------------------------------------------ generation
    def _block(self, b: int) -> dict:
        cached = self._cache.get(b)
        if cached is not None:
            self._cache.move_to_end(b)
            return cached
        data = self._generate_block(b)
        self._cache[b] = data
        while len(self._cache) > self._cache_blocks:
            self._cache.popitem(last=False)
        return data

    def _generate_block(self, b: int) -> dict:
        sensor, scenario = self.sensor, self.scenario
        k0, k1 = self._block_start(b), self._block_start(b + 1)
        firing = np.arange(k0, k1, dtype=np.int64)
        t_firing = firing / self._rate_float
        dirs_sensor, ring = sensor.directions(firing)  # [K, R, 3]
        rot, pos = scenario.ego.pose(t_firing)
        n_per = dirs_sensor.shape[1]
        turning = scenario.ego.has_jitter or scenario.ego.yaw_rate != 0.0  # an attitude per firing
        if turning:
            dirs_world = _rotate_per_firing(rot, dirs_sensor).reshape(-1, 3)
            dirs_sensor = dirs_sensor.reshape(-1, 3)
        else:  # constant attitude: one matrix product
            dirs_sensor = dirs_sensor.reshape(-1, 3)
            dirs_world = dirs_sensor @ rot[0].T
        origins = np.repeat(pos, n_per, axis=0)
        samples = pos
        beam_origins = sensor.beam_origins()
        offset = beam_origins.any()
        if offset:  # lasers apart from the sensor's origin: each ray starts at its beam's, turned with the sensor
            if turning:
                turned = _rotate_per_firing(rot, np.broadcast_to(beam_origins, (rot.shape[0],) + beam_origins.shape))
            else:
                turned = np.broadcast_to(beam_origins @ rot[0].T, (pos.shape[0],) + beam_origins.shape)
            origins = origins + turned.reshape(-1, 3)
            # the origins' spread for the caster's bounds: the beams' extremes bound the rest (offsets along z)
            lo, hi = np.argmin(beam_origins[:, 2]), np.argmax(beam_origins[:, 2])
            samples = np.concatenate([pos + turned[:, lo], pos + turned[:, hi]])
        t = np.repeat(t_firing, n_per)

        max_range = sensor.max_range
        static = scenario.static_in_x_range(float(pos[:, 0].min()) - max_range, float(pos[:, 0].max()) + max_range)
        if len(scenario.objects):
            # consecutive blocks see the same static tiles: reuse the concatenation
            if self._boxes_of is None or self._boxes_of[0] is not static:
                self._boxes_of = (static, BoxSet.concat([static.boxes, scenario.objects]))
            boxes = self._boxes_of[1]
        else:
            boxes = static.boxes
        rng = _rng(self.seed, scenario.name, "block", sensor.name, b)
        hits = cast_rays(origins, dirs_world, t, scenario.ground, boxes, static.cylinders, static.ellipsoids,
                         max_range, rng, len(scenario.objects), origin_samples=samples)
        if self.realism is not None and self._shape_names:
            self._shape_objects(b, hits, origins, dirs_world, t, boxes, static, max_range)

        # only rays that hit something can return: their dropout draws and range noise, in ray order, then
        # the intensity noise of the returns kept
        hit = np.flatnonzero(hits.distance <= max_range)
        u = rng.random(hit.size, dtype=np.float32)
        range_noise = rng.standard_normal(hit.size, dtype=np.float32) * np.float32(sensor.range_noise_std)
        distance, refl, cos = hits.distance[hit], hits.reflectivity[hit], hits.cos_incidence[hit]
        # received power ~ reflectivity * (0.2 + 0.8 cos) / range^4-ish: detection range scales with its 4th root
        effective = refl * (0.2 + 0.8 * cos)
        detect_range = max_range * np.sqrt(np.sqrt(np.clip(effective / sensor.reference_reflectivity, 1e-4, 1.0)))
        rng_m = distance + range_noise
        p_drop = 1.0 - (1.0 - sensor.dropout) * (1.0 - hits.extra_dropout[hit])
        keep = (distance <= detect_range) & (rng_m >= sensor.min_range) & (rng_m <= max_range) & (u >= p_drop)
        if self.realism is not None:
            zero = self._vehicle_surfaces(b, hits, hit, keep, origins, dirs_world, t, distance)
        sel = np.flatnonzero(keep)
        idx = hit[sel]
        rng_k = rng_m[sel]
        moved = None
        if self.realism is not None and self.realism.mixed_pixels > 0:
            moved = self._mixed_pixels(b, hits.distance, idx, n_per, max_range)
            rng_k = rng_k + moved.astype(rng_k.dtype)
        intensity_noise = rng.standard_normal(idx.size, dtype=np.float32) * np.float32(sensor.intensity_noise_std)
        intensity = np.clip(
            refl[sel] * (0.3 + 0.7 * cos[sel])
            * np.exp((rng_k * (-1.0 / sensor.intensity_range_scale)).astype(np.float32))
            + intensity_noise, 0.0, 1.0)
        if self.realism is not None:
            weak = distance[sel] > self.realism.weak_from * detect_range[sel]
            intensity = self.realism.intensity(intensity, hits.surface[idx], self._beam_gain[ring[idx % n_per]],
                                               weak, zero[sel], self._intensity_scale)
        points = np.empty((idx.size, 4), dtype=np.float32)
        for c in range(3):  # per component: NumPy's loops over [n, 3] arrays are several times slower
            np.multiply(dirs_sensor[idx, c], rng_k, out=points[:, c], casting="same_kind")
            if offset and beam_origins[:, c].any():  # a return lies on its beam, which starts at the beam's origin
                points[:, c] += beam_origins[ring[idx % n_per], c].astype(np.float32)
        points[:, 3] = intensity
        return {
            "points": points,
            "t": t[idx],
            "firing": firing[idx // n_per],
            "ring": ring[idx % n_per].astype(np.int16),
            "surface": hits.surface[idx],
            # a mixed pixel lies between its object and what is behind: on neither
            "object": hits.object_index[idx] if moved is None else
            np.where(moved > 0, -1, hits.object_index[idx]).astype(hits.object_index.dtype),
            "object_rays": hits.object_rays,
            "object_visible": hits.object_visible,
            "rays": t.shape[0],
        }

    def _mixed_pixels(self, b: int, distance: np.ndarray, idx: np.ndarray, n_per: int, max_range: float) -> np.ndarray:
        """How far each return ``idx`` (rays of block ``b``, ``n_per`` to a firing) moves along its ray as a mixed
        pixel: toward the farther of its beam's neighbours one firing before and after (in the block) when that
        neighbour hit something at least ``mixed_gap`` behind it."""
        far = np.full(idx.size, -np.inf)
        for step in (-n_per, n_per):
            nb = idx + step
            d = distance[np.clip(nb, 0, distance.size - 1)]
            far = np.maximum(far, np.where((nb >= 0) & (nb < distance.size) & (d <= max_range), d, -np.inf))
        rng = _rng(self.seed, self.scenario.name, "realism", "mixed", self.sensor.name, b)
        return self.realism.mixed_ranges(rng, distance[idx], far)

    def _object_frame(self, o: np.ndarray, rays: np.ndarray, origins: np.ndarray, dirs: np.ndarray, t: np.ndarray,
                      distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays ``rays`` are at ``distance`` along them, and their directions, in the frames of objects
        ``o`` at the rays' times."""
        objects = self.scenario.objects
        centre = objects.center[o] + objects.velocity[o] * t[rays, None]
        yaw = objects.yaw[o] + objects.yaw_rate[o] * t[rays]
        c, s = np.cos(yaw), np.sin(yaw)
        rel = origins[rays] + dirs[rays] * distance[:, None] - centre
        d = dirs[rays]
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], c * rel[:, 1] - s * rel[:, 0], rel[:, 2]], 1)
        ldir = np.stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]], 1)
        return local, ldir

    def _shape_objects(self, b: int, hits, origins: np.ndarray, dirs: np.ndarray, t: np.ndarray, boxes: BoxSet,
                       static, max_range: float) -> None:
        """Follows the rays that hit a shaped object's box onto its shape (:mod:`lidarops.data.shapes`), and
        sends those that miss it on into the scene from inside the box (the caster does not see a box from
        within it), in place in ``hits``; a ray passing several shaped objects is followed up to three times.
        The objects' visibility counts stay those of their boxes: occlusion is judged by an object's outline,
        as KITTI's annotators judge it, not by the gaps between a pedestrian's legs."""
        objects, n_obj = self.scenario.objects, len(self.scenario.objects)
        todo = np.flatnonzero(hits.object_index >= 0)
        for round_ in range(3):
            todo = todo[(hits.distance[todo] <= max_range) & (self._shape_of[hits.object_index[todo]] >= 0)]
            if not todo.size:
                return
            o = hits.object_index[todo]
            local, ldir = self._object_frame(o, todo, origins, dirs, t, hits.distance[todo])
            miss = np.zeros(todo.size, bool)
            for k, name in enumerate(self._shape_names):
                g = np.flatnonzero(self._shape_of[o] == k)
                if not g.size:
                    continue
                step, on, cos = _trace(name, local[g], ldir[g], objects.half[o[g]], self._shape_u[o[g]])
                hits.distance[todo[g[on]]] += step[on]
                hits.cos_incidence[todo[g[on]]] = cos[on]
                if name == "Pedestrian" and self.realism.hair_dropout > 0:  # the head's top: hair, often dark
                    half_z = objects.half[o[g[on]], 2]
                    z = local[g[on], 2] + ldir[g[on], 2] * step[on]
                    hair = todo[g[on]][(z + half_z) > 0.87 * 2 * half_z]
                    hits.extra_dropout[hair] = np.maximum(hits.extra_dropout[hair], self.realism.hair_dropout)
                miss[g[~on]] = True
            gone = todo[miss]
            if not gone.size:
                return
            start = hits.distance[gone] + 1e-3  # just inside the box: its faces are behind
            rng = _rng(self.seed, self.scenario.name, "realism", "recast", self.sensor.name, b, round_)
            again = cast_rays(origins[gone] + dirs[gone] * start[:, None], dirs[gone], t[gone], self.scenario.ground,
                              boxes, static.cylinders, static.ellipsoids, max_range, rng, n_obj)
            far = again.distance + start > max_range
            again.distance[far], again.surface[far], again.object_index[far] = np.inf, SURFACE_NONE, -1
            hits.distance[gone] = again.distance + start
            for field in ("surface", "object_index", "cos_incidence", "reflectivity", "extra_dropout"):
                getattr(hits, field)[gone] = getattr(again, field)
            todo = gone[again.object_index >= 0]

    def _box_heights(self, o: np.ndarray, rays: np.ndarray, origins: np.ndarray, dirs: np.ndarray, t: np.ndarray,
                     distance: np.ndarray) -> np.ndarray:
        """Height fractions (0 bottom, 1 top) in the boxes of objects ``o`` of returns ``rays`` at ``distance``."""
        local, _ = self._object_frame(o, rays, origins, dirs, t, distance)
        return local[:, 2] / (2.0 * self.scenario.objects.half[o, 2]) + 0.5

    def _vehicle_surfaces(self, b: int, hits, hit: np.ndarray, keep: np.ndarray, origins: np.ndarray,
                          dirs: np.ndarray, t: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """Drops the vehicle returns that glass and round roofs lose and the drone returns that spinning rotors lose
        (``keep`` in place); returns, per hit, whether it reads zero intensity (dark paint, glass, tyres)."""
        zero = np.zeros(hit.size, bool)
        obj = hits.object_index[hit]
        v = np.flatnonzero(keep & (obj >= 0))
        v = v[self._vehicle[obj[v]]]
        if v.size:
            o = obj[v]
            height = self._box_heights(o, hit[v], origins, dirs, t, distance[v])
            rng = _rng(self.seed, self.scenario.name, "realism", "block", self.sensor.name, b)
            back, reads_zero = self.realism.vehicle_returns(rng, height, self._dark[o])
            keep[v[~back]] = False
            zero[v] = reads_zero
        r = np.flatnonzero(keep & (obj >= 0)) if self._rotors.any() else np.zeros(0, np.int64)
        r = r[self._rotors[obj[r]]]
        if r.size:  # a drone's spinning rotors: a stream of its own, so that scenes without drones stay the same
            height = self._box_heights(obj[r], hit[r], origins, dirs, t, distance[r])
            rng = _rng(self.seed, self.scenario.name, "realism", "rotors", self.sensor.name, b)
            keep[r[~self.realism.rotor_returns(rng, height)]] = False
        return zero

    def _span(self, k0: int, k1: int) -> dict:
        """Concatenated block data for firings ``[k0, k1)``."""
        if k1 <= k0:
            z = np.zeros
            n_obj = len(self.scenario.objects)
            return {"points": z((0, 4), np.float32), "t": z(0), "firing": z(0, np.int64), "ring": z(0, np.int16),
                    "surface": z(0, np.uint8), "object": z(0, np.int32), "object_rays": z(n_obj, np.int64),
                    "object_visible": z(n_obj, np.int64), "rays": 0}
        parts = [self._block(b) for b in range(self._block_of(k0), self._block_of(k1 - 1) + 1)]
        out = {key: np.concatenate([p[key] for p in parts]) for key in ("points", "t", "firing", "ring", "surface", "object")}
        sel = (out["firing"] >= k0) & (out["firing"] < k1)
        if not sel.all():
            out = {key: value[sel] for key, value in out.items()}
        out["object_rays"] = np.sum([p["object_rays"] for p in parts], axis=0)
        out["object_visible"] = np.sum([p["object_visible"] for p in parts], axis=0)
        out["rays"] = sum(p["rays"] for p in parts)
        return out

    # ------------------------------------------------------------------ public API
    def stream(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """All points with timestamps in ``[t0, t1)``, in time order.

        Args:
            t0, t1 (float): span in seconds (``0 <= t0``, at most :data:`MAX_STREAM_SPAN` long).

        Returns:
            points (ndarray float32[n, 4]): ``x, y, z, intensity``, each in the sensor frame at its time.
            t (ndarray float64[n]): timestamps (non-decreasing).
        """
        t0, t1 = _time(t0, "t0"), _time(t1, "t1")
        if t1 < t0:
            raise ValueError(f"t1 must be >= t0 (the span [t0, t1)), got t0={t0!r}, t1={t1!r}")
        if t1 - t0 > MAX_STREAM_SPAN:  # all of it is simulated and held at once: ~1.3 M points per second
            raise ValueError(f"the span [t0, t1) of stream() is at most {MAX_STREAM_SPAN:g} s, got {t1 - t0:g} s; "
                             "take a longer stream in pieces with slices(t0, t1, dt)")
        data = self._span(self._first_firing_at_or_after(t0), self._first_firing_at_or_after(t1))
        return data["points"], data["t"]

    def slices(self, t0: float, t1: float, dt: float = 0.01) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Consecutive ``stream`` slices ``[t0 + i dt, t0 + (i + 1) dt)`` up to ``t1``.

        Yields:
            (points float32[n, 4], t float64[n]) per slice.
        """
        t0, t1 = _time(t0, "t0"), _time(t1, "t1")
        if t1 < t0:
            raise ValueError(f"t1 must be >= t0 (the span [t0, t1)), got t0={t0!r}, t1={t1!r}")
        dt = real(dt, "dt", 0, lo_open=True, unit=" s")
        n = int(np.ceil((t1 - t0) / dt - 1e-9))
        for i in range(n):
            yield self.stream(t0 + i * dt, min(t0 + (i + 1) * dt, t1))

    def sweep(self, i: int) -> Frame:
        """Frame ``i``: one full revolution (spinning) or one ``frame_period`` integration (Risley).

        Args:
            i (int): frame index (>= 0); frame ``i`` covers ``[i T, (i + 1) T)``.

        Returns:
            Frame with ``points``, ``t``, ``boxes`` (sensor frame at the middle of the sweep), ``labels``,
            ``num_points_in_box``, ``object_ids``, ``velocities``, ``yaw_rates``, ``visibility``,
            ``instance``, ``surface``, ``ring`` and ``sensor_pose``.
        """
        i = self._frame_index(i)
        fpf = self.sensor.firings_per_frame
        k0, k1 = i * fpf, (i + 1) * fpf
        data = self._span(k0, k1)
        t_ref = 0.5 * (float(self.firing_time(k0)) + float(self.firing_time(k1)))
        pose = self.sensor_pose(t_ref)
        n_obj = len(self.scenario.objects)
        boxes_s = self.object_boxes_at(t_ref, frame="sensor") if n_obj else np.zeros((0, 7))
        if self.realism is not None and self._label_inset is not None and n_obj:
            boxes_s[:, 3:5] -= 2 * self._label_inset  # labels as tight as real annotators draw them
        keep = np.hypot(boxes_s[:, 0], boxes_s[:, 1]) <= self.scenario.label_range
        if isinstance(self.sensor, RisleyLidar) and n_obj:
            az = np.degrees(np.arctan2(boxes_s[:, 1], boxes_s[:, 0]))
            el = np.degrees(np.arctan2(boxes_s[:, 2], np.hypot(boxes_s[:, 0], boxes_s[:, 1])))
            keep &= (np.abs(az) <= self.sensor.fov_h_deg / 2 + 5) & (np.abs(el) <= self.sensor.fov_v_deg / 2 + 5)
        kept = np.flatnonzero(keep)
        boxes = boxes_s[kept].astype(np.float32)
        frame_index_of_object = np.full(n_obj + 1, -1, dtype=np.int32)
        frame_index_of_object[kept] = np.arange(kept.size, dtype=np.int32)
        instance = frame_index_of_object[data["object"]]  # -1 stays -1 (last entry)
        velocities = (self.scenario.objects.velocity[kept] @ pose[:3, :3]).astype(np.float32)
        with np.errstate(invalid="ignore", divide="ignore"):
            visibility = np.where(data["object_rays"][kept] > 0,
                                  data["object_visible"][kept] / np.maximum(data["object_rays"][kept], 1), np.nan)
        return Frame(
            points=data["points"],
            t=data["t"],
            boxes=boxes,
            labels=self.scenario.object_labels[kept],
            num_points_in_box=count_points_in_boxes(data["points"], boxes),
            class_names=CLASSES,
            frame_index=i,
            timestamp=t_ref,
            sensor_pose=pose,
            object_ids=kept.astype(np.int64),
            velocities=velocities,
            yaw_rates=self.scenario.objects.yaw_rate[kept].astype(np.float32),
            visibility=visibility.astype(np.float32),
            instance=instance,
            surface=data["surface"],
            ring=data["ring"],
            source=f"synthetic:{self.scenario.name}",
            meta={"scenario": self.scenario.name, "seed": self.seed, "sensor": self.sensor.name,
                  "object_counts": dict(self.scenario.object_counts), "rays": int(data["rays"])},
        )

    def frames(self, n: int, start: int = 0) -> Iterator[Frame]:
        """Yields sweeps ``start, ..., start + n - 1``."""
        n, start = integer(n, "n", 0), self._frame_index(start, "start")
        for i in range(start, start + n):
            yield self.sweep(i)

    def __repr__(self) -> str:
        return f"Simulator({self.scenario.name!r}, seed={self.seed}, sensor={self.sensor.name!r})"


class SyntheticFrames:
    """A frame source of simulated sweeps (a :class:`~lidarops.data.datasets.FrameSource`).

    Frame ``i`` is sweep ``i % frames_per_scene`` of scene ``i // frames_per_scene``; each scene is a
    :class:`Simulator` with its own seed derived from ``seed``, so ``frames_per_scene=1`` gives
    independent KITTI-like frames and larger values give sequences.

    Args:
        scenario (str): scenario name.
        num_frames (int): number of frames.
        seed (int): base seed.
        frames_per_scene (int): consecutive sweeps taken from each scene.
        sensor (str or LidarSensor or None): sensor (default: the scenario's).
        object_counts: see :class:`Simulator`.
        fov_deg (float or None): apply :meth:`Frame.crop_forward` with this opening (e.g. 90 for KITTI-like
            frames).
        **scenario_options: passed to :class:`Simulator`.
    """

    def __init__(self, scenario: str = "driving_city", num_frames: int = 100, seed: int = 0, frames_per_scene: int = 1,
                 sensor: "str | LidarSensor | None" = None, object_counts=None, fov_deg: float | None = None,
                 **scenario_options) -> None:
        if not isinstance(scenario, str) or scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {scenario!r}: scenario must be one of {sorted(SCENARIOS)}")
        num_frames, seed = integer(num_frames, "num_frames", 0), integer(seed, "seed", 0)
        frames_per_scene = integer(frames_per_scene, "frames_per_scene", 1)
        if fov_deg is not None:
            fov_deg = real(fov_deg, "fov_deg", 0, 360, lo_open=True, unit=" degrees")
        self.scenario, self.num_frames, self.seed = scenario, num_frames, seed
        self.frames_per_scene, self.sensor, self.object_counts = int(frames_per_scene), sensor, object_counts
        self.fov_deg, self.options = fov_deg, scenario_options
        self._sim: Simulator | None = None
        self._scene = -1

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_sim"], state["_scene"] = None, -1  # rebuilt on demand (e.g. in DataLoader workers)
        return state

    def scene_seed(self, scene: int) -> int:
        """Seed of scene ``scene``."""
        return self.seed * 1_000_003 + scene

    def simulator(self, scene: int) -> Simulator:
        """The simulator of scene ``scene`` (the last one is cached)."""
        if scene != self._scene or self._sim is None:
            self._sim = Simulator(self.scenario, seed=self.scene_seed(scene), sensor=self.sensor,
                                  object_counts=self.object_counts, **self.options)
            self._scene = scene
        return self._sim

    def __len__(self) -> int:
        return self.num_frames

    def __getitem__(self, i: int) -> Frame:
        if not -self.num_frames <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range ({self.num_frames} frames)")
        i %= self.num_frames
        scene, sweep = divmod(i, self.frames_per_scene)
        frame = self.simulator(scene).sweep(sweep)
        if self.fov_deg is not None:
            frame = frame.crop_forward(self.fov_deg)
        frame.frame_index = i
        frame.meta["scene"] = scene
        return frame

    def __repr__(self) -> str:
        return f"SyntheticFrames({self.scenario!r}, {self.num_frames} frames, seed={self.seed})"
