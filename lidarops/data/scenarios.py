"""The simulator's scenario presets: ``driving_city``, ``driving_highway``, ``drone_bridge`` and
``drone_lock``, built from the primitives of :mod:`lidarops.data.scene` (NumPy only).

Each preset is a pure function of its seed: object counts (:func:`sample_object_counts`), object
placement in lanes or flight regions, the static structure of each tile along x (buildings, poles,
vegetation, bridges, water) and the ego motion. :func:`build_scenario` builds one by name.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from lidarops.data._checks import integer, real
from lidarops.data.frame import CLASSES
from lidarops.data.scene import (
    CLASS_REFLECTIVITY,
    CLASS_SIZE_STATS,
    SURFACE_OBJECT,
    SURFACE_POLE,
    SURFACE_STRUCTURE,
    BoxSet,
    EgoMotion,
    Ground,
    MaterialFn,
    Scenario,
    StaticPrimitives,
    _rng,
    _StaticBuilder,
    _uniform_material,
)

__all__ = ["SCENARIOS", "CLUTTERED_SCENARIOS", "SENSOR_HEIGHT", "MAX_OBJECTS", "build_scenario", "sample_object_counts"]

#: The scenarios that take the options ``street_clutter``, ``low_clutter`` and ``roadside_structures`` (roadside
#: clutter a detector must learn to reject).
CLUTTERED_SCENARIOS: tuple[str, ...] = ("driving_city", "driving_highway")
#: the driving scenarios' default sensor height above the ground (m; their option ``sensor_height``)
SENSOR_HEIGHT = 1.73


# ---------------------------------------------------------------------------------------------
# object counts and placement
# ---------------------------------------------------------------------------------------------
CountSpec = "int | tuple[int, int] | Callable[[np.random.Generator], int]"

#: Most objects of one class a scene can be asked for (placement tries every one of them).
MAX_OBJECTS = 1000


def sample_object_counts(
    rng: np.random.Generator,
    defaults: Mapping[str, object],
    object_counts: "Mapping[str, object] | Callable[[np.random.Generator], Mapping[str, int]] | str | None",
) -> dict[str, int]:
    """Draws how many objects of each class a scene gets.

    Args:
        rng (Generator): random generator.
        defaults (mapping class -> spec): the scenario's defaults.
        object_counts: ``None`` (the defaults), ``"empty"`` (no objects), ``"dense"`` (30-45 cars in
            driving scenes, 3 drones in drone scenes), a mapping from class name to a spec, or a callable
            ``rng -> mapping`` whose result is used as the mapping.  A spec is an ``int``, an inclusive
            ``(low, high)`` range drawn uniformly, or a callable ``rng -> int``.  Classes missing from a
            mapping keep their default spec.

    Returns:
        dict[str, int]: a count for every class of :data:`CLASSES`.

    Raises:
        ValueError: an unknown class name or preset, or a count that is not an int in [0, MAX_OBJECTS]
            (bools and floats are refused, not truncated).
    """
    specs: dict[str, object] = {name: 0 for name in CLASSES}
    specs.update(defaults)
    if isinstance(object_counts, str):
        if object_counts == "empty":
            specs = {name: 0 for name in CLASSES}
        elif object_counts == "dense":
            if specs.get("Drone", 0) and not specs.get("Car", 0):
                specs["Drone"] = 3
            else:
                specs["Car"] = (30, 45)
        else:
            raise ValueError(f"unknown object_counts preset {object_counts!r} (use 'empty', 'dense' or a dict)")
    elif callable(object_counts):
        specs.update(dict(object_counts(rng)))
    elif object_counts is not None:
        specs.update(dict(object_counts))
    counts: dict[str, int] = {}
    for name in CLASSES:
        spec = specs.get(name, 0)
        what = f"object_counts[{name!r}]"
        if callable(spec):
            n = integer(spec(rng), f"the count returned for {what}", 0, MAX_OBJECTS)
        elif isinstance(spec, (tuple, list)):
            if len(spec) != 2:
                raise ValueError(f"{what} must be an int or a (low, high) pair, got {spec!r}")
            lo, hi = integer(spec[0], f"{what} low", 0, MAX_OBJECTS), integer(spec[1], f"{what} high", 0, MAX_OBJECTS)
            if hi < lo:
                raise ValueError(f"{what} must be (low, high) with low <= high, got {spec!r}")
            n = int(rng.integers(lo, hi + 1))
        else:
            n = integer(spec, what, 0, MAX_OBJECTS)
        counts[name] = n
    unknown = set(specs) - set(CLASSES)
    if unknown:
        raise ValueError(f"unknown class name(s) in object_counts: {sorted(unknown)}; classes are {CLASSES}")
    return counts


def _ego_speed(value) -> float:
    # forward along the road, at most 100 m/s (360 km/h): a NaN or huge speed would move every tile away
    return real(value, "ego_speed", 0, 100, unit=" m/s")


def _sample_size(rng: np.random.Generator, name: str) -> np.ndarray:
    mean, std = CLASS_SIZE_STATS[name]
    z = np.clip(rng.normal(size=3), -2.0, 2.0)
    return np.maximum(np.asarray(mean) + z * np.asarray(std), 0.1)


@dataclass
class Lane:
    """A 1D slot along x where objects of some classes drive (or stand) at one common speed, so they
    never run into each other.

    Attributes:
        y (float): lateral position of the lane centre.
        heading (float): yaw of objects in the lane (0 = +x, pi = -x).
        speed (float): speed along the heading (m/s, >= 0).
        x_range (tuple[float, float]): where objects may start.
        classes (tuple[str, ...]): classes allowed.
        gap (float): minimum free space between objects (m).
        jitter (float): lateral jitter (m).
    """

    y: float
    heading: float
    speed: float
    x_range: tuple[float, float]
    classes: tuple[str, ...]
    gap: float = 2.0
    jitter: float = 0.15


@dataclass
class _Placed:
    center: list = field(default_factory=list)
    half: list = field(default_factory=list)
    yaw: list = field(default_factory=list)
    velocity: list = field(default_factory=list)
    yaw_rate: list = field(default_factory=list)
    refl: list = field(default_factory=list)
    label: list = field(default_factory=list)

    def add(self, name, center, size, yaw, velocity, yaw_rate, rng) -> None:
        self.center.append(center)
        self.half.append(np.asarray(size) / 2)
        self.yaw.append(yaw)
        self.velocity.append(velocity)
        self.yaw_rate.append(yaw_rate)
        lo, hi = CLASS_REFLECTIVITY[name]
        self.refl.append(rng.uniform(lo, hi))
        self.label.append(CLASSES.index(name))

    def build(self) -> tuple[BoxSet, np.ndarray]:
        k = len(self.center)
        if k == 0:
            return BoxSet.empty(), np.zeros(0, np.int64)
        boxes = BoxSet(
            np.asarray(self.center, np.float64).reshape(k, 3),
            np.asarray(self.half, np.float64).reshape(k, 3),
            np.asarray(self.yaw, np.float64),
            np.asarray(self.velocity, np.float64).reshape(k, 3),
            np.asarray(self.yaw_rate, np.float64),
            np.asarray(self.refl, np.float64),
            np.full(k, SURFACE_OBJECT, np.uint8),
            np.arange(k, dtype=np.int32),
        )
        return boxes, np.asarray(self.label, np.int64)


_PLACEMENT_ORDER = ("Bus", "Truck", "Car", "Cyclist", "Pedestrian", "Barrier", "TrafficCone")


def _place_in_lanes(rng: np.random.Generator, ground: Ground, lanes: Sequence[Lane], counts: Mapping[str, int],
                    placed: _Placed, reserved: Sequence[tuple[int, float, float]] = (), groups: float = 0.0,
                    group_rng: "np.random.Generator | None" = None) -> dict[str, int]:
    """Places ground objects into lanes without overlaps; returns how many of each class fit. ``groups``: the
    probability that a pedestrian walks (or stands) with one to three others close behind it in its lane, drawn
    from ``group_rng`` (they count toward the pedestrians asked for)."""
    occupied: list[list[tuple[float, float]]] = [[] for _ in lanes]
    for lane_index, lo, hi in reserved:
        occupied[lane_index].append((lo, hi))
    done: dict[str, int] = {name: 0 for name in CLASSES}
    for name in _PLACEMENT_ORDER:
        want = counts.get(name, 0)
        allowed = [i for i, lane in enumerate(lanes) if name in lane.classes]
        n_ok = 0
        if want and allowed:
            weights = np.array([lanes[i].x_range[1] - lanes[i].x_range[0] for i in allowed], dtype=np.float64)
            weights /= weights.sum()
            for _ in range(want):
                if n_ok >= want:  # companions of a group filled the count
                    break
                for _attempt in range(60):
                    li = allowed[int(rng.choice(len(allowed), p=weights))]
                    lane = lanes[li]
                    size = _sample_size(rng, name)
                    x = rng.uniform(*lane.x_range)
                    half_len = size[0] / 2 + lane.gap / 2
                    if any(x - half_len < b and a < x + half_len for a, b in occupied[li]):
                        continue
                    occupied[li].append((x - half_len, x + half_len))
                    y = lane.y + rng.uniform(-lane.jitter, lane.jitter)
                    yaw = lane.heading + rng.normal(0, 0.02 if lane.speed > 0 else 0.05)
                    _add_on_ground(placed, ground, name, x, y, size, yaw, lane.speed * np.cos(lane.heading),
                                   lane.speed * np.sin(lane.heading), rng)
                    n_ok += 1
                    if groups and name == "Pedestrian" and group_rng.random() < groups:
                        n_ok += _companions(group_rng, ground, lane, occupied[li], placed, x, size,
                                            min(want - n_ok, int(group_rng.integers(1, 4))))
                    break
        done[name] = n_ok
    return done


def _companions(rng: np.random.Generator, ground: Ground, lane: Lane, occupied: list, placed: _Placed,
                x: float, size: np.ndarray, n: int) -> int:
    """Up to ``n`` pedestrians in single file behind one at ``x`` in ``lane`` (0.15-0.5 m apart, its speed and
    heading), each where the lane is free; returns how many were placed."""
    own = len(occupied) - 1  # the leader's slot: the group may stand inside its margin
    back = -1.0 if np.cos(lane.heading) >= 0 else 1.0
    done, prev_x, prev_len = 0, x, size[0]
    for _ in range(n):
        sz = _sample_size(rng, "Pedestrian")
        cx = prev_x + back * (prev_len / 2 + rng.uniform(0.15, 0.5) + sz[0] / 2)
        lo, hi = cx - sz[0] / 2, cx + sz[0] / 2
        if any(lo < b and a < hi for k, (a, b) in enumerate(occupied) if k < own):
            break
        occupied.append((min(lo, prev_x), max(hi, prev_x)))
        y = lane.y + rng.uniform(-lane.jitter, lane.jitter)
        _add_on_ground(placed, ground, "Pedestrian", cx, y, sz, lane.heading + rng.normal(0, 0.05),
                       lane.speed * np.cos(lane.heading), lane.speed * np.sin(lane.heading), rng)
        done, prev_x, prev_len = done + 1, cx, sz[0]
    return done


def _place_across(rng: np.random.Generator, ground: Ground, name: str, n: int, placed: _Placed,
                  taken: list[tuple[np.ndarray, float]], draw_xy: Callable[[], np.ndarray],
                  speed: tuple[float, float], heading_sd: float) -> list[float]:
    """Up to ``n`` objects of class ``name`` moving across the road at ``draw_xy()`` positions, their footprints'
    circumscribed circles clear of ``taken`` (extended with theirs: no two boxes overlap at any heading), heading
    across it (normal spread ``heading_sd``), at a speed drawn in ``speed``; returns their ``x``."""
    xs: list[float] = []
    for _ in range(n):
        size = _sample_size(rng, name)
        radius = float(np.hypot(size[0], size[1])) / 2
        for _attempt in range(30):
            c = draw_xy()
            if all(np.hypot(*(c - o)) >= radius + r for o, r in taken):
                break
        else:
            continue
        taken.append((c, radius))
        heading, vx, vy = _across(rng, speed, heading_sd)
        _add_on_ground(placed, ground, name, c[0], c[1], size, heading, vx, vy, rng)
        xs.append(float(c[0]))
    return xs


def _across(rng: np.random.Generator, speed: tuple[float, float], heading_sd: float) -> tuple[float, float, float]:
    """A heading across the road (either way, normal spread ``heading_sd``) and the velocity at a speed drawn in
    ``speed``: ``(heading, vx, vy)``."""
    heading = (np.pi / 2 if rng.random() < 0.5 else -np.pi / 2) + rng.normal(0, heading_sd)
    v = rng.uniform(*speed)
    return heading, v * np.cos(heading), v * np.sin(heading)


def _add_on_ground(placed: _Placed, ground: Ground, name: str, x: float, y: float, size, yaw: float, vx: float,
                   vy: float, rng: np.random.Generator) -> None:
    """An object of class ``name`` standing on the ground at ``(x, y)``, moving at ``(vx, vy)`` along the ground's
    mean slope."""
    z = float(ground.height(np.array([x]), np.array([y]))[0]) + size[2] / 2
    placed.add(name, (x, y, z), size, yaw, (vx, vy, ground.slope[0] * vx + ground.slope[1] * vy), 0.0, rng)


def _place_crossing(rng: np.random.Generator, ground: Ground, n: int, placed: _Placed,
                    road: tuple[float, float] = (-10.0, 10.0), x_range: tuple[float, float] = (5.0, 30.0),
                    groups: float = 0.0, group_rng: np.random.Generator | None = None) -> tuple[float, int]:
    """Up to ``n`` pedestrians crossing the road ahead of the ego on a crosswalk 3 m wide at a random ``x``
    (their footprints' circumscribed circles apart, so no two boxes overlap at any heading; walking across at
    1.0-1.6 m/s, some diagonally); returns the crosswalk's ``x`` and how many were placed. The real scans' nearest
    pedestrians cross in front of the car, often in groups; on the sidewalks alone a pedestrian is never nearer
    than about 15 m in the camera's view. ``groups``: :func:`_place_crossing_groups`."""
    xc = float(rng.uniform(*x_range))
    if groups and group_rng is not None:
        return xc, _place_crossing_groups(rng, group_rng, ground, n, placed, xc, road, groups)
    xs = _place_across(rng, ground, "Pedestrian", n, placed, [],
                       lambda: np.array([xc + rng.uniform(-1.5, 1.5), rng.uniform(*road)]), (1.0, 1.6), 0.3)
    return xc, len(xs)


