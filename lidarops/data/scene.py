"""Scene description for the simulator: ground, static primitives, moving labelled objects and ego
motion (NumPy only). The four scenario presets built from them are in :mod:`lidarops.data.scenarios`
(``SCENARIOS``, ``build_scenario`` and ``sample_object_counts`` stay importable from here).

World frame: x east/forward along the road, y left, z up (metres).  Everything random is drawn from
generators seeded by ``(seed, scenario, purpose, index)``, so a scene is a pure function of its seed.

Static structures are generated in tiles along x (``tile_length`` metres), lazily, so a car can drive
for as long as you like (:class:`Scenario` caches them).
"""
from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from lidarops._lazy import lazy_attributes
from lidarops._moved import renamed_kwargs
from lidarops.data.geometry import euler_to_matrix

__all__ = [
    "SURFACE_KINDS",
    "SURFACE_NONE",
    "SURFACE_GROUND",
    "SURFACE_STRUCTURE",
    "SURFACE_POLE",
    "SURFACE_VEGETATION",
    "SURFACE_OBJECT",
    "CLASS_SIZE_STATS",
    "BoxSet",
    "CylinderSet",
    "EllipsoidSet",
    "StaticPrimitives",
    "Ground",
    "EgoMotion",
    "Scenario",
    "SCENARIOS",
    "build_scenario",
    "sample_object_counts",
]

SURFACE_NONE, SURFACE_GROUND, SURFACE_STRUCTURE, SURFACE_POLE, SURFACE_VEGETATION, SURFACE_OBJECT = range(6)
#: Names of the ``Frame.surface`` codes.
SURFACE_KINDS = ("none", "ground", "structure", "pole", "vegetation", "object")

#: Size statistics per class: mean and standard deviation of (dx length, dy width, dz height) in
#: metres (KITTI for Car/Pedestrian/Cyclist, nuScenes for Truck/Bus/Barrier/TrafficCone, a small
#: multirotor for Drone).  Sizes are drawn from normals truncated at 2 sigma.
CLASS_SIZE_STATS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "Car": ((3.89, 1.62, 1.53), (0.43, 0.10, 0.14)),
    "Pedestrian": ((0.84, 0.66, 1.76), (0.23, 0.14, 0.11)),
    "Cyclist": ((1.76, 0.60, 1.74), (0.18, 0.12, 0.09)),
    "Truck": ((6.93, 2.51, 2.84), (1.80, 0.25, 0.50)),
    "Bus": ((10.9, 2.94, 3.47), (1.20, 0.12, 0.25)),
    "Barrier": ((2.53, 0.50, 0.98), (0.30, 0.10, 0.10)),
    "TrafficCone": ((0.41, 0.41, 1.07), (0.06, 0.06, 0.15)),
    "Drone": ((0.70, 0.70, 0.30), (0.08, 0.08, 0.04)),
}

#: Reflectivity range (uniform) per class at 905 nm.
CLASS_REFLECTIVITY: dict[str, tuple[float, float]] = {
    "Car": (0.05, 0.7),
    "Pedestrian": (0.15, 0.5),
    "Cyclist": (0.15, 0.5),
    "Truck": (0.2, 0.6),
    "Bus": (0.2, 0.6),
    "Barrier": (0.3, 0.6),
    "TrafficCone": (0.5, 0.9),
    "Drone": (0.1, 0.4),
}


# ---------------------------------------------------------------------------------------------
# primitive sets (structure of arrays)
# ---------------------------------------------------------------------------------------------
@dataclass
class BoxSet:
    """Upright oriented boxes, possibly moving: at time ``t`` box ``j`` has centre
    ``center[j] + velocity[j] * t`` and yaw ``yaw[j] + yaw_rate[j] * t``.

    Attributes:
        center (float64[K, 3]), half (float64[K, 3]: half sizes), yaw (float64[K]),
        velocity (float64[K, 3]), yaw_rate (float64[K]), reflectivity (float64[K]),
        kind (uint8[K]: surface code), object_index (int32[K]: labelled object, -1 for static).
    """

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    velocity: np.ndarray
    yaw_rate: np.ndarray
    reflectivity: np.ndarray
    kind: np.ndarray
    object_index: np.ndarray

    @staticmethod
    def empty() -> "BoxSet":
        z = np.zeros
        return BoxSet(z((0, 3)), z((0, 3)), z(0), z((0, 3)), z(0), z(0), z(0, np.uint8), z(0, np.int32))

    def __len__(self) -> int:
        return int(self.center.shape[0])

    @staticmethod
    def concat(sets: Sequence["BoxSet"]) -> "BoxSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return BoxSet.empty()
        return BoxSet(*(np.concatenate([getattr(s, f.name) for s in sets]) for f in dataclasses.fields(BoxSet)))

    def at(self, t: float) -> np.ndarray:
        """Boxes at time ``t`` as ``float64[K, 7]`` (x, y, z, dx, dy, dz, heading)."""
        out = np.empty((len(self), 7))
        out[:, :3] = self.center + self.velocity * t
        out[:, 3:6] = 2.0 * self.half
        out[:, 6] = self.yaw + self.yaw_rate * t
        return out

    def as_boxes(self) -> np.ndarray:
        """Boxes at time 0, ``float64[K, 7]``."""
        return self.at(0.0)


