"""What a real spinning LiDAR reports that the ray caster alone does not: a sensor's intensity response and
the surfaces of real vehicles (NumPy only).

The ray caster sees a vehicle as a box and reports intensity as reflectivity, incidence and range. Real scans
differ in ways measured by ``benchmarks/bm_sim2real.py`` on real KITTI frames ([docs/data.md]):

* **Intensity.** KITTI's HDL-64E reports asphalt at about 0.27 near the car, falling with range. Weak
  returns are reported as exactly 0: 72 % of the returns beyond 40 m and half of those on cars. Values come in
  steps of 0.01.
* **Vehicles are not boxes.** Windows return little (glass), and a rounded roof sends grazing rays away. So
  only 14 % of a real car's returns lie in the top third of its box, against 45 % for a box.

A :class:`Realism` applies these effects to the caster's returns:

* it gives the labelled objects their shapes (:mod:`lidarops.data.shapes`): a ray that meets a box is
  followed onto the car, truck, bus, pedestrian or cyclist inside it, or on past it;
* it drops window and roof returns (the greenhouse: the upper part of a vehicle's box);
* it reads dark paint, glass and tyres as zero intensity;
* it scales intensity per surface kind and per beam, zeroes weak returns near the detection limit, and
  quantises;
* it adds street furniture and roadside clutter to driving scenes (the scenario option ``street_clutter``);
* optionally, low clutter and roadside structures: guard rails, railings, walls with wheelie bins before them, bar
  fences (``low_clutter``, ``roadside_structures``);
* optionally (the ``kitti_dr`` profile), it reports returns at depth edges between the two surfaces (mixed
  pixels), walks pedestrians in groups, draws vehicle labels tighter than their bodies, and randomises each
  scene's sensor height, beam count, dropout, range noise and intensity scale.

The simulator takes it as ``Simulator(..., realism="kitti")``. Its random numbers come from a stream of their
own, so frames without it are exactly those of before.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from lidarops.data._checks import real
from lidarops.data.shapes import SHAPES

__all__ = ["Realism", "REALISM_PRESETS", "make_realism"]


@dataclass(frozen=True)
class Realism:
    """Effects of a real sensor and real vehicles on the simulated returns.

    Attributes:
        vehicle_classes (tuple[str, ...]): classes whose boxes get a vehicle's surfaces.
        shaped_classes (tuple[str, ...]): classes whose boxes hold their real shapes
            (:data:`lidarops.data.shapes.SHAPES`: a car's hood, cabin and wheels, a walking pedestrian, a
            cyclist on a bicycle...): a ray that meets the box goes on to the shape, or past the object.
        greenhouse_from (float): height fraction of the box above which lie windows and roof.
        greenhouse_keep (float): probability that a return from a window (the greenhouse's sides) comes back.
        roof_keep (float): probability that a return from the roof (the box's top) comes back: a rounded roof
            sends grazing rays away.
        greenhouse_zero (float): probability that a greenhouse return that comes back reads 0 (glass).
        dark_paint (float): share of vehicles with dark paint.
        dark_zero, light_zero (float): probability that a body return of a dark or light vehicle reads 0.
        tyre_band (float): height fraction below which lie tyres, bumpers and the shadowed underbody.
        tyre_zero (float): probability that a return there reads 0.
        surface_gain (tuple[float, ...]): intensity gain per ``SURFACE_KINDS`` code (none, ground,
            structure, pole, vegetation, object).
        beam_gain_std (float): spread of the per-beam intensity calibration (a gain drawn once per beam).
        weak_from (float): returns beyond this fraction of their surface's detection range read 0.
        quantum (float): intensity is reported in steps of this size (0: not quantised).
        street_clutter (float): density of the clutter added to driving scenes: street furniture and shrubs in
            ``driving_city``, shrubs, saplings and posts on ``driving_highway``'s verges (the scenario option
            ``street_clutter``; 1 about one piece per 6 m of pavement; 0 none).
        low_clutter (float): density of the low clutter added to driving scenes: planters, low walls, low bushes,
            stones and verge berms, 0.2-1 m tall, beside the road (the scenario option ``low_clutter``; 1 about one
            piece per 10 m of each roadside zone; 0 none).
        roadside_structures (float): density of the roadside structures added to driving scenes: guard rails on
            posts and metal railings along the kerb, walls with wheelie bins before them and bar fences with a tall
            post along the walkway (the scenario option ``roadside_structures``; 1: 15 m free between two structures
            of a roadside zone on average; 0 none).
        mixed_pixels (float): probability that a return at a depth edge is reported somewhere between the two
            surfaces its beam straddles (a mixed pixel): the return's neighbour on the same beam, one firing before
            or after, lies at least ``mixed_gap`` farther; the range moves a uniform fraction of the way to it.
        mixed_gap (float): the depth step (m) that makes an edge.
        mount_height_jitter (float): domain randomisation of the sensor's height above the ground, drawn once per
            scene uniformly within this many metres of the scenario's (the driving scenarios' ``sensor_height``).
        ground_slope (float): domain randomisation of the road's grade in the driving scenes: the ground slopes by up
            to this along the road (rise over run; across it 0.3 of that), drawn per scene, while the sensor stays
            level, so the road ahead rises or falls in its frame as at a change of grade (the scenarios' option
            ``ground_slope``; 0: the scenarios' own, up to 0.015 in the city and 0.02 on the highway).
        ground_slope_bias (float): added to that grade (the scenarios' option ``ground_slope_bias``): the real scans'
            objects at 10-45 m stand a median 1 % of their range above the ground under the car (up to 2.7 %, the
            90th percentile), where the simulator's stand on it.
        intensity_scale_jitter (float): domain randomisation of the intensity scale: one gain per scene, drawn
            log-uniformly in ``[1 / (1 + j), 1 + j]``.
        pedestrian_groups (float): probability that a pedestrian of ``driving_city`` walks or stands with one to
            three others in single file close behind it (the scenario option ``pedestrian_groups``).
        crossing_pedestrians (float): probability that a ``driving_city`` scene has a crosswalk 5-30 m ahead with one
            to eight of its pedestrians crossing the road on it (the scenario option ``crossing_pedestrians``): the
            real scans' nearest pedestrians; on the sidewalks alone none is nearer than about 15 m in the camera's
            view. The traffic does not stop for them: meant for single frames, not long sequences.
        crossing_groups (float): probability that a pedestrian crossing the road (``crossing_pedestrians``) leads one
            to three others walking with it, side by side or in file, 0.1-0.5 m between their boxes (the scenario
            option ``crossing_groups``): the real scans' crossing pedestrians walk so, their centres 0.6-0.9 m apart.
        crossing_cyclists (float): probability that a ``driving_city`` scene has one to three of its cyclists riding
            across the road 6-40 m ahead (the scenario option ``crossing_cyclists``): seen broadside, as the real
            scans' cyclists crossing at junctions are; the bicycle lanes never show one so. Single frames, as above.
        parking_lots (float): probability that a ``driving_city`` scene has a parking lot beside the street, beyond
            the walkway (the scenario option ``parking_lots``): its cars parked across the street, at a slant or along
            it side by side, often under trees; the street's lanes park cars along the road only.
        open_ground (float): probability that a ``driving_city`` building stands behind raised open ground (a lawn or
            a terrace 0.15-0.9 m above the street, 4-14 m deep) instead of at the walkway (the scenario option
            ``open_ground``): flat returns above the road's level beside it, which hold no car.
        label_tightness (float): a vehicle's label is tighter than its body, as KITTI's annotators draw it: each
            side of the label's length and of its width moves in by a uniform amount up to this (m), drawn once
            per vehicle (the returns stay where they are: some fall just outside the label).
        beam_choices (tuple[int, ...]): domain randomisation of a spinning sensor's beams, a count drawn per scene
            from these (each equally likely): the sensor's table halved (every other beam) while it holds more, or
            with a beam added between each two while that stays within the count (64 -> 32, 64 -> 127 for 128).
            Empty: the sensor as it is.
        dropout_max (float): domain randomisation of the sensor's random dropout: per scene, uniform between the
            sensor's own and this (0: the sensor's).
        range_noise_max (float): the same for the range noise's standard deviation (m).
        pedestrian_build (float): how far pedestrians' shapes vary from the plain one, in [0, 1]: each pedestrian's
            legs are up to 1 + this times as thick, its coat's hem reaches up to 0.18 x this of its height below
            the hip, and its shoulders are up to a quarter x this narrower (uniform, per pedestrian; 0: every
            pedestrian bare-legged, without a coat, its arms held out from the body).
        hair_dropout (float): probability that a return from the top of a pedestrian's head (above 0.87 of its
            height) is lost: hair, often dark, returns less than skin and clothes (0: none lost).
        laser_offsets (bool): an HDL-64E's beams start at its lasers' heights above its origin
            (:func:`lidarops.data.sensors.hdl64_beam_offsets`), as on the real sensor; other sensors as they are.
        rotor_keep (float): probability that a return from a shaped drone's rotor discs (the top ``rotor_from`` of
            its box) comes back: two thin blades spinning at thousands of turns a minute cover a small part of the
            disc they sweep at the instant of a pulse (1: every return kept).
        rotor_from (float): height fraction of a drone's box above which lie its rotors.
        reflectivity_output (bool): the sensor reports calibrated reflectivity, as Livox sensors do, rather than a
            raw intensity: the return's strength corrected for range, so it does not fall with distance.
    """

    vehicle_classes: tuple[str, ...] = ("Car", "Truck", "Bus")
    shaped_classes: tuple[str, ...] = ("Car", "Truck", "Bus", "Pedestrian", "Cyclist")
    greenhouse_from: float = 0.62
    greenhouse_keep: float = 0.2
    roof_keep: float = 0.3
    greenhouse_zero: float = 0.7
    dark_paint: float = 0.45
    dark_zero: float = 0.7
    light_zero: float = 0.1
    tyre_band: float = 0.25
    tyre_zero: float = 0.5
    surface_gain: tuple[float, ...] = (1.0, 6.0, 1.5, 1.0, 1.0, 1.0)
    beam_gain_std: float = 0.1
    weak_from: float = 0.75
    quantum: float = 0.01
    street_clutter: float = 1.0
    low_clutter: float = 0.0
    roadside_structures: float = 0.0
    mixed_pixels: float = 0.0
    mixed_gap: float = 1.0
    mount_height_jitter: float = 0.0
    ground_slope: float = 0.0
    ground_slope_bias: float = 0.0
    intensity_scale_jitter: float = 0.0
    pedestrian_groups: float = 0.0
    crossing_pedestrians: float = 0.0
    crossing_groups: float = 0.0
    crossing_cyclists: float = 0.0
    parking_lots: float = 0.0
    open_ground: float = 0.0
    label_tightness: float = 0.0
    beam_choices: tuple[int, ...] = ()
    dropout_max: float = 0.0
    range_noise_max: float = 0.0
    pedestrian_build: float = 0.0
    hair_dropout: float = 0.0
    laser_offsets: bool = False
    rotor_keep: float = 1.0
    rotor_from: float = 0.83
    reflectivity_output: bool = False

    def __post_init__(self) -> None:
        for name in ("greenhouse_from", "greenhouse_keep", "roof_keep", "greenhouse_zero", "dark_paint", "dark_zero",
                     "light_zero", "tyre_band", "tyre_zero", "weak_from"):
            real(getattr(self, name), name, 0, 1)
        real(self.beam_gain_std, "beam_gain_std", 0, 1)
        real(self.quantum, "quantum", 0, 0.5)
        real(self.street_clutter, "street_clutter", 0, 10)
        real(self.low_clutter, "low_clutter", 0, 10)
        real(self.roadside_structures, "roadside_structures", 0, 10)
        real(self.mixed_pixels, "mixed_pixels", 0, 1)
        real(self.mixed_gap, "mixed_gap", 0.05, 100, unit=" m")
        real(self.mount_height_jitter, "mount_height_jitter", 0, 0.5, unit=" m")
        real(self.ground_slope, "ground_slope", 0, 0.1)
        real(self.ground_slope_bias, "ground_slope_bias", -0.05, 0.05)
        real(self.intensity_scale_jitter, "intensity_scale_jitter", 0, 1)
        real(self.pedestrian_groups, "pedestrian_groups", 0, 1)
        real(self.crossing_pedestrians, "crossing_pedestrians", 0, 1)
        real(self.crossing_groups, "crossing_groups", 0, 1)
        real(self.crossing_cyclists, "crossing_cyclists", 0, 1)
        real(self.parking_lots, "parking_lots", 0, 1)
        real(self.open_ground, "open_ground", 0, 1)
        real(self.label_tightness, "label_tightness", 0, 0.5, unit=" m")
        real(self.dropout_max, "dropout_max", 0, 0.9)
        real(self.range_noise_max, "range_noise_max", 0, 1, unit=" m")
        real(self.pedestrian_build, "pedestrian_build", 0, 1)
        real(self.hair_dropout, "hair_dropout", 0, 1)
        real(self.rotor_keep, "rotor_keep", 0, 1)
        real(self.rotor_from, "rotor_from", 0, 1)
        for flag in ("laser_offsets", "reflectivity_output"):
            if getattr(self, flag) not in (True, False):
                raise ValueError(f"{flag} must be True or False, got {getattr(self, flag)!r}")
        if not isinstance(self.beam_choices, tuple) or not all(
                isinstance(b, int) and not isinstance(b, bool) and 1 <= b <= 1024 for b in self.beam_choices):
            raise ValueError(f"beam_choices must be a tuple of beam counts in [1, 1024], got {self.beam_choices!r}")
        if len(self.surface_gain) != 6:
            raise ValueError(f"surface_gain must hold one gain per surface kind (6), got {self.surface_gain!r}")
        for g in self.surface_gain:
            real(g, "surface_gain", 0, 100)
        if not self.vehicle_classes or not all(isinstance(c, str) for c in self.vehicle_classes):
            raise ValueError(f"vehicle_classes must be class names, got {self.vehicle_classes!r}")
        if not isinstance(self.shaped_classes, tuple) or not all(c in SHAPES for c in self.shaped_classes):
            raise ValueError(f"shaped_classes must be a tuple of names from {sorted(SHAPES)}, got {self.shaped_classes!r}")

    def beam_gains(self, rng: np.random.Generator, beams: int) -> np.ndarray:
        """One intensity gain per beam (a sensor's calibration table), positive."""
        return np.clip(1.0 + self.beam_gain_std * rng.standard_normal(beams), 0.5, 1.5)

    def vehicle_returns(self, rng: np.random.Generator, height: np.ndarray, dark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For returns on vehicles at ``height`` (fraction of the box, 0 bottom, 1 top) of vehicles painted
        ``dark`` (bool per return): which come back, and which of those read 0."""
        u_keep, u_zero = rng.random(height.size), rng.random(height.size)
        glass = height >= self.greenhouse_from
        roof = height >= 0.98
        keep = ~glass | (u_keep < np.where(roof, self.roof_keep, self.greenhouse_keep))
        p_zero = np.where(dark, self.dark_zero, self.light_zero)
        p_zero = np.where(height < self.tyre_band, np.maximum(p_zero, self.tyre_zero), p_zero)
        p_zero = np.where(glass, self.greenhouse_zero, p_zero)
        return keep, u_zero < p_zero

    def rotor_returns(self, rng: np.random.Generator, height: np.ndarray) -> np.ndarray:
        """For returns on drones at ``height`` (fraction of the box, 0 bottom, 1 top): which come back (the rotors'
        discs lose most)."""
        return (height < self.rotor_from) | (rng.random(height.size) < self.rotor_keep)

    def scene_draws(self, rng: np.random.Generator) -> tuple[float, float]:
        """A scene's domain randomisation: ``(mounting height offset in m, intensity gain)``."""
        u = rng.uniform(-1.0, 1.0, size=2)
        return float(self.mount_height_jitter * u[0]), float(np.exp(np.log1p(self.intensity_scale_jitter) * u[1]))

    def scene_sensor(self, rng: np.random.Generator, sensor):
        """A scene's sensor under the domain randomisation of its beams (a spinning sensor), dropout and range noise,
        with its lasers' offsets (an HDL-64E) and reporting reflectivity (``reflectivity_output``)."""
        from lidarops.data.sensors import SpinningLidar, hdl64_beam_offsets

        spinning = isinstance(sensor, SpinningLidar)
        offsets = self.laser_offsets and spinning and sensor.name == "hdl64" and not sensor.beam_offsets_z
        if not (self.beam_choices and spinning or self.dropout_max or self.range_noise_max or offsets
                or self.reflectivity_output):
            return sensor
        u = rng.random(3)
        changes = {}
        if self.reflectivity_output:  # corrected for range: exp(-range / scale) stays 1
            changes["intensity_range_scale"] = 1e12
        table = np.asarray(sensor.elevations_deg if spinning else (), np.float64)
        heights = np.asarray(hdl64_beam_offsets(table) if offsets else getattr(sensor, "beam_offsets_z", ()),
                             np.float64)
        if self.beam_choices and spinning:  # the lasers' heights follow their beams
            want = self.beam_choices[min(int(u[0] * len(self.beam_choices)), len(self.beam_choices) - 1)]
            if want < len(table):  # every other beam, as many times as it takes
                while len(table) > want and len(table) > 1:
                    table, heights = table[::2], heights[::2]
            elif want > len(table):  # a beam between each two, while that stays within the count
                while 1 < len(table) and 2 * len(table) - 1 <= want:
                    between = np.arange(1, len(table))
                    if heights.size:
                        heights = np.insert(heights, between, (heights[:-1] + heights[1:]) / 2)
                    table = np.insert(table, between, (table[:-1] + table[1:]) / 2)
            changes["elevations_deg"] = tuple(float(e) for e in table)
        if heights.size:
            changes["beam_offsets_z"] = tuple(float(h) for h in heights)
        if self.dropout_max > sensor.dropout:
            changes["dropout"] = float(sensor.dropout + u[1] * (self.dropout_max - sensor.dropout))
        if self.range_noise_max > sensor.range_noise_std:
            changes["range_noise_std"] = float(sensor.range_noise_std
                                               + u[2] * (self.range_noise_max - sensor.range_noise_std))
        return sensor.replace(**changes) if changes else sensor

    def mixed_ranges(self, rng: np.random.Generator, near: np.ndarray, far: np.ndarray) -> np.ndarray:
        """For returns at ``near`` (m) whose beam neighbour lies at ``far`` (``-inf``: none): how far each moves
        along its ray (0 where it is no mixed pixel)."""
        u_mix, u_at = rng.random(near.size), rng.random(near.size)
        edge = (far >= near + self.mixed_gap) & (u_mix < self.mixed_pixels)
        return np.where(edge, u_at * (far - near), 0.0)

    def intensity(self, raw: np.ndarray, surface: np.ndarray, beam_gain: np.ndarray, weak: np.ndarray,
                  zero: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """The reported intensity: ``raw`` scaled per surface and beam (and by the scene's ``scale``), 0 where
        ``weak`` or ``zero``, quantised."""
        gain = np.asarray(self.surface_gain, np.float32)[surface] * (beam_gain.astype(np.float32) * np.float32(scale))
        x = raw * gain
        # a soft knee above 0.6: bright markings amplified by the gains approach 1 instead of piling up on it
        out = np.where(x < 0.6, x, 0.6 + 0.4 * np.tanh((x - 0.6) / 0.4)).astype(np.float32)
        out[weak | zero] = 0.0
        if self.quantum > 0:  # a quantum that does not divide 1 can round past it: clipped back
            out = np.clip(np.round(out / self.quantum) * self.quantum, 0.0, 1.0)
        return out.astype(np.float32)


#: Named profiles: ``kitti`` (the HDL-64E of KITTI, calibrated against its scans, pedestrians crossing the road
#: ahead in two scenes of five, a parking lot beside it in two of five, raised open ground before three buildings
#: of ten, low clutter and roadside structures (guard rails, railings, walls with bins, fences) beside the road;
#: not the cyclists riding across the road, which cost the real pedestrians, docs/data.md) and
#: ``kitti_dr`` (the same with mixed pixels at depth edges, pedestrians in groups as often as in the real scans,
#: vehicle labels as tight as KITTI's, the lasers' heights above the sensor's origin, pedestrians of varied builds
#: and hair, and the domain randomisation of the sensor's height, beams, dropout, range noise and intensity scale, for what
#: the real scans leave uncertain); ``avia`` (a Livox Avia on a drone, from its datasheet: no labelled real scans of
#: one were found to calibrate against): reflectivity reported in 256 steps, diffuse surfaces of 0-100 % on 0-150
#: (0-0.59), not falling with range; mixed pixels at depth edges (its beam is 0.28 deg tall); drones shaped as
#: quadcopters whose spinning rotors return a quarter of the rays that meet their discs; the domain randomisation of
#: dropout, range noise and the intensity scale.
REALISM_PRESETS = {"kitti": Realism(crossing_pedestrians=0.4, parking_lots=0.4, open_ground=0.3, low_clutter=2.0,
                                     roadside_structures=0.7),
                   "kitti_dr": Realism(mixed_pixels=0.5, mount_height_jitter=0.2, intensity_scale_jitter=0.3,
                                       pedestrian_groups=0.3, label_tightness=0.07, beam_choices=(32, 64, 64, 128),
                                       dropout_max=0.2, range_noise_max=0.05, laser_offsets=True,
                                       pedestrian_build=1.0, hair_dropout=0.4, low_clutter=2.0,
                                       roadside_structures=0.7, crossing_pedestrians=0.4,
                                       parking_lots=0.4, open_ground=0.3),
                   "avia": Realism(shaped_classes=("Car", "Truck", "Bus", "Pedestrian", "Cyclist", "Drone"),
                                   surface_gain=(0.59,) * 6, beam_gain_std=0.02, weak_from=1.0, quantum=1 / 255,
                                   street_clutter=0.0, mixed_pixels=0.3, mixed_gap=0.5, rotor_keep=0.25,
                                   reflectivity_output=True, intensity_scale_jitter=0.2, dropout_max=0.1,
                                   range_noise_max=0.04)}


def make_realism(realism: "str | Realism | None") -> Realism | None:
    """``None``, a preset name, a preset with fields changed (``"kitti:crossing_groups=0.6,low_clutter=1"``; a
    tuple field's items joined by ``/``: ``beam_choices=32/64``; a flag ``true`` or ``false``) or a
    :class:`Realism` (returned as is)."""
    if realism is None or isinstance(realism, Realism):
        return realism
    if isinstance(realism, str):
        name, colon, changes = realism.partition(":")
        if name in REALISM_PRESETS and not colon:
            return dataclasses.replace(REALISM_PRESETS[name])
        if name in REALISM_PRESETS and changes:
            return dataclasses.replace(REALISM_PRESETS[name], **_parse_fields(realism, changes))
    raise ValueError(f"realism must be None, a Realism, one of {sorted(REALISM_PRESETS)} or one with fields changed "
                     f"('kitti:crossing_groups=0.6'), got {realism!r}")


def _parse_fields(text: str, changes: str) -> dict:
    """``field=value,...`` of a profile string, each value read as its field's type."""
    kinds = {f.name: f.type for f in dataclasses.fields(Realism)}
    out: dict = {}
    for item in changes.split(","):
        key, eq, value = (part.strip() for part in item.partition("="))
        if not eq or not key or not value:
            raise ValueError(f"realism {text!r}: expected preset:field=value,..., got {item!r}")
        if key not in kinds:
            raise ValueError(f"realism {text!r}: {key!r} is not a Realism field (fields: {', '.join(kinds)})")
        kind = str(kinds[key])
        try:
            if kind == "bool":
                if value.lower() not in ("true", "false"):
                    raise ValueError(value)
                out[key] = value.lower() == "true"
            elif kind.startswith("tuple"):
                cast = int if "int" in kind else float if "float" in kind else str
                out[key] = tuple(cast(v) for v in value.split("/") if v) if value != "()" else ()
            else:
                out[key] = float(value)
        except ValueError:
            raise ValueError(f"realism {text!r}: {key}={value!r} is not a {kind}") from None
    return out