def _place_crossing_groups(rng: np.random.Generator, group_rng: np.random.Generator, ground: Ground, n: int,
                           placed: _Placed, xc: float, road: tuple[float, float], groups: float) -> int:
    """``n`` pedestrians on the crosswalk at ``xc`` as :func:`_place_crossing` places them, except that each one, with
    probability ``groups``, leads one to three others walking with it (its heading and speed): side by side, their
    boxes' sides 0.1-0.35 m apart, or in file, 0.15-0.5 m between them. The real scans' crossing pedestrians walk so,
    their centres 0.6-0.9 m from their nearest neighbour, where pedestrians placed one by one stand about a metre or
    more apart. A group's circumscribed circle stays clear of every other group's; returns how many were placed."""
    taken: list[tuple[np.ndarray, float]] = []
    done = 0
    while done < n:
        m = 1 + (min(n - done - 1, int(group_rng.integers(1, 4))) if group_rng.random() < groups else 0)
        sizes = [_sample_size(rng, "Pedestrian") for _ in range(m)]
        abreast = group_rng.random() < 0.5
        offsets = [0.0]  # along the group's lateral axis (abreast) or its heading (in file)
        for a, b in zip(sizes[:-1], sizes[1:]):
            k = 1 if abreast else 0
            gap = group_rng.uniform(0.1, 0.35) if abreast else group_rng.uniform(0.15, 0.5)
            offsets.append(offsets[-1] - ((a[k] + b[k]) / 2 + gap))
        offsets = np.asarray(offsets) - (offsets[0] + offsets[-1]) / 2
        radius = max(abs(o) + float(np.hypot(sz[0], sz[1])) / 2 for o, sz in zip(offsets, sizes))
        # the whole group inside the crosswalk's reserved 6 m and within half a metre of the road's edges, where
        # the lanes, the walkways and their clutter keep clear, as a lone crosser is
        half_x = max(0.0, min(1.5, 3.0 - radius))
        lo, hi = road[0] + max(0.0, radius - 0.5), road[1] - max(0.0, radius - 0.5)
        for _attempt in range(30):
            c = np.array([xc + rng.uniform(-half_x, half_x), rng.uniform(lo, hi)])
            if all(np.hypot(*(c - o)) >= radius + r for o, r in taken):
                break
        else:
            break
        taken.append((c, radius))
        heading, vx, vy = _across(rng, (1.0, 1.6), 0.3)
        axis = np.array([-np.sin(heading), np.cos(heading)]) if abreast else np.array([np.cos(heading), np.sin(heading)])
        for o, sz in zip(offsets, sizes):
            p = c + o * axis
            # one heading for the whole group: boxes side by side at a common yaw cannot touch across the gaps
            _add_on_ground(placed, ground, "Pedestrian", p[0], p[1], sz, heading, vx, vy, rng)
        done += m
    return done


def _place_crossing_cyclists(rng: np.random.Generator, ground: Ground, n: int, placed: _Placed,
                             road: tuple[float, float] = (-10.0, 10.0), x_range: tuple[float, float] = (6.0, 40.0)
                             ) -> list[float]:
    """Up to ``n`` cyclists riding across the road ahead of the ego, each at its own ``x`` in ``x_range`` (heading
    across it, some at a slant; 3-6 m/s), none overlapping an object placed before (a crosswalk's pedestrians) or
    another; returns their ``x``. The sensor sees them broadside, their whole length: the real scans hold such
    cyclists (crossing at a junction), the bicycle lanes along the road never show one that way."""
    taken = [(np.asarray(c[:2], np.float64), float(np.hypot(*h[:2]))) for c, h in zip(placed.center, placed.half)]
    return _place_across(rng, ground, "Cyclist", n, placed, taken,
                         lambda: np.array([rng.uniform(*x_range), rng.uniform(*road)]), (3.0, 6.0), 0.35)


#: |y| (m) where a ``driving_city`` parking lot begins: beyond the walkway and the clutter along its outer edge
_LOT_FRONT = 16.2


@dataclass
class _Lot:
    """A parking lot beside the city street, on ``side`` (+1 / -1), from ``x0`` to ``x1``, reaching ``depth`` metres
    beyond :data:`_LOT_FRONT`; ``trees``: rows of ``(x, y, trunk radius, crown bottom above the ground, crown
    radius, crown half-height, reflectivity)`` along its front, their crowns over the first row of cars."""

    side: float
    x0: float
    x1: float
    depth: float
    trees: list = field(default_factory=list)

    def covers(self, side: float, lo: float, hi: float) -> bool:
        return side == self.side and lo < self.x1 and hi > self.x0