@dataclass
class CylinderSet:
    """Static vertical cylinders (poles, trunks, pillars).

    Attributes:
        center_xy (float64[K, 2]), z_min, z_max, radius, reflectivity (float64[K]), kind (uint8[K]).
    """

    center_xy: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    radius: np.ndarray
    reflectivity: np.ndarray
    kind: np.ndarray

    @staticmethod
    def empty() -> "CylinderSet":
        z = np.zeros
        return CylinderSet(z((0, 2)), z(0), z(0), z(0), z(0), z(0, np.uint8))

    def __len__(self) -> int:
        return int(self.center_xy.shape[0])

    @staticmethod
    def concat(sets: Sequence["CylinderSet"]) -> "CylinderSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return CylinderSet.empty()
        return CylinderSet(*(np.concatenate([getattr(s, f.name) for s in sets]) for f in dataclasses.fields(CylinderSet)))


@dataclass
class EllipsoidSet:
    """Static axis-aligned ellipsoids of foliage: a ray entering one travels an exponentially
    distributed distance (mean ``mean_free_path``) before it returns, or passes through.

    Attributes:
        center (float64[K, 3]), radii (float64[K, 3]), mean_free_path, reflectivity (float64[K]).
    """

    center: np.ndarray
    radii: np.ndarray
    mean_free_path: np.ndarray
    reflectivity: np.ndarray

    @staticmethod
    def empty() -> "EllipsoidSet":
        z = np.zeros
        return EllipsoidSet(z((0, 3)), z((0, 3)), z(0), z(0))

    def __len__(self) -> int:
        return int(self.center.shape[0])

    @staticmethod
    def concat(sets: Sequence["EllipsoidSet"]) -> "EllipsoidSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return EllipsoidSet.empty()
        return EllipsoidSet(*(np.concatenate([getattr(s, f.name) for s in sets]) for f in dataclasses.fields(EllipsoidSet)))


@dataclass
class StaticPrimitives:
    """The static part of a scene: boxes, cylinders and foliage ellipsoids."""

    boxes: BoxSet = field(default_factory=BoxSet.empty)
    cylinders: CylinderSet = field(default_factory=CylinderSet.empty)
    ellipsoids: EllipsoidSet = field(default_factory=EllipsoidSet.empty)

    @staticmethod
    def concat(parts: Sequence["StaticPrimitives"]) -> "StaticPrimitives":
        return StaticPrimitives(
            BoxSet.concat([p.boxes for p in parts]),
            CylinderSet.concat([p.cylinders for p in parts]),
            EllipsoidSet.concat([p.ellipsoids for p in parts]),
        )


class _StaticBuilder:
    """Collects static primitives as Python lists, then packs them into arrays."""

    def __init__(self, ground: "Ground") -> None:
        self.ground = ground
        self.boxes: list[tuple] = []
        self.cylinders: list[tuple] = []
        self.ellipsoids: list[tuple] = []

    @renamed_kwargs(yaw="heading")
    def box(self, cx, cy, cz, dx, dy, dz, heading=0.0, refl=0.3, kind=SURFACE_STRUCTURE, piece=10.0) -> None:
        """An upright box; ``piece`` is the longest side of the pieces it is cut into for culling."""
        self.boxes.append((cx, cy, cz, dx / 2, dy / 2, dz / 2, heading, refl, kind, piece))

    @renamed_kwargs(yaw="heading")
    def box_on_ground(self, cx, cy, dx, dy, height, heading=0.0, refl=0.3, kind=SURFACE_STRUCTURE, bury=0.5,
                      lift=0.0) -> None:
        """A box standing on the ground, its base buried ``bury`` below the lowest corner (or floating
        ``lift`` above the ground when ``lift > 0``)."""
        c, s = np.cos(heading), np.sin(heading)
        xs = cx + np.array([1, -1, -1, 1]) * dx / 2 * c - np.array([1, 1, -1, -1]) * dy / 2 * s
        ys = cy + np.array([1, -1, -1, 1]) * dx / 2 * s + np.array([1, 1, -1, -1]) * dy / 2 * c
        heights = self.ground.height(xs, ys)
        if lift > 0:
            bottom = float(heights.max()) + lift
            top = bottom + height
        else:
            bottom = float(heights.min()) - bury
            top = float(heights.max()) + height
        self.box(cx, cy, (bottom + top) / 2, dx, dy, top - bottom, heading, refl, kind)

    def cylinder(self, cx, cy, radius, height, refl=0.3, kind=SURFACE_POLE, base=None) -> None:
        z0 = float(self.ground.height(np.array([cx]), np.array([cy]))[0]) - 0.3 if base is None else base
        self.cylinders.append((cx, cy, z0, z0 + height + (0.3 if base is None else 0.0), radius, refl, kind))

    def ellipsoid(self, cx, cy, cz, rx, ry, rz, refl=0.5, mean_free_path=0.35) -> None:
        self.ellipsoids.append((cx, cy, cz, rx, ry, rz, mean_free_path, refl))

    def tree(self, rng: np.random.Generator, cx: float, cy: float) -> None:
        trunk_h = rng.uniform(2.2, 4.0)
        self.cylinder(cx, cy, rng.uniform(0.12, 0.3), trunk_h, refl=rng.uniform(0.25, 0.4), kind=SURFACE_POLE)
        g = float(self.ground.height(np.array([cx]), np.array([cy]))[0])
        r = rng.uniform(1.3, 3.0)
        rz = r * rng.uniform(0.8, 1.5)
        self.ellipsoid(cx, cy, g + trunk_h + rz * 0.7, r, r * rng.uniform(0.8, 1.2), rz, refl=rng.uniform(0.4, 0.65))

    def build(self) -> StaticPrimitives:
        """Packs the primitives; boxes longer than their ``piece`` length are cut into pieces (the same
        solid) so that each piece subtends a small angular window for culling."""
        if self.boxes:
            pieces = []
            for cx, cy, cz, hx, hy, hz, yaw, refl, kind, max_piece in self.boxes:
                nx = max(1, int(np.ceil(2 * hx / max_piece)))
                ny = max(1, int(np.ceil(2 * hy / max_piece)))
                if nx == 1 and ny == 1:
                    pieces.append((cx, cy, cz, hx, hy, hz, yaw, refl, kind))
                    continue
                c, s = np.cos(yaw), np.sin(yaw)
                for i in range(nx):
                    u = -hx + (2 * i + 1) * hx / nx
                    for j in range(ny):
                        v = -hy + (2 * j + 1) * hy / ny
                        pieces.append((cx + c * u - s * v, cy + s * u + c * v, cz, hx / nx, hy / ny, hz, yaw, refl, kind))
            b = np.asarray(pieces, dtype=np.float64)
            k = len(b)
            boxes = BoxSet(b[:, 0:3].copy(), b[:, 3:6].copy(), b[:, 6].copy(), np.zeros((k, 3)), np.zeros(k),
                           b[:, 7].copy(), b[:, 8].astype(np.uint8), np.full(k, -1, np.int32))
        else:
            boxes = BoxSet.empty()
        if self.cylinders:
            c = np.asarray(self.cylinders, dtype=np.float64)
            cylinders = CylinderSet(c[:, 0:2].copy(), c[:, 2].copy(), c[:, 3].copy(), c[:, 4].copy(), c[:, 5].copy(),
                                    c[:, 6].astype(np.uint8))
        else:
            cylinders = CylinderSet.empty()
        if self.ellipsoids:
            e = np.asarray(self.ellipsoids, dtype=np.float64)
            ellipsoids = EllipsoidSet(e[:, 0:3].copy(), e[:, 3:6].copy(), e[:, 6].copy(), e[:, 7].copy())
        else:
            ellipsoids = EllipsoidSet.empty()
        return StaticPrimitives(boxes, cylinders, ellipsoids)


# ---------------------------------------------------------------------------------------------
# ground
# ---------------------------------------------------------------------------------------------
MaterialFn = Callable[[np.ndarray, np.ndarray], "tuple[np.ndarray, np.ndarray]"]