def _place_parking_lot(rng: np.random.Generator, ground: Ground, placed: _Placed) -> tuple[_Lot, int]:
    """One parking lot beside the street, 20-45 m long, its cars parked in bays across the street (in one row or two
    back to back), at a slant (35-63 deg), or along it side by side in columns; 55-95 % of the bays taken, or (one
    lot in five) none. The real scans' parked cars stand at every heading, in lots and at the kerb, often under
    trees; the street's lanes hold them along the road only. Returns the lot (for the tiles: no building front on
    it, trees along it) and how many cars it holds."""
    side = 1.0 if rng.random() < 0.5 else -1.0
    x0 = float(rng.uniform(-10.0, 45.0))
    x1 = x0 + float(rng.uniform(20.0, 45.0))
    layout = int(rng.integers(3))  # 0 across, 1 at a slant, 2 along the street in columns
    taken = 0.0 if rng.random() < 0.2 else rng.uniform(0.55, 0.95)  # an empty lot: open asphalt
    l_max = CLASS_SIZE_STATS["Car"][0][0] + 2 * CLASS_SIZE_STATS["Car"][1][0]
    w_max = CLASS_SIZE_STATS["Car"][0][1] + 2 * CLASS_SIZE_STATS["Car"][1][1]
    cars: list[tuple[float, float, float]] = []  # x, |y| beyond the front, heading
    if layout < 2:
        angle = np.pi / 2 if layout == 0 else float(rng.uniform(0.6, 1.1))
        pitch = (w_max + rng.uniform(0.5, 1.1)) / np.sin(angle)  # parallel neighbours, their sides apart
        reach_x = l_max / 2 * abs(np.cos(angle)) + w_max / 2 * np.sin(angle)
        half_y = l_max / 2 * np.sin(angle) + w_max / 2 * abs(np.cos(angle)) + 0.15  # a row's half-depth
        rows = 1 if rng.random() < 0.5 else 2
        for row in range(rows):
            # the nose to the aisle or to the street; at a slant all one way, as painted bays are
            heading = angle if rng.random() < 0.5 else angle + np.pi
            heading = heading if row == 0 else heading + np.pi
            for x in np.arange(x0 + reach_x, x1 - reach_x, pitch):
                if rng.random() < taken:
                    cars.append((float(x), half_y * (2 * row + 1), heading))
        depth = 2 * half_y * rows
    else:
        pitch = w_max + rng.uniform(0.5, 1.1)
        deep = int(rng.integers(2, 6))
        for x in np.arange(x0 + l_max / 2, x1 - l_max / 2, l_max + rng.uniform(5.5, 7.0)):
            heading = 0.0 if rng.random() < 0.5 else np.pi
            for j in range(deep):
                if rng.random() < taken:
                    cars.append((float(x), pitch * (j + 0.5), heading))
        depth = pitch * deep
    for x, dy, heading in cars:
        size = _sample_size(rng, "Car")
        y = side * (_LOT_FRONT + dy)
        z = float(ground.height(np.array([x]), np.array([y]))[0]) + size[2] / 2
        # a small skew, bounded so neighbours 0.5 m apart never touch
        placed.add("Car", (x, y, z), size, heading + np.clip(rng.normal(0, 0.03), -0.06, 0.06), (0.0, 0.0, 0.0), 0.0,
                   rng)
    trees = []
    if rng.random() < 0.6:
        for x in np.arange(x0 + rng.uniform(0, 4), x1, rng.uniform(7.0, 12.0)):
            r = float(rng.uniform(1.5, 3.0))
            trees.append((float(x), side * (_LOT_FRONT - 0.3), float(rng.uniform(0.12, 0.25)),
                          float(rng.uniform(2.2, 3.2)), r, r * float(rng.uniform(0.6, 1.0)), float(rng.uniform(0.4, 0.65))))
    return _Lot(side, x0, x1, depth + 1.0, trees), len(cars)