def _uniform_material(reflectivity: float, dropout: float = 0.0) -> MaterialFn:
    def material(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.full(x.shape, reflectivity), np.full(x.shape, dropout)

    return material


@dataclass
class Ground:
    """Ground height field ``z = z0 + slope . (x, y) + sum_k amp_k sin(k_k . (x, y) + phase_k)``.

    The waves model gentle undulation and roughness; their slopes are kept small so that a ray meets
    the ground once.

    Attributes:
        z0 (float), slope (float64[2]), wave_amp (float64[W]), wave_k (float64[W, 2]),
        wave_phase (float64[W]), material (callable ``(x, y) -> (reflectivity, extra_dropout)``).
    """

    z0: float = 0.0
    slope: np.ndarray = field(default_factory=lambda: np.zeros(2))
    wave_amp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    wave_k: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    wave_phase: np.ndarray = field(default_factory=lambda: np.zeros(0))
    material: MaterialFn = field(default_factory=lambda: _uniform_material(0.15))

    def linear(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The plane part ``z0 + slope . (x, y)``."""
        return self.z0 + self.slope[0] * x + self.slope[1] * y

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height at ``(x, y)``.

        Args:
            x, y (ndarray[...]): world coordinates.

        Returns:
            ndarray[...] (float64).
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.linear(x, y)
        for a, (kx, ky), p in zip(self.wave_amp, self.wave_k, self.wave_phase):
            z = z + a * np.sin(kx * x + ky * y + p)
        return z

    def height_and_gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height and its partial derivatives at ``(x, y)``.

        The sines are evaluated in float32 (4x faster; the error is below 1e-6 m for these amplitudes).
        """
        z = self.linear(x, y)
        gx = np.full_like(z, self.slope[0])
        gy = np.full_like(z, self.slope[1])
        for a, (kx, ky), p in zip(self.wave_amp.tolist(), self.wave_k.tolist(), self.wave_phase.tolist()):
            phase = (kx * x + ky * y + p).astype(np.float32)
            z += a * np.sin(phase)
            c = np.cos(phase)
            gx += (a * kx) * c
            gy += (a * ky) * c
        return z, gx, gy

    @staticmethod
    def random(rng: np.random.Generator, max_slope: float = 0.015, roughness: float = 0.03, z0: float = 0.0,
               material: MaterialFn | None = None) -> "Ground":
        """A gently sloped ground with a few long undulations and fine roughness.

        Each wave's slope ``amp * |k|`` stays below about 0.006, so rays down to about 1 deg below
        the horizon still meet the ground once.
        """
        slope = rng.uniform(-max_slope, max_slope, size=2) * np.array([1.0, 0.3])
        wavelengths = np.array([80.0, 23.0, 5.3])
        amps = np.array([0.05, 0.02, roughness * 0.15])
        angles = rng.uniform(0, 2 * np.pi, size=3)
        k = (2 * np.pi / wavelengths)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        phase = rng.uniform(0, 2 * np.pi, size=3)
        return Ground(z0, slope, amps, k, phase, material or _uniform_material(0.15))


# ---------------------------------------------------------------------------------------------
# ego motion
# ---------------------------------------------------------------------------------------------
@dataclass
class EgoMotion:
    """Pose of the sensor in the world: constant velocity plus an optional hovering jitter.

    ``position(t) = position0 + velocity * t + sum_j jitter_pos[j] * sin(2 pi f_j t + phi_j)`` and the
    roll/pitch/yaw angles likewise (``angles0 + yaw_rate * t`` on yaw, plus their jitter).

    Attributes:
        position0 (float64[3]), velocity (float64[3]), angles0 (float64[3]: roll, pitch, yaw),
        yaw_rate (float), jitter_freq (float64[J], Hz), jitter_phase (float64[J]),
        jitter_pos (float64[J, 3], m), jitter_ang (float64[J, 3], rad).
    """

    position0: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angles0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rate: float = 0.0
    jitter_freq: np.ndarray = field(default_factory=lambda: np.zeros(0))
    jitter_phase: np.ndarray = field(default_factory=lambda: np.zeros(0))
    jitter_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    jitter_ang: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def has_jitter(self) -> bool:
        return self.jitter_freq.size > 0

    def pose(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World-from-sensor rotation and position.

        Args:
            t (float or ndarray float64[K]): times (s).

        Returns:
            rotation (ndarray[..., 3, 3]), position (ndarray[..., 3]).
        """
        t = np.asarray(t, dtype=np.float64)
        flat = t.reshape(-1)
        # one [K] array per component and [J, K] jitter terms: the long axis innermost (K x 3 and K x J
        # arrays run NumPy's elementwise loops several times slower)
        pos = [self.position0[i] + self.velocity[i] * flat for i in range(3)]
        ang = [np.full(flat.shape, self.angles0[i]) for i in range(3)]
        ang[2] += self.yaw_rate * flat
        if self.has_jitter:
            s = np.sin(np.multiply.outer(2 * np.pi * self.jitter_freq, flat) + self.jitter_phase[:, None])  # [J, K]
            for i in range(3):
                pos[i] += self.jitter_pos[:, i] @ s
                ang[i] += self.jitter_ang[:, i] @ s
        position = np.stack(pos, axis=-1).reshape(t.shape + (3,))
        rotation = euler_to_matrix(*(a.reshape(t.shape) for a in ang))
        return rotation, position

    @staticmethod
    def hover(rng: np.random.Generator, position: Sequence[float], yaw: float = 0.0, pitch: float = 0.0,
              amplitude_m: float = 0.05, amplitude_deg: float = 0.5) -> "EgoMotion":
        """A hovering drone: a few slow sinusoids of a few cm and a fraction of a degree."""
        freqs = np.array([0.23, 0.61, 1.37, 2.9])
        pos_amp = rng.normal(0, amplitude_m / 2, size=(4, 3))
        ang_amp = rng.normal(0, np.deg2rad(amplitude_deg) / 2, size=(4, 3))
        return EgoMotion(np.asarray(position, dtype=np.float64), np.zeros(3), np.array([0.0, pitch, yaw]), 0.0,
                         freqs, rng.uniform(0, 2 * np.pi, 4), pos_amp, ang_amp)


# ---------------------------------------------------------------------------------------------
# scenario
# ---------------------------------------------------------------------------------------------
@dataclass
class Scenario:
    """A complete scene: ground, ego motion, labelled objects and static structure (by tiles).

    Attributes:
        name (str): scenario name.
        seed (int): its seed.
        default_sensor (str): sensor preset used when the simulator gets none.
        ground (Ground): ground height field.
        ego (EgoMotion): sensor pose over time.
        objects (BoxSet): labelled moving objects (``object_index`` = row).
        object_labels (int64[K]): class index per object.
        label_range (float): objects farther than this (horizontally) from the sensor are left out
            of frames.
        tile_length (float): x extent of a static tile (m).
        tile_fn (callable ``(k, rng) -> StaticPrimitives``): static structure of tile ``k``.
        object_counts (dict[str, int]): objects of each class actually placed.
    """

    name: str
    seed: int
    default_sensor: str
    ground: Ground
    ego: EgoMotion
    objects: BoxSet
    object_labels: np.ndarray
    label_range: float
    tile_length: float
    tile_fn: Callable[[int, np.random.Generator], StaticPrimitives]
    object_counts: dict[str, int] = field(default_factory=dict)
    _tiles: dict[int, StaticPrimitives] = field(default_factory=dict, repr=False)
    _merged: dict[tuple[int, int], StaticPrimitives] = field(default_factory=dict, repr=False)

    def tile(self, k: int) -> StaticPrimitives:
        """Static primitives of tile ``k`` (covering ``x in [k L, (k + 1) L)``), cached."""
        if k not in self._tiles:
            rng = _rng(self.seed, self.name, "tile", k)
            self._tiles[k] = self.tile_fn(k, rng)
        return self._tiles[k]

    def static_in_x_range(self, x_lo: float, x_hi: float) -> StaticPrimitives:
        """Static primitives of all tiles overlapping ``[x_lo, x_hi]``."""
        k_lo = int(np.floor(x_lo / self.tile_length))
        k_hi = int(np.floor(x_hi / self.tile_length))
        key = (k_lo, k_hi)
        if key not in self._merged:
            if len(self._merged) > 64:
                self._merged.clear()
            self._merged[key] = StaticPrimitives.concat([self.tile(k) for k in range(k_lo, k_hi + 1)])
        return self._merged[key]


def _rng(seed: int, *keys: object) -> np.random.Generator:
    """A generator seeded by the seed and a tuple of keys (strings hashed stably with crc32)."""
    words = [int(seed) & 0xFFFFFFFF, (int(seed) >> 32) & 0xFFFFFFFF]
    for key in keys:
        if isinstance(key, str):
            words.append(zlib.crc32(key.encode()))
        else:
            words.append(int(key) & 0xFFFFFFFF)
            words.append((int(key) >> 32) & 0xFFFFFFFF)
    return np.random.default_rng(words)


# the presets live in lidarops.data.scenarios (which imports this module): re-exported lazily
_FROM_SCENARIOS = ("SCENARIOS", "build_scenario", "sample_object_counts", "MAX_OBJECTS")


__getattr__, _dir = lazy_attributes(__name__, {name: ("lidarops.data.scenarios", name) for name in _FROM_SCENARIOS},
                                   globals())