def _lot_material(material, lots: Sequence[_Lot]):
    """``material`` with asphalt on the lots."""
    def lot_material(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        refl, drop = material(x, y)
        for lot in lots:
            on = (x >= lot.x0) & (x <= lot.x1) & (lot.side * y >= _LOT_FRONT) & (lot.side * y <= _LOT_FRONT + lot.depth)
            refl = np.where(on, 0.12, refl)
        return refl, drop

    return lot_material


def _place_drones(rng: np.random.Generator, n: int, region: tuple[tuple[float, float], ...], speed: tuple[float, float],
                  placed: _Placed, avoid: Sequence[np.ndarray] = ()) -> int:
    """Drones at random 3D positions (at least 3 m apart), flying with random 3D velocity and yaw rate."""
    centers: list[np.ndarray] = [np.asarray(a, dtype=np.float64) for a in avoid]
    n_ok = 0
    for _ in range(n):
        for _attempt in range(60):
            c = np.array([rng.uniform(*region[0]), rng.uniform(*region[1]), rng.uniform(*region[2])])
            if any(np.linalg.norm(c - o) < 3.0 for o in centers):
                continue
            centers.append(c)
            heading = rng.uniform(-np.pi, np.pi)
            climb = rng.uniform(-0.3, 0.3)
            v = rng.uniform(*speed) * np.array([np.cos(heading) * np.cos(climb), np.sin(heading) * np.cos(climb),
                                                 np.sin(climb)])
            placed.add("Drone", c, _sample_size(rng, "Drone"), rng.uniform(-np.pi, np.pi), v, rng.uniform(-0.8, 0.8), rng)
            n_ok += 1
            break
    return n_ok


# ---------------------------------------------------------------------------------------------
# driving_city
# ---------------------------------------------------------------------------------------------
def _city_material(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ay = np.abs(y)
    refl = np.where(ay < 10.7, 0.12, 0.28)  # asphalt road, concrete sidewalk
    dashed = (np.abs(ay - 3.5) < 0.075) & (np.mod(x, 9.0) < 3.0)  # lane dividers
    solid = (ay < 0.15) | (np.abs(ay - 7.0) < 0.075)  # centre line and bike-lane lines
    refl = np.where(dashed | solid, 0.6, refl)
    return refl, np.zeros_like(refl)


def _city_tile(ground: Ground, tile_length: float, lots: Sequence["_Lot"] = (), open_ground: float = 0.0,
               seed: int = 0) -> Callable[[int, np.random.Generator], StaticPrimitives]:
    def build(k: int, rng: np.random.Generator) -> StaticPrimitives:
        b = _StaticBuilder(ground)
        # raised open ground before a building (lawns, terraces): from a stream of its own, so that without it the
        # tile is what it was
        open_rng = _rng(seed, "driving_city", "open_ground", k) if open_ground else None
        x0, x1 = k * tile_length, (k + 1) * tile_length
        cross = None
        if rng.random() < 0.3:  # a cross street in this tile
            cx = rng.uniform(x0 + 10, x1 - 10)
            cross = (cx - 8.0, cx + 8.0)
        for side in (-1.0, 1.0):
            # building facades from |y| = 16 outwards, alleys between them
            x = x0 + rng.uniform(0, 3)
            while x < x1 - 3:
                length = min(rng.uniform(8, 30), x1 - x)
                if cross and x < cross[1] and x + length > cross[0]:
                    if x < cross[0] - 3:
                        length = cross[0] - x
                    else:
                        x = cross[1] + rng.uniform(0, 2)
                        continue
                lot = next((lot for lot in lots if lot.covers(side, x, x + length)), None)
                if length >= 3:
                    depth = rng.uniform(8, 20)
                    setback = rng.uniform(0, 2.0) + (lot.depth + _LOT_FRONT - 16 if lot else 0.0)  # behind a lot
                    if open_rng is not None and lot is None and open_rng.random() < open_ground:
                        terrace = open_rng.uniform(4.0, 14.0)
                        b.box_on_ground(x + length / 2, side * (16 + terrace / 2), length, terrace,
                                        open_rng.uniform(0.15, 0.9), refl=open_rng.uniform(0.25, 0.5), bury=0.1)
                        setback += terrace
                    b.box_on_ground(x + length / 2, side * (16 + setback + depth / 2), length, depth,
                                    rng.uniform(6, 30), refl=rng.uniform(0.2, 0.45))
                    if rng.random() < 0.4 and lot is None:  # hedge along the facade
                        b.ellipsoid(x + length / 2, side * 15.2, float(ground.height(np.array([x]), np.array([side * 15.2]))[0]) + 0.5,
                                    length / 2 * 0.9, 0.45, 0.75, refl=rng.uniform(0.4, 0.6), mean_free_path=0.25)
                gap = rng.uniform(0.5, 5.0)
                if gap > 2.5 and rng.random() < 0.6 and lot is None:  # fence closing the alley
                    b.box_on_ground(x + length + gap / 2, side * 16.0, gap, 0.06, rng.uniform(1.2, 2.0),
                                    refl=rng.uniform(0.2, 0.5), bury=0.1)
                x += length + gap
            # poles and trees along the curb
            x = x0 + rng.uniform(0, 6)
            while x < x1 - 1:
                if not (cross and cross[0] - 1 < x < cross[1] + 1):
                    r = rng.random()
                    if r < 0.35:
                        height = rng.uniform(5.0, 9.0)
                        b.cylinder(x, side * 11.0, rng.uniform(0.1, 0.18), height, refl=rng.uniform(0.3, 0.6))
                        if rng.random() < 0.7:  # lamp arm over the road
                            g = float(ground.height(np.array([x]), np.array([side * 11.0]))[0])
                            b.box(x, side * 9.9, g + height - 0.15, 0.25, 2.2, 0.18, refl=0.4, kind=SURFACE_POLE)
                    elif r < 0.5:  # traffic sign
                        b.cylinder(x, side * 11.0, 0.04, 2.2, refl=0.4)
                        g = float(ground.height(np.array([x]), np.array([side * 11.0]))[0])
                        b.box(x, side * 11.0, g + 2.5, 0.04, 0.7, 0.6, refl=0.9, kind=SURFACE_POLE)
                    else:
                        b.tree(rng, x, side * 11.2)
                x += rng.uniform(6, 18)
        for lot in lots:  # trees along a lot's front, their crowns over its first row
            for tx, ty, trunk, bottom, r, rz, refl in lot.trees:
                if x0 <= tx < x1:
                    g = float(ground.height(np.array([tx]), np.array([ty]))[0])
                    b.cylinder(tx, ty, trunk, bottom + rz * 0.3, refl=0.3, kind=SURFACE_POLE)
                    b.ellipsoid(tx, ty, g + bottom + rz, r, r, rz, refl=refl)
        return b.build()

    return build


def _shrub(b: _StaticBuilder, rng: np.random.Generator, ground: Ground, x: float, y: float, size: float,
           spread_y: float) -> None:
    """A shrub: a few overlapping foliage blobs, irregular as real ones are (one ellipsoid reads as a smooth
    dome), kept within ``spread_y`` of ``y`` across the road."""
    g = float(ground.height(np.array([x]), np.array([y]))[0])
    for _ in range(int(rng.integers(2, 6))):
        r = size * rng.uniform(0.35, 0.7)
        ry = min(r, spread_y)
        b.ellipsoid(x + rng.uniform(-size, size) * 0.6, y + rng.uniform(-1, 1) * max(spread_y - ry, 0.0),
                    g + rng.uniform(0.3, 1.0) * size, r, ry, r * rng.uniform(0.6, 1.2), refl=rng.uniform(0.25, 0.65),
                    mean_free_path=rng.uniform(0.15, 0.4))


def _street_clutter(ground: Ground, seed: int, density: float, k: int, x0: float, x1: float) -> StaticPrimitives:
    """A city tile's street furniture and roadside clutter, the kind a detector must learn not to take for
    objects: a kerb, and bollards, bins, parking meters and parked bicycles on the strip between the kerb and
    the walkers, bushes along the facades. Everything keeps clear of the parking lane (|y| < 10.5) and of the
    pedestrians' lanes (|y| 11.3 to 14.4), so no labelled box holds clutter. It draws from a random stream of
    its own: without it, the tile's other primitives are what they were."""
    rng = _rng(seed, "driving_city", "clutter", k)
    b = _StaticBuilder(ground)
    for side in (-1.0, 1.0):
        x = x0
        while x < x1:  # the kerb, in segments broken by driveways
            length = min(rng.uniform(6.0, 25.0), x1 - x)
            b.box_on_ground(x + length / 2, side * 10.7, length, 0.25, 0.14, refl=rng.uniform(0.25, 0.4), bury=0.1)
            x += length + rng.uniform(0.0, 4.0)
        n = rng.poisson(density * (x1 - x0) / 6.0)
        for x in np.sort(rng.uniform(x0, x1, n)):
            kind = rng.random()
            if kind < 0.3:  # a row of bollards
                for j in range(int(rng.integers(1, 5))):
                    b.cylinder(x + 1.5 * j, side * 10.95, rng.uniform(0.06, 0.12), rng.uniform(0.7, 1.1),
                               refl=rng.uniform(0.2, 0.6))
            elif kind < 0.45:  # a rubbish bin
                b.cylinder(x, side * 10.98, rng.uniform(0.2, 0.28), rng.uniform(0.9, 1.2), refl=rng.uniform(0.1, 0.4),
                           kind=SURFACE_STRUCTURE)
            elif kind < 0.55:  # a parking meter: a post and its head at chest height
                b.cylinder(x, side * 10.95, 0.05, 1.2, refl=0.4)
                g = float(ground.height(np.array([x]), np.array([side * 10.95]))[0])
                b.box(x, side * 10.95, g + 1.35, 0.2, 0.15, 0.35, refl=0.35, kind=SURFACE_POLE)
            elif kind < 0.7:  # a parked bicycle along the kerb
                b.box_on_ground(x, side * 11.05, 1.7, 0.08, rng.uniform(0.9, 1.1), heading=rng.uniform(-0.15, 0.15),
                                refl=rng.uniform(0.2, 0.5), bury=0.0)
            elif kind < 0.8:  # a fire hydrant, a post box or a sign post: pedestrian-sized, not pedestrians
                if rng.random() < 0.5:
                    b.cylinder(x, side * 10.98, rng.uniform(0.1, 0.2), rng.uniform(0.6, 1.3), refl=rng.uniform(0.2, 0.7),
                               kind=SURFACE_STRUCTURE)
                else:
                    b.cylinder(x, side * 10.98, 0.04, rng.uniform(1.8, 2.6), refl=0.4)
                    g = float(ground.height(np.array([x]), np.array([side * 10.98]))[0])
                    b.box(x, side * 10.98, g + rng.uniform(1.6, 2.4), 0.04, rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6),
                          refl=rng.uniform(0.5, 0.9), kind=SURFACE_POLE)
            else:  # a shrub along a facade: many weak, scattered returns
                _shrub(b, rng, ground, x, side * 15.2, rng.uniform(0.4, 1.1), 0.45)
    return b.build()


def _roadside_clutter(ground: Ground, seed: int, density: float, k: int, x0: float, x1: float) -> StaticPrimitives:
    """A highway tile's verge beyond the guard rails and the barrier lane: shrubs, saplings and delineator
    posts close to the road (the kind of roadside a detector sees false pedestrians in), clear of every
    labelled lane (|y| < 13.3 on the right, < 14.0 on the left). Its own random stream."""
    rng = _rng(seed, "driving_highway", "clutter", k)
    b = _StaticBuilder(ground)
    for y_lo, y_hi in ((-17.0, -13.5), (14.3, 15.7), (16.4, 19.5)):
        n = rng.poisson(density * (x1 - x0) / 8.0 * (y_hi - y_lo) / 3.5)
        for x in np.sort(rng.uniform(x0, x1, n)):
            y = rng.uniform(y_lo + 0.3, y_hi - 0.3)
            room = min(y - y_lo, y_hi - y)  # to the zone's edges: nothing reaches a lane
            kind = rng.random()
            if kind < 0.55:
                _shrub(b, rng, ground, x, y, rng.uniform(0.3, 1.3), room)
            elif kind < 0.75:  # a sapling: a thin trunk and a small crown
                h = rng.uniform(1.2, 2.5)
                b.cylinder(x, y, rng.uniform(0.03, 0.08), h, refl=rng.uniform(0.25, 0.4))
                g = float(ground.height(np.array([x]), np.array([y]))[0])
                r = rng.uniform(0.4, 0.9)
                b.ellipsoid(x, y, g + h + r * 0.5, r, min(r, room), r, refl=rng.uniform(0.4, 0.6),
                            mean_free_path=0.3)
            else:  # a delineator or a marker post
                b.cylinder(x, y, rng.uniform(0.05, 0.1), rng.uniform(0.9, 1.6), refl=rng.uniform(0.3, 0.9))
    return b.build()


def _low_clutter(scenario: str):
    """A driving tile's low clutter (the scenario option ``low_clutter``): planters, low walls, low bushes, stones and
    (on the highway) grassy berms, 0.2-1 m tall and up to a few metres wide, where the real scans' far returns off
    the road stand (at 40-75 m most real non-ground clusters are that low and wide; the street clutter's are posts).
    Clear of every labelled lane, as the street clutter; a random stream of its own."""
    # zones (y from, y to) clear of the lanes: the city's kerb strip and the walkway's outer edge before the facades,
    # the highway's verges
    zones = {"driving_city": ((-15.8, -14.6), (-11.2, -10.8), (10.8, 11.2), (14.6, 15.8)),
             "driving_highway": ((-17.0, -13.5), (14.3, 15.7), (16.4, 19.5))}[scenario]

    def build(ground: Ground, seed: int, density: float, k: int, x0: float, x1: float) -> StaticPrimitives:
        rng = _rng(seed, scenario, "low_clutter", k)
        b = _StaticBuilder(ground)
        for y_lo, y_hi in zones:
            width = y_hi - y_lo
            for x in np.sort(rng.uniform(x0, x1, rng.poisson(density * (x1 - x0) / 10.0 * min(width, 2.0)))):
                y = rng.uniform(y_lo, y_hi)
                room = max(min(y - y_lo, y_hi - y), 0.05)  # to the zone's edges: nothing reaches a lane
                kind = rng.random()
                g = float(ground.height(np.array([x]), np.array([y]))[0])
                if kind < 0.3:  # a low bush: a few dense, weakly returning blobs near the ground
                    _shrub(b, rng, ground, x, y, rng.uniform(0.25, 0.6), room)
                elif kind < 0.5:  # a stone or a heap: one solid blob, half sunk
                    r = rng.uniform(0.2, 0.6)
                    b.ellipsoid(x, y, g, r * rng.uniform(1.0, 2.0), min(r, room), r, refl=rng.uniform(0.2, 0.5),
                                mean_free_path=0.02)
                elif kind < 0.75 or scenario != "driving_city":
                    if scenario == "driving_city":  # a planter: a low box across a metre or two
                        b.box_on_ground(x, y, rng.uniform(0.6, 2.0), min(rng.uniform(0.4, 1.0), 2 * room),
                                        rng.uniform(0.3, 0.8), heading=rng.uniform(-0.1, 0.1),
                                        refl=rng.uniform(0.15, 0.45), bury=0.1)
                    else:  # a grassy berm along the verge: long, low, rough
                        b.ellipsoid(x, y, g, rng.uniform(2.0, 6.0), min(rng.uniform(0.5, 1.5), room),
                                    rng.uniform(0.3, 0.7), refl=rng.uniform(0.3, 0.5), mean_free_path=0.1)
                else:  # a low wall or a fence segment along the walkway
                    b.box_on_ground(x, y, rng.uniform(1.5, 6.0), min(0.25, 2 * room), rng.uniform(0.4, 1.0),
                                    refl=rng.uniform(0.2, 0.5), bury=0.1)
        return b.build()

    return build


def _bar_fence(b: _StaticBuilder, rng: np.random.Generator, ground: Ground, x: float, y: float, length: float,
               height: float) -> None:
    """A metal fence or railing along x: posts every 2-3 m, a top and a bottom rail, vertical bars 0.1-0.16 m apart
    (a beam returns from some bars and passes between others, as on real railings)."""
    g = lambda xx: float(ground.height(np.array([xx]), np.array([y]))[0])  # noqa: E731
    refl = rng.uniform(0.25, 0.6)
    r_post, r_bar = rng.uniform(0.03, 0.05), rng.uniform(0.008, 0.015)
    for xp in np.arange(x, x + length + 1e-9, rng.uniform(2.0, 3.0)):
        b.cylinder(xp, y, r_post, height, refl=refl)
    for xp in np.arange(x + rng.uniform(0.05, 0.1), x + length, rng.uniform(0.1, 0.16)):
        b.cylinder(xp, y, r_bar, height - 0.05, refl=refl)
    xm, bottom = x + length / 2, rng.uniform(0.08, 0.2)
    for z, dz in ((height - 0.03, 0.05), (bottom, 0.04)):
        b.box(xm, y, g(xm) + z, length, 0.04, dz, refl=refl, kind=SURFACE_STRUCTURE)


def _guard_rail(b: _StaticBuilder, rng: np.random.Generator, ground: Ground, x: float, y: float, length: float,
                side: float) -> None:
    """A W-beam guard rail along x, its top 0.7-0.8 m above the ground, on posts every 2-4 m behind it."""
    top = rng.uniform(0.7, 0.8)
    refl = rng.uniform(0.35, 0.6)  # galvanised steel
    b.box_on_ground(x + length / 2, y, length, 0.08, 0.31, refl=refl, lift=top - 0.31, kind=SURFACE_STRUCTURE)
    for xp in np.arange(x + rng.uniform(0.2, 1.0), x + length, rng.uniform(2.0, 4.0)):
        b.box_on_ground(xp, y + side * 0.1, 0.1, 0.12, top - 0.05, refl=refl * 0.8, kind=SURFACE_POLE, bury=0.3)


def _wall_with_bins(b: _StaticBuilder, rng: np.random.Generator, ground: Ground, x: float, y: float, length: float,
                    side: float, room: float) -> None:
    """A garden or garage wall (or a board fence) 1.4-2.6 m tall along x, and often wheelie bins or a large waste
    container standing before it on the road's side, within ``room`` of the wall's face."""
    depth = rng.uniform(0.15, 0.3)
    b.box_on_ground(x + length / 2, y, length, depth, rng.uniform(1.4, 2.6), refl=rng.uniform(0.15, 0.5), bury=0.1)
    if rng.random() < 0.6:
        xb = x + rng.uniform(0.2, max(length - 2.0, 0.3))
        for _ in range(int(rng.integers(1, 4))):
            if rng.random() < 0.15:  # a 1,100 l container
                w, d, h = rng.uniform(1.2, 1.4), rng.uniform(0.9, 1.1), rng.uniform(1.25, 1.45)
            else:  # a 120-360 l wheelie bin
                w, d, h = rng.uniform(0.48, 0.7), rng.uniform(0.55, 0.88), rng.uniform(0.93, 1.2)
            d = min(d, room - depth / 2 - 0.1)  # room for a turn of up to 0.08 rad
            if d < 0.3 or xb + w > x + length:
                break
            face = y - side * (depth / 2 + 0.02 + d / 2)
            b.box_on_ground(xb + w / 2, face, w, d, h, heading=rng.uniform(-0.08, 0.08),
                            refl=rng.uniform(0.05, 0.45), bury=0.0)
            xb += w + rng.uniform(0.05, 0.5)


def _roadside_structures(scenario: str):
    """A driving tile's roadside structures (the scenario option ``roadside_structures``), what the real scans'
    confident false positives stand on: W-beam guard rails on posts and metal railings of vertical bars along the
    kerb, garden and garage walls with wheelie bins before them, and bar fences with a tall post at their end along
    the walkway's outer edge (on the highway: bar fences, tall posts and walls on the verges), and standing objects
    of a pedestrian's size in every zone (:func:`_person_sized`). Clear of every labelled lane, as the other clutter;
    a random stream of its own."""
    # (y from, y to, the structures the zone takes): the city's kerb strip and the walkway's outer edge, the
    # highway's verges beyond the rails
    zones = {"driving_city": ((-11.2, -10.8, "kerb"), (10.8, 11.2, "kerb"), (-15.8, -14.6, "edge"),
                              (14.6, 15.8, "edge")),
             "driving_highway": ((-17.0, -13.5, "verge"), (16.4, 19.5, "verge"))}[scenario]

    def build(ground: Ground, seed: int, density: float, k: int, x0: float, x1: float) -> StaticPrimitives:
        rng = _rng(seed, scenario, "roadside_structures", k)
        b = _StaticBuilder(ground)
        for y_lo, y_hi, zone in zones:
            side = 1.0 if y_lo > 0 else -1.0
            x = x0 + rng.exponential(15.0 / density)
            while x < x1 - 1.0:
                kind = rng.random()
                if zone == "kerb":
                    length = min(rng.uniform(6.0, 30.0), x1 - x)
                    if kind < 0.5:
                        _guard_rail(b, rng, ground, x, side * 11.0, length, side)
                    else:
                        _bar_fence(b, rng, ground, x, side * 11.05, length, rng.uniform(0.9, 1.2))
                else:
                    length = min(rng.uniform(3.0, 12.0), x1 - x)
                    far = (y_hi if side > 0 else -y_lo) - 0.05  # the zone's edge away from the road
                    if kind < 0.45 and zone == "edge":
                        # the wall's centre 0.2 m inside the zone's far edge: the bins keep to the zone
                        _wall_with_bins(b, rng, ground, x, side * (far - 0.15), length, side, y_hi - y_lo - 0.2)
                    elif kind < 0.8:
                        yf = side * (far - 0.05) if zone == "edge" else rng.uniform(y_lo + 0.2, y_hi - 0.2)
                        _bar_fence(b, rng, ground, x, yf, length, rng.uniform(1.2, 2.0))
                        if rng.random() < 0.5:  # a lamp or sign post at the fence's end
                            b.cylinder(x + length + 0.3, yf, rng.uniform(0.05, 0.1), rng.uniform(3.0, 6.0),
                                       refl=rng.uniform(0.3, 0.6))
                    else:  # a solid wall, 1-2 m, along the verge or the walkway
                        yw = side * (far - 0.15) if zone == "edge" else rng.uniform(y_lo + 0.3, y_hi - 0.3)
                        b.box_on_ground(x + length / 2, yw, length, 0.25, rng.uniform(1.0, 2.0),
                                        refl=rng.uniform(0.2, 0.45), bury=0.1)
                x += length + rng.exponential(15.0 / density) + 0.5
            for x in np.sort(rng.uniform(x0, x1, rng.poisson(density * (x1 - x0) / 12.0))):
                _person_sized(b, rng, ground, x, y_lo, y_hi, zone)
        return b.build()

    return build


def _person_sized(b: _StaticBuilder, rng: np.random.Generator, ground: Ground, x: float, y_lo: float, y_hi: float,
                  zone: str) -> None:
    """One standing object of a pedestrian's size and return count that is not one, within ``[y_lo, y_hi]``: the
    dense, narrow clusters of 0.3-0.8 m across and 1-2 m tall that the real scans' confident pedestrian and cyclist
    false positives stand on at 20-50 m. On the kerb strip (0.4 m wide): a post carrying a sign, a box or a mailbox
    at chest height, or a narrow column; wider zones: also utility cabinets, narrow dense shrubs and conifers, and
    young trees whose foliage starts low."""
    width = y_hi - y_lo
    y = rng.uniform(y_lo + min(0.2, width / 2), y_hi - min(0.2, width / 2))
    room = min(y - y_lo, y_hi - y) - 0.01  # to the zone's edges
    g = float(ground.height(np.array([x]), np.array([y]))[0])
    kind = rng.random() if zone != "kerb" else rng.random() * 0.4
    if kind < 0.2:  # a post with a sign, a parcel box or a mailbox at 0.9-1.6 m
        r = min(rng.uniform(0.04, 0.08), room)
        top = rng.uniform(1.1, 1.9)
        b.cylinder(x, y, r, top, refl=rng.uniform(0.3, 0.6))
        dz = rng.uniform(0.25, 0.6)
        b.box(x, y, g + top - dz / 2, rng.uniform(0.3, 0.6), min(rng.uniform(0.15, 0.4), 2 * room), dz,
              refl=rng.uniform(0.2, 0.8), kind=SURFACE_POLE)
    elif kind < 0.4:  # a column or a bollard of a pedestrian's width
        b.cylinder(x, y, min(rng.uniform(0.15, 0.3), room), rng.uniform(1.2, 2.5), refl=rng.uniform(0.2, 0.5),
                   kind=SURFACE_STRUCTURE)
    elif kind < 0.6:  # a utility cabinet
        b.box_on_ground(x, y, rng.uniform(0.5, 1.1), min(rng.uniform(0.3, 0.5), 2 * room - 0.05),
                        rng.uniform(1.0, 1.7), heading=0.0, refl=rng.uniform(0.15, 0.5), bury=0.05)
    elif kind < 0.8:  # a narrow, dense shrub or conifer
        rz = rng.uniform(0.5, 1.1)
        r = rng.uniform(0.25, 0.5)
        b.ellipsoid(x, y, g + rz * rng.uniform(0.8, 1.0), r, min(r, room), rz, refl=rng.uniform(0.3, 0.6),
                    mean_free_path=rng.uniform(0.04, 0.15))
    else:  # a young tree: a thin trunk, its foliage from 0.8-1.8 m
        h = rng.uniform(0.8, 1.8)
        b.cylinder(x, y, min(rng.uniform(0.04, 0.1), room), h + 0.3, refl=rng.uniform(0.25, 0.4))
        r = rng.uniform(0.3, 0.7)
        b.ellipsoid(x, y, g + h + r, r, min(r, room), r * rng.uniform(0.9, 1.4), refl=rng.uniform(0.4, 0.6),
                    mean_free_path=rng.uniform(0.1, 0.3))


def _cluttered(tile_fn, clutter, ground: Ground, seed: int, density: float, tile_length: float):
    """``tile_fn`` with each tile's ``clutter`` added (``density`` 0: the tiles as they are)."""
    if density <= 0:
        return tile_fn

    def build(k: int, rng: np.random.Generator) -> StaticPrimitives:
        base = tile_fn(k, rng)
        return StaticPrimitives.concat([base, clutter(ground, seed, density, k, k * tile_length, (k + 1) * tile_length)])

    return build


def _sensor_height(value) -> float:
    # the sensor's height above the ground under it (KITTI's HDL-64E: 1.73 m)
    return real(value, "sensor_height", 0.5, 5.0, unit=" m")


def _road_ground(rng: np.random.Generator, ground_slope: float | None, default: float, bias: float,
                 **kwargs) -> Ground:
    """A driving scene's ground, its grade along the road drawn up to ``ground_slope`` (rise over run; across it 0.3
    of that; None: ``default``) and shifted by ``bias``: the sensor stays level, so the road ahead rises or falls in
    its frame as at a change of grade."""
    slope = default if ground_slope is None else real(ground_slope, "ground_slope", 0, 0.1)
    ground = Ground.random(rng, max_slope=slope, **kwargs)
    if real(bias, "ground_slope_bias", -0.05, 0.05):
        ground.slope = ground.slope + np.array([bias, 0.0])
    return ground


def _driving_city(seed: int, object_counts=None, ego_speed: float | None = None, street_clutter: float = 0.0,
                  sensor_height: float = SENSOR_HEIGHT, pedestrian_groups: float = 0.0, low_clutter: float = 0.0,
                  roadside_structures: float = 0.0, crossing_pedestrians: float = 0.0, crossing_cyclists: float = 0.0,
                  parking_lots: float = 0.0, open_ground: float = 0.0, crossing_groups: float = 0.0,
                  ground_slope: float | None = None, ground_slope_bias: float = 0.0, **unused) -> Scenario:
    _no_unused(unused, "driving_city")
    street_clutter = real(street_clutter, "street_clutter", 0, 10)
    low_clutter = real(low_clutter, "low_clutter", 0, 10)
    roadside_structures = real(roadside_structures, "roadside_structures", 0, 10)
    pedestrian_groups = real(pedestrian_groups, "pedestrian_groups", 0, 1)
    crossing_pedestrians = real(crossing_pedestrians, "crossing_pedestrians", 0, 1)
    crossing_cyclists = real(crossing_cyclists, "crossing_cyclists", 0, 1)
    crossing_groups = real(crossing_groups, "crossing_groups", 0, 1)
    parking_lots = real(parking_lots, "parking_lots", 0, 1)
    open_ground = real(open_ground, "open_ground", 0, 1)
    height = _sensor_height(sensor_height)
    rng = _rng(seed, "driving_city", "scene")
    ground = _road_ground(rng, ground_slope, 0.015, ground_slope_bias, material=_city_material)
    speed = float(rng.uniform(3.0, 12.0)) if ego_speed is None else _ego_speed(ego_speed)
    ego_y = -1.75
    g0 = float(ground.height(np.array([0.0]), np.array([ego_y]))[0])
    ego = EgoMotion(np.array([0.0, ego_y, g0 + height]), np.array([speed, 0.0, speed * ground.slope[0]]))
    defaults = {"Car": (8, 30), "Pedestrian": (2, 15), "Cyclist": (0, 5), "Truck": (0, 2), "Bus": (0, 2),
                "Barrier": (0, 4), "TrafficCone": (0, 6)}
    counts = sample_object_counts(rng, defaults, object_counts)
    xr = (-50.0, 100.0)
    lane_speed_fwd = rng.uniform(6, 13)
    lane_speed_back = rng.uniform(6, 13), rng.uniform(6, 13)
    bike = rng.uniform(3.5, 6.5, size=2)
    walk = rng.uniform(1.0, 1.6, size=4)
    vehicles = ("Car", "Truck", "Bus")
    lanes = [
        Lane(-1.75, 0.0, speed, xr, ("Car", "Truck"), gap=6.0),  # ego lane at the ego's speed
        Lane(-5.25, 0.0, lane_speed_fwd, xr, vehicles, gap=6.0),
        Lane(1.75, np.pi, lane_speed_back[0], xr, ("Car", "Truck"), gap=6.0),
        Lane(5.25, np.pi, lane_speed_back[1], xr, vehicles, gap=6.0),
        Lane(-7.75, 0.0, bike[0], xr, ("Cyclist",), gap=2.0, jitter=0.2),
        Lane(7.75, np.pi, bike[1], xr, ("Cyclist",), gap=2.0, jitter=0.2),
        Lane(-9.6, 0.0, 0.0, xr, ("Car", "Truck", "Bus", "Barrier", "TrafficCone"), gap=1.0, jitter=0.1),
        Lane(9.6, np.pi, 0.0, xr, ("Car", "Truck", "Bus", "Barrier", "TrafficCone"), gap=1.0, jitter=0.1),
    ]
    for side, (w1, w2) in ((-1, walk[:2]), (1, walk[2:])):
        lanes += [
            Lane(side * 11.6, 0.0, w1, (-40.0, 70.0), ("Pedestrian",), gap=0.6, jitter=0.05),
            Lane(side * 12.8, np.pi, w2, (-40.0, 70.0), ("Pedestrian",), gap=0.6, jitter=0.05),
            Lane(side * 14.0, rng.choice([0.0, np.pi]), 0.0, (-40.0, 70.0), ("Pedestrian",), gap=0.4, jitter=0.1),
        ]
    placed = _Placed()
    # the ego car occupies its lane around x = 0; a crosswalk, where there is one, every lane across the road
    reserved, crossing = [(0, -3.5, 3.5)], 0
    cross_rng = _rng(seed, "driving_city", "crossing") if crossing_pedestrians else None
    if cross_rng is not None and cross_rng.random() < crossing_pedestrians and counts.get("Pedestrian", 0):
        want = min(counts["Pedestrian"], int(cross_rng.integers(1, 9)))
        xc, crossing = _place_crossing(cross_rng, ground, want, placed, groups=crossing_groups,
                                       group_rng=_rng(seed, "driving_city", "crossing_groups") if crossing_groups else None)
        reserved += [(i, xc - 3.0, xc + 3.0) for i in range(8)]  # the eight vehicle, bike and parking lanes
        counts = {**counts, "Pedestrian": counts["Pedestrian"] - crossing}
    across = []
    cyc_rng = _rng(seed, "driving_city", "crossing_cyclists") if crossing_cyclists else None
    if cyc_rng is not None and cyc_rng.random() < crossing_cyclists and counts.get("Cyclist", 0):
        across = _place_crossing_cyclists(cyc_rng, ground, min(counts["Cyclist"], int(cyc_rng.integers(1, 4))), placed)
        reserved += [(i, x - 1.5, x + 1.5) for x in across for i in range(8)]
        counts = {**counts, "Cyclist": counts["Cyclist"] - len(across)}
    done = _place_in_lanes(rng, ground, lanes, counts, placed, reserved=reserved, groups=pedestrian_groups,
                           group_rng=_rng(seed, "driving_city", "groups") if pedestrian_groups else None)
    done["Pedestrian"] += crossing
    done["Cyclist"] += len(across)
    lots: list[_Lot] = []
    lot_rng = _rng(seed, "driving_city", "parking_lots") if parking_lots else None
    if lot_rng is not None and lot_rng.random() < parking_lots:
        lot, n_lot = _place_parking_lot(lot_rng, ground, placed)
        lots.append(lot)
        done["Car"] += n_lot
        ground.material = _lot_material(ground.material, lots)
    z0 = float(ground.z0)
    done["Drone"] = _place_drones(rng, counts["Drone"], ((-30.0, 70.0), (-9.0, 9.0), (z0 + 6.0, z0 + 15.0)), (1.0, 8.0),
                                  placed, avoid=[ego.position0])
    objects, labels = placed.build()
    tile_length = 40.0
    tiles = _city_tile(ground, tile_length, lots, open_ground, seed)
    return Scenario("driving_city", seed, "hdl64", ground, ego, objects, labels, 80.0, tile_length,
                    _cluttered(_cluttered(_cluttered(tiles, _street_clutter, ground, seed, street_clutter, tile_length),
                                          _low_clutter("driving_city"), ground, seed, low_clutter, tile_length),
                               _roadside_structures("driving_city"), ground, seed, roadside_structures, tile_length), done)


# ---------------------------------------------------------------------------------------------
# driving_highway
# ---------------------------------------------------------------------------------------------
def _highway_material(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    refl = np.where((y > -11.1) & (y < 14.1), 0.12, 0.35)  # asphalt; grass/gravel outside
    lines = (np.abs(y + 3.7) < 0.08) | (np.abs(y + 7.4) < 0.08) | (np.abs(y - 6.7) < 0.08) | (np.abs(y - 10.4) < 0.08)
    dashed = lines & (np.mod(x, 12.0) < 4.0)
    edge = (np.abs(y + 11.1) < 0.1) | (np.abs(y - 14.1) < 0.1) | (np.abs(y - 0.9) < 0.08) | (np.abs(y - 2.1) < 0.08)
    refl = np.where(dashed | edge, 0.6, refl)
    return refl, np.zeros_like(refl)


def _highway_tile(ground: Ground, tile_length: float) -> Callable[[int, np.random.Generator], StaticPrimitives]:
    def build(k: int, rng: np.random.Generator) -> StaticPrimitives:
        b = _StaticBuilder(ground)
        x0, x1 = k * tile_length, (k + 1) * tile_length
        xm = (x0 + x1) / 2
        # median concrete wall, in two halves so it follows the slope
        for xa in (x0, xm):
            b.box_on_ground(xa + tile_length / 4, 1.5, tile_length / 2, 0.6, 0.9, refl=0.35, bury=0.3)
        # guard rails on posts
        for y_rail in (-13.0, 16.0):
            for xa in (x0, xm):
                b.box_on_ground(xa + tile_length / 4, y_rail, tile_length / 2, 0.08, 0.35, refl=0.45,
                                lift=0.45, kind=SURFACE_STRUCTURE)
            for xp in np.arange(x0 + 2.0, x1, 4.0):
                b.cylinder(xp, y_rail + np.sign(y_rail) * 0.1, 0.06, 0.8, refl=0.4)
        # lamp posts on the median wall
        for xp in np.arange(x0 + rng.uniform(0, 20), x1, 40.0):
            g = float(ground.height(np.array([xp]), np.array([1.5]))[0])
            b.cylinder(xp, 1.5, 0.12, 9.0, refl=0.45, base=g + 0.5)
        # embankment vegetation and trees
        for side, y_lo in ((-1, 17.0), (1, 20.0)):
            for _ in range(int(rng.integers(3, 9))):
                x = rng.uniform(x0 + 2, x1 - 2)
                y = side * rng.uniform(y_lo, y_lo + 15)
                if rng.random() < 0.5:
                    b.tree(rng, x, y)
                else:
                    g = float(ground.height(np.array([x]), np.array([y]))[0])
                    r = rng.uniform(1.0, 2.5)
                    b.ellipsoid(x, y, g + r * 0.4, r, r * rng.uniform(0.6, 1.4), r * 0.6, refl=rng.uniform(0.4, 0.6))
        if rng.random() < 0.25:  # noise barrier wall
            side_y = -20.0 if rng.random() < 0.5 else 24.0
            b.box_on_ground(xm, side_y, tile_length * rng.uniform(0.4, 0.9), 0.3, rng.uniform(3.0, 5.0), refl=0.3)
        if rng.random() < 0.15:  # overpass: deck, girders, pillars
            xc = rng.uniform(x0 + 8, x1 - 8)
            g = float(ground.height(np.array([xc]), np.array([0.0]))[0])
            clearance = rng.uniform(5.2, 6.5)
            b.box(xc, 2.5, g + clearance + 0.9 + 0.6, 12.0, 90.0, 1.2, refl=0.3)
            for dx in (-4.5, -1.5, 1.5, 4.5):
                b.box(xc + dx, 2.5, g + clearance + 0.45, 0.5, 90.0, 0.9, refl=0.35)
            for yp in (-17.0, 1.5, 20.0):
                for dx in (-3.0, 3.0):
                    b.cylinder(xc + dx, yp, 0.7, clearance + 0.5, refl=0.3, kind=SURFACE_STRUCTURE)
        elif rng.random() < 0.1:  # sign gantry
            xc = rng.uniform(x0 + 5, x1 - 5)
            g = float(ground.height(np.array([xc]), np.array([0.0]))[0])
            for yp in (-12.5, 15.5):
                b.cylinder(xc, yp, 0.25, 7.0, refl=0.4)
            b.box(xc, 1.5, g + 6.8, 0.4, 28.5, 0.4, refl=0.45, kind=SURFACE_POLE)
            b.box(xc + 0.25, -6.0, g + 5.6, 0.05, 7.0, 2.0, refl=0.85, kind=SURFACE_POLE)
        return b.build()

    return build


def _driving_highway(seed: int, object_counts=None, ego_speed: float | None = None, street_clutter: float = 0.0,
                     sensor_height: float = SENSOR_HEIGHT, low_clutter: float = 0.0, roadside_structures: float = 0.0,
                     ground_slope: float | None = None, ground_slope_bias: float = 0.0, **unused) -> Scenario:
    _no_unused(unused, "driving_highway")
    street_clutter = real(street_clutter, "street_clutter", 0, 10)
    low_clutter = real(low_clutter, "low_clutter", 0, 10)
    roadside_structures = real(roadside_structures, "roadside_structures", 0, 10)
    height = _sensor_height(sensor_height)
    rng = _rng(seed, "driving_highway", "scene")
    ground = _road_ground(rng, ground_slope, 0.02, ground_slope_bias, roughness=0.02, material=_highway_material)
    speeds = rng.uniform([24.0, 27.0, 30.0], [26.0, 30.0, 34.0])  # right, middle, left lane
    speed = float(speeds[1]) if ego_speed is None else _ego_speed(ego_speed)
    ego_y = -5.55
    g0 = float(ground.height(np.array([0.0]), np.array([ego_y]))[0])
    ego = EgoMotion(np.array([0.0, ego_y, g0 + height]), np.array([speed, 0.0, speed * ground.slope[0]]))
    defaults = {"Car": (10, 30), "Truck": (2, 8), "Bus": (0, 2), "Barrier": (0, 8), "TrafficCone": (0, 10)}
    counts = sample_object_counts(rng, defaults, object_counts)
    xr = (-80.0, 150.0)
    back = rng.uniform([22.0, 26.0, 29.0], [25.0, 29.0, 34.0])
    lanes = [
        Lane(-9.25, 0.0, speeds[0], xr, ("Car", "Truck", "Bus"), gap=10.0),
        Lane(-5.55, 0.0, speed, xr, ("Car", "Truck", "Bus"), gap=12.0),
        Lane(-1.85, 0.0, speeds[2], xr, ("Car",), gap=12.0),
        Lane(4.85, np.pi, back[2], xr, ("Car",), gap=12.0),
        Lane(8.55, np.pi, back[1], xr, ("Car", "Truck", "Bus"), gap=12.0),
        Lane(12.25, np.pi, back[0], xr, ("Car", "Truck", "Bus"), gap=10.0),
        Lane(-12.1, 0.0, 0.0, (-40.0, 120.0), ("Barrier", "TrafficCone"), gap=0.8, jitter=0.1),
    ]
    placed = _Placed()
    done = _place_in_lanes(rng, ground, lanes, counts, placed, reserved=[(1, -3.5, 3.5)])
    z0 = float(ground.z0)
    done["Drone"] = _place_drones(rng, counts["Drone"], ((-30.0, 100.0), (-12.0, 15.0), (z0 + 8.0, z0 + 18.0)),
                                  (5.0, 20.0), placed, avoid=[ego.position0])
    objects, labels = placed.build()
    tile_length = 50.0
    return Scenario("driving_highway", seed, "hdl64", ground, ego, objects, labels, 100.0, tile_length,
                    _cluttered(_cluttered(_cluttered(_highway_tile(ground, tile_length), _roadside_clutter, ground,
                                                     seed, street_clutter, tile_length), _low_clutter("driving_highway"),
                                          ground, seed, low_clutter, tile_length), _roadside_structures("driving_highway"),
                               ground, seed, roadside_structures, tile_length), done)


# ---------------------------------------------------------------------------------------------
# drone_bridge
# ---------------------------------------------------------------------------------------------
def _water_material(reflectivity: float = 0.05, dropout: float = 0.85) -> MaterialFn:
    return _uniform_material(reflectivity, dropout)


def _single_tile(build_static: Callable[[np.random.Generator], StaticPrimitives]) -> Callable[[int, np.random.Generator], StaticPrimitives]:
    def build(k: int, rng: np.random.Generator) -> StaticPrimitives:
        return build_static(rng) if k == 0 else StaticPrimitives()

    return build


def _drone_bridge(seed: int, object_counts=None, **unused) -> Scenario:
    _no_unused(unused, "drone_bridge")
    rng = _rng(seed, "drone_bridge", "scene")
    ground = Ground(0.0, np.zeros(2), np.array([0.02, 0.01]), np.array([[0.9, 0.3], [-0.4, 1.7]]),
                    rng.uniform(0, 2 * np.pi, 2), _water_material())
    bridge_x = rng.uniform(48.0, 62.0)
    deck_top = rng.uniform(11.0, 13.0)
    ego_z = deck_top - rng.uniform(1.5, 4.5)
    ego = EgoMotion.hover(rng, (0.0, rng.uniform(-3, 3), ego_z), yaw=rng.normal(0, 0.05))
    bank = rng.uniform(28.0, 36.0)

    def static(rng: np.random.Generator) -> StaticPrimitives:
        b = _StaticBuilder(ground)
        bank_top = 2.5
        for side in (-1, 1):  # river banks / quays: big boxes whose tops are the land
            b.box(100.0, side * (bank + 85.0), (bank_top - 4.0) / 2, 300.0, 170.0, bank_top + 4.0, refl=0.3, piece=30.0)
        # deck, girders, railings, lamp posts
        deck_w = rng.uniform(10.0, 14.0)
        span = 2 * bank + 120.0
        b.box(bridge_x, 0.0, deck_top - 0.6, deck_w, span, 1.2, refl=0.3)
        for gx in np.linspace(bridge_x - deck_w / 2 + 0.8, bridge_x + deck_w / 2 - 0.8, 4):
            b.box(gx, 0.0, deck_top - 1.2 - 0.8, 0.5, span, 1.6, refl=0.35)
        for rx in (bridge_x - deck_w / 2 + 0.05, bridge_x + deck_w / 2 - 0.05):
            b.box(rx, 0.0, deck_top + 0.55, 0.1, span, 1.1, refl=0.45)
            for yl in np.arange(-span / 2 + 5, span / 2, 25.0):
                b.cylinder(rx, yl, 0.1, 7.0, refl=0.4, base=deck_top)
        # pillars in the water and on the banks
        for yp in (-bank + 4.0, -bank / 3, bank / 3, bank - 4.0):
            for dx in (-deck_w / 4, deck_w / 4):
                b.cylinder(bridge_x + dx, yp, rng.uniform(0.8, 1.2), deck_top - 2.0 + 2.0, refl=0.3,
                           kind=SURFACE_STRUCTURE, base=-2.0)
        # an arch over the deck (Tyne-bridge-like), in steps, with hangers
        arch_h = rng.uniform(15.0, 25.0)
        n_seg = 24
        ys = np.linspace(-bank - 10, bank + 10, n_seg + 1)
        for xa in (bridge_x - deck_w / 2 - 0.6, bridge_x + deck_w / 2 + 0.6):
            for y_a, y_b in zip(ys[:-1], ys[1:]):
                ym = (y_a + y_b) / 2
                h = arch_h * (1.0 - (ym / (bank + 10)) ** 2)
                b.box(xa, ym, deck_top - 1.5 + h, 1.0, y_b - y_a, 1.2, refl=0.35)
                if abs(ym) < bank and h > 3.0:
                    b.cylinder(xa, ym, 0.08, h - 1.5, refl=0.4, base=deck_top)
        # trees and buildings on the banks
        for _ in range(int(rng.integers(10, 25))):
            side = rng.choice([-1, 1])
            x, y = rng.uniform(-10, 150), side * rng.uniform(bank + 3, bank + 40)
            if abs(x - bridge_x) < deck_w:
                continue
            b.cylinder(x, y, rng.uniform(0.15, 0.3), rng.uniform(2.5, 4.0), refl=0.3, base=bank_top - 0.2)
            r = rng.uniform(1.5, 3.5)
            b.ellipsoid(x, y, bank_top + 3.0 + r * 0.8, r, r, r * 1.1, refl=rng.uniform(0.4, 0.6))
        for _ in range(int(rng.integers(4, 10))):
            side = rng.choice([-1, 1])
            x, y = rng.uniform(20, 200), side * rng.uniform(bank + 45, bank + 100)
            h = rng.uniform(8, 35)
            b.box(x, y, bank_top + (h - 1) / 2, rng.uniform(10, 30), rng.uniform(10, 25), h + 1, refl=rng.uniform(0.2, 0.45))
        return b.build()

    counts = sample_object_counts(rng, {"Drone": (1, 3)}, object_counts)
    placed = _Placed()
    n = _place_drones(rng, counts["Drone"], ((10.0, bridge_x - 8.0), (-20.0, 20.0), (ego_z - 5.0, ego_z + 6.0)),
                      (0.5, 4.0), placed, avoid=[ego.position0])
    objects, labels = placed.build()
    done = {name: 0 for name in CLASSES}
    done["Drone"] = n
    return Scenario("drone_bridge", seed, "avia", ground, ego, objects, labels, 120.0, 1e4, _single_tile(static), done)


# ---------------------------------------------------------------------------------------------
# drone_lock
# ---------------------------------------------------------------------------------------------
def _drone_lock(seed: int, object_counts=None, **unused) -> Scenario:
    _no_unused(unused, "drone_lock")
    rng = _rng(seed, "drone_lock", "scene")
    ground = Ground(0.0, np.zeros(2), np.array([0.015]), np.array([[1.1, 0.4]]), rng.uniform(0, 2 * np.pi, 1),
                    _water_material(0.05, 0.8))
    half_width = rng.uniform(5.0, 7.0)
    wall_top = rng.uniform(6.0, 9.0)
    gate_x = rng.uniform(50.0, 75.0)
    ego = EgoMotion.hover(rng, (0.0, rng.uniform(-1.0, 1.0), rng.uniform(2.5, 4.5)), yaw=rng.normal(0, 0.03))

    def static(rng: np.random.Generator) -> StaticPrimitives:
        b = _StaticBuilder(ground)
        for side in (-1, 1):
            # lock wall + quay as one block whose inner face is the wall
            b.box(55.0, side * (half_width + 30.0), (wall_top - 5.0) / 2, 200.0, 60.0, wall_top + 5.0, refl=0.35,
                  piece=20.0)
            for xl in np.arange(-40.0 + rng.uniform(0, 15), 150.0, 15.0):  # ladders
                b.box(xl, side * (half_width - 0.1), wall_top / 2 - 1.0, 0.5, 0.2, wall_top + 2.0, refl=0.5,
                      kind=SURFACE_POLE)
            for xl in np.arange(-40.0, 150.0, 10.0):  # bollards and railing posts
                b.cylinder(xl, side * (half_width + 0.6), 0.25, 0.6, refl=0.4, base=wall_top)
                b.cylinder(xl + 5.0, side * (half_width + 1.5), 0.04, 1.1, refl=0.45, base=wall_top)
            b.box(55.0, side * (half_width + 1.5), wall_top + 1.05, 190.0, 0.05, 0.08, refl=0.5)
            # a hut and trees on the quay
            b.box(gate_x + rng.uniform(-8, 8), side * (half_width + rng.uniform(8, 14)), wall_top + 1.5,
                  rng.uniform(4, 8), rng.uniform(3, 6), 3.0, refl=0.3)
            for _ in range(int(rng.integers(2, 6))):
                x, y = rng.uniform(10, 120), side * rng.uniform(half_width + 5, half_width + 25)
                b.cylinder(x, y, 0.2, 3.0, refl=0.3, base=wall_top - 0.2)
                r = rng.uniform(1.5, 3.0)
                b.ellipsoid(x, y, wall_top + 2.8 + r * 0.8, r, r, r * 1.1, refl=rng.uniform(0.4, 0.6))
        # gates: the closed downstream gate ahead, the upstream one behind
        b.box(gate_x, 0.0, (wall_top + 1.0 - 3.0) / 2, 1.0, 2 * half_width, wall_top + 4.0, refl=0.3)
        b.box(gate_x + 0.3, 0.0, wall_top + 0.9, 0.1, 2 * half_width, 1.0, refl=0.5)  # walkway rail
        b.box(-25.0, 0.0, (wall_top + 1.0 - 3.0) / 2, 1.0, 2 * half_width, wall_top + 4.0, refl=0.3)
        return b.build()

    counts = sample_object_counts(rng, {"Drone": (0, 2)}, object_counts)
    placed = _Placed()
    n = _place_drones(rng, counts["Drone"], ((8.0, gate_x - 6.0), (-half_width + 1.5, half_width - 1.5), (1.5, wall_top)),
                      (0.3, 2.5), placed, avoid=[ego.position0])
    objects, labels = placed.build()
    done = {name: 0 for name in CLASSES}
    done["Drone"] = n
    return Scenario("drone_lock", seed, "avia", ground, ego, objects, labels, 100.0, 1e4, _single_tile(static), done)


def _no_unused(unused: dict, name: str) -> None:
    if unused:
        raise TypeError(f"scenario {name!r} got unexpected option(s) {sorted(unused)}")


#: Scenario builders by name: ``builder(seed, object_counts=None, **options) -> Scenario``.
SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "driving_city": _driving_city,
    "driving_highway": _driving_highway,
    "drone_bridge": _drone_bridge,
    "drone_lock": _drone_lock,
}


def build_scenario(name: str, seed: int = 0, object_counts=None, **options) -> Scenario:
    """Builds a scenario preset.

    Args:
        name (str): one of :data:`SCENARIOS`.
        seed (int): random seed.
        object_counts: see :func:`sample_object_counts`.
        **options: scenario options (the driving scenarios: ``ego_speed``, ``street_clutter``, ``low_clutter``,
            ``roadside_structures``, ``sensor_height``;
            ``driving_city``: ``pedestrian_groups``, ``crossing_pedestrians``, ``crossing_groups``,
            ``crossing_cyclists``, ``parking_lots``, ``open_ground``).

    Returns:
        Scenario.

    Raises:
        ValueError: unknown scenario name, a seed that is not an int >= 0, an ``ego_speed`` that is not
            a finite number in [0, 100] m/s.
    """
    if not isinstance(name, str) or name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}")
    return SCENARIOS[name](integer(seed, "seed", 0), object_counts=object_counts, **options)
