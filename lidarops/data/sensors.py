"""LiDAR sensor models: where each ray points and when it fires (NumPy only).

Two families, both described by a *firing* sequence: firing ``k`` happens at ``t = k / firing_rate``
seconds and emits ``rays_per_firing`` rays at once.

* :class:`SpinningLidar` -- a multi-beam rotating sensor (one firing = one column of all beams).
  Presets :func:`hdl64` (KITTI's Velodyne HDL-64E) and :func:`pandar64` (PandaSet's Hesai Pandar64).
  The head turns clockwise seen from above; a sweep starts and ends at the rear (azimuth +-180 deg) and
  faces forward (+x) half way, like KITTI's scans.
* :class:`RisleyLidar` -- a two-prism Risley scanner drawing a non-repetitive rosette.  Preset
  :func:`avia` (Livox Avia: 70.4 x 77.2 deg, 240,000 points/s, 6 channels).  Each prism deflects the
  beam by a fixed angle in a direction that turns with the prism; the sum of the two counter-rotating
  deflections draws petals through the centre whose orientation drifts, so the covered part of the
  field of view keeps growing with integration time.

Sensor noise parameters (range noise, dropout, max range, intensity) live on the sensor; the simulator
applies them.  Every preset function takes keyword overrides, e.g. ``hdl64(range_noise_std=0.0)``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from lidarops.data._checks import integer, real

__all__ = [
    "LidarSensor",
    "SpinningLidar",
    "RisleyLidar",
    "hdl64",
    "hdl64_beam_offsets",
    "pandar64",
    "avia",
    "SENSOR_PRESETS",
    "make_sensor",
]


@dataclass(frozen=True)
class LidarSensor:
    """Parameters shared by all sensors.

    Attributes:
        name (str): preset name.
        max_range (float): range (m) at which a target of reflectivity ``reference_reflectivity`` seen
            head-on is still detected; darker or grazing targets drop out earlier (``range ~ power^(1/4)``).
        min_range (float): closer returns are discarded (m).
        range_noise_std (float): Gaussian range noise (m), along the ray.
        dropout (float): probability that a return is lost at random.
        intensity_noise_std (float): Gaussian noise added to the [0, 1] intensity.
        reference_reflectivity (float): reflectivity at which ``max_range`` is specified.
        intensity_range_scale (float): intensity decays as ``exp(-range / scale)``.
        frame_period (float): seconds per frame (one sweep, or one integration window).
    """

    name: str = "lidar"
    max_range: float = 120.0
    min_range: float = 0.9
    range_noise_std: float = 0.02
    dropout: float = 0.02
    intensity_noise_std: float = 0.02
    reference_reflectivity: float = 0.8
    intensity_range_scale: float = 250.0
    frame_period: float = 0.1

    def __post_init__(self) -> None:
        # a NaN or negative parameter would not fail here but deep in the ray caster (or never: a NaN
        # range silently drops every return), so each is checked where the sensor is made
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a str, got {self.name!r}")
        real(self.max_range, "max_range", 0, lo_open=True, unit=" m")
        real(self.min_range, "min_range", 0, self.max_range, hi_open=True, unit=" m (below max_range)")
        real(self.range_noise_std, "range_noise_std", 0, unit=" m")
        real(self.dropout, "dropout", 0, 1, hi_open=True)
        real(self.intensity_noise_std, "intensity_noise_std", 0)
        real(self.reference_reflectivity, "reference_reflectivity", 0, 1, lo_open=True)
        real(self.intensity_range_scale, "intensity_range_scale", 0, lo_open=True, unit=" m")
        real(self.frame_period, "frame_period", 0, 3600, lo_open=True, unit=" s")

    def _check_firings_per_frame(self) -> None:
        if self.firings_per_frame < 1:
            raise ValueError(f"a frame must hold at least one firing: firing_rate * frame_period is "
                             f"{self.firing_rate * self.frame_period:g}")

    # -- firing schedule (implemented by subclasses) -----------------------------------------
    @property
    def firing_rate(self) -> float:
        """Firings per second."""
        raise NotImplementedError

    @property
    def rays_per_firing(self) -> int:
        """Rays emitted per firing."""
        raise NotImplementedError

    @property
    def firings_per_frame(self) -> int:
        """Firings in one frame (an integer by construction)."""
        return int(round(self.firing_rate * self.frame_period))

    @property
    def points_per_second(self) -> float:
        """Rays per second."""
        return self.firing_rate * self.rays_per_firing

    def firing_rate_fraction(self) -> Fraction:
        """``firing_rate`` as an exact fraction (for exact block boundaries)."""
        return Fraction(repr(float(self.firing_rate))).limit_denominator(10**6)

    def directions(self, firing_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray directions of firings in the sensor frame.

        Args:
            firing_index (ndarray int64[K]): firing indices.

        Returns:
            dirs (ndarray float64[K, R, 3]): unit directions (x forward, y left, z up).
            ring (ndarray int16[R]): beam / channel index of each of the R rays of a firing.
        """
        raise NotImplementedError

    def beam_origins(self) -> np.ndarray:
        """Where each of the ``rays_per_firing`` rays of a firing starts, in the sensor frame (m): the sensor's
        origin unless its lasers sit apart from it (a spinning sensor's ``beam_offsets_z``).

        Returns:
            ndarray float64[R, 3].
        """
        return np.zeros((self.rays_per_firing, 3))

    def in_field_of_view(self, dirs: np.ndarray) -> np.ndarray:
        """Whether sensor-frame directions lie in the field of view (with a small tolerance).

        Args:
            dirs (ndarray[N, 3]): directions or points in the sensor frame.

        Returns:
            ndarray bool[N].
        """
        raise NotImplementedError

    def replace(self, **changes) -> "LidarSensor":
        """A copy with some fields changed (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)


def _check_elevations(elevations_deg) -> None:
    """A non-empty sequence of beam elevations, each a number of degrees in [-90, 90]."""
    if isinstance(elevations_deg, (str, bytes)) or not hasattr(elevations_deg, "__len__") or not len(elevations_deg):
        raise ValueError(f"elevations_deg must be a non-empty sequence of angles in degrees, got {elevations_deg!r}")
    for i, e in enumerate(elevations_deg):
        real(e, f"elevations_deg[{i}]", -90, 90, unit=" degrees")


@dataclass(frozen=True)
class SpinningLidar(LidarSensor):
    """Multi-beam rotating LiDAR.

    Attributes:
        elevations_deg (tuple[float, ...]): beam elevation angles, degrees (beam ``i`` = ring ``i``).
        columns_per_rev (int): firings (columns) per revolution.
        rotation_hz (float): revolutions per second (= frames per second).
        beam_offsets_z (tuple[float, ...]): each beam's origin above the sensor's origin (m): a real HDL-64E's
            lasers sit 0.1-0.2 m above the point its coordinates are measured from, so a beam's returns are
            not on one cone through the origin (:func:`hdl64_beam_offsets`). Empty: every beam starts at the
            origin.
    """

    elevations_deg: tuple[float, ...] = field(default_factory=tuple)
    columns_per_rev: int = 2083
    rotation_hz: float = 10.0
    beam_offsets_z: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        _check_elevations(self.elevations_deg)
        if isinstance(self.beam_offsets_z, (str, bytes)) or not hasattr(self.beam_offsets_z, "__len__") \
                or len(self.beam_offsets_z) not in (0, len(self.elevations_deg)):
            raise ValueError(f"beam_offsets_z must be empty or hold one offset per beam ({len(self.elevations_deg)}), "
                             f"got {self.beam_offsets_z!r}")
        for i, h in enumerate(self.beam_offsets_z):
            real(h, f"beam_offsets_z[{i}]", -1, 1, unit=" m")
        integer(self.columns_per_rev, "columns_per_rev", 1, 10**6)
        real(self.rotation_hz, "rotation_hz", 0, 1000, lo_open=True, unit=" Hz")
        object.__setattr__(self, "frame_period", 1.0 / self.rotation_hz)
        super().__post_init__()
        el = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))
        object.__setattr__(self, "_cos_el", np.cos(el))
        object.__setattr__(self, "_sin_el", np.sin(el))

    @property
    def firing_rate(self) -> float:
        return float(self.columns_per_rev * self.rotation_hz)

    @property
    def rays_per_firing(self) -> int:
        return len(self.elevations_deg)

    @property
    def firings_per_frame(self) -> int:
        return int(self.columns_per_rev)

    def beam_origins(self) -> np.ndarray:
        origins = np.zeros((self.rays_per_firing, 3))
        if self.beam_offsets_z:
            origins[:, 2] = self.beam_offsets_z
        return origins

    def azimuth(self, firing_index: np.ndarray) -> np.ndarray:
        """Azimuth (rad, ``atan2(y, x)`` in the sensor frame) of firings: +pi at the start of a sweep,
        decreasing (clockwise) to 0 (forward) half way.

        Args:
            firing_index (ndarray int64[K]).

        Returns:
            ndarray float64[K] in ``(-pi, pi]``.
        """
        column = np.mod(np.asarray(firing_index, dtype=np.int64), self.columns_per_rev)
        return np.pi - 2.0 * np.pi * column / self.columns_per_rev

    def directions(self, firing_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        az = self.azimuth(firing_index)
        ca, sa = np.cos(az)[:, None], np.sin(az)[:, None]
        dirs = np.empty((az.shape[0], self.rays_per_firing, 3))
        dirs[..., 0] = ca * self._cos_el
        dirs[..., 1] = sa * self._cos_el
        dirs[..., 2] = self._sin_el
        return dirs, np.arange(self.rays_per_firing, dtype=np.int16)

    def in_field_of_view(self, dirs: np.ndarray) -> np.ndarray:
        dirs = np.asarray(dirs, dtype=np.float64)
        el = np.degrees(np.arctan2(dirs[:, 2], np.hypot(dirs[:, 0], dirs[:, 1])))
        tol = 1e-3
        return (el >= min(self.elevations_deg) - tol) & (el <= max(self.elevations_deg) + tol)


@dataclass(frozen=True)
class RisleyLidar(LidarSensor):
    """Two-prism Risley scanner (non-repetitive rosette).

    The deflection of channel ``c`` at time ``t`` is ``u = (e^{i theta1} + e^{i theta2}) / 2`` (|u| <= 1)
    with ``theta_j = 2 pi f_j t + phase_j(c)``; the ray's azimuth is ``u_x * fov_h / 2`` and its
    elevation ``u_y * fov_v / 2``.  With counter-rotating prisms (``f1 > 0 > f2``) and an irrational
    speed ratio the pattern never repeats.

    Attributes:
        fov_h_deg (float): horizontal field of view, degrees.
        fov_v_deg (float): vertical field of view, degrees.
        points_per_s (float): rays per second, all channels together.
        channels (int): lasers firing together.
        prism_hz (tuple[float, float]): prism rotation rates, Hz (signed).
    """

    fov_h_deg: float = 70.4
    fov_v_deg: float = 77.2
    points_per_s: float = 240_000.0
    channels: int = 6
    prism_hz: tuple[float, float] = (121.57, -77.73)

    def __post_init__(self) -> None:
        super().__post_init__()
        real(self.fov_h_deg, "fov_h_deg", 0, 180, lo_open=True, hi_open=True, unit=" degrees")
        real(self.fov_v_deg, "fov_v_deg", 0, 180, lo_open=True, hi_open=True, unit=" degrees")
        integer(self.channels, "channels", 1, 1024)
        real(self.points_per_s, "points_per_s", 0, 1e8, lo_open=True)
        if isinstance(self.prism_hz, (str, bytes)) or not hasattr(self.prism_hz, "__len__") or len(self.prism_hz) != 2:
            raise ValueError(f"prism_hz must be two rotation rates (Hz), got {self.prism_hz!r}")
        for i, hz in enumerate(self.prism_hz):
            real(hz, f"prism_hz[{i}]", -1e5, 1e5, unit=" Hz")
        self._check_firings_per_frame()

    @property
    def firing_rate(self) -> float:
        return float(self.points_per_s / self.channels)

    @property
    def rays_per_firing(self) -> int:
        return int(self.channels)

    def angles(self, firing_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Azimuth and elevation (rad) of every ray of some firings.

        Args:
            firing_index (ndarray int64[K]).

        Returns:
            azimuth, elevation (ndarray float64[K, channels]).
        """
        az, el = self._angles_by_channel(firing_index)
        return az.T, el.T

    def _angles_by_channel(self, firing_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Azimuth and elevation as ``[channels, K]`` arrays: the long axis innermost, which NumPy's
        elementwise loops run several times faster than ``[K, 6]``.

        The deflection is ``u = (e^{i theta1} + e^{i theta2}) / 2`` with ``theta_j = 2 pi turns_j(k) +
        offset_j(c)``; the cosines and sines are taken per firing and per channel and combined with the
        angle-addition formulas (4 trigonometric calls per firing instead of 4 per ray; the same values
        up to rounding).
        """
        k = np.asarray(firing_index, dtype=np.int64)
        rate = self.firing_rate
        c = np.arange(self.channels)
        orient = np.pi * c / self.channels  # petals of different channels point different ways
        petal = 2.0 * np.pi * 0.6180339887 * c / self.channels
        ux = np.zeros((self.channels, k.shape[0]))
        uy = np.zeros((self.channels, k.shape[0]))
        for hz, offset in ((self.prism_hz[0], orient + petal), (self.prism_hz[1], orient - petal)):
            turn = 2.0 * np.pi * np.mod(hz * (k / rate), 1.0)
            ct, st = np.cos(turn), np.sin(turn)
            co, so = np.cos(offset)[:, None], np.sin(offset)[:, None]
            ux += co * ct - so * st
            uy += co * st + so * ct
        ux *= 0.5 * np.deg2rad(self.fov_h_deg) / 2.0
        uy *= 0.5 * np.deg2rad(self.fov_v_deg) / 2.0
        return ux, uy

    def directions(self, firing_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        az, el = self._angles_by_channel(firing_index)
        dirs = np.empty((az.shape[1], self.channels, 3))
        xyz = dirs.transpose(2, 1, 0)  # [3, channels, K] view
        # within +-60 deg the cosine is >= 0.5 and sqrt(1 - sin^2) is as accurate as np.cos (to an ulp or two),
        # for one libm call per ray fewer
        se, sa = np.sin(el), np.sin(az)
        ce = np.sqrt(1.0 - se * se) if self.fov_v_deg <= 120.0 else np.cos(el)
        ca = np.sqrt(1.0 - sa * sa) if self.fov_h_deg <= 120.0 else np.cos(az)
        np.multiply(ce, ca, out=xyz[0])
        np.multiply(ce, sa, out=xyz[1])
        xyz[2] = se
        return dirs, np.arange(self.channels, dtype=np.int16)

    def in_field_of_view(self, dirs: np.ndarray) -> np.ndarray:
        dirs = np.asarray(dirs, dtype=np.float64)
        az = np.arctan2(dirs[:, 1], dirs[:, 0])
        el = np.arctan2(dirs[:, 2], np.hypot(dirs[:, 0], dirs[:, 1]))
        tol = 1e-6
        return (np.abs(az) <= np.deg2rad(self.fov_h_deg) / 2 + tol) & (
            np.abs(el) <= np.deg2rad(self.fov_v_deg) / 2 + tol
        )


def _hdl64_elevations() -> tuple[float, ...]:
    upper = np.linspace(2.0, -8.33, 32)  # upper block: ~1/3 deg spacing
    lower = np.linspace(-8.83, -24.9, 32)  # lower block: ~1/2 deg spacing
    return tuple(float(x) for x in np.concatenate([upper, lower]))


def _pandar64_elevations() -> tuple[float, ...]:
    top = [14.882, 11.032, 8.059, 5.057, 3.040, 2.028]
    dense = list(2.028 - 0.167 * np.arange(1, 49))  # 0.167 deg spacing from ~1.86 to ~-6.0
    low = [-7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0, -19.0, -25.0]
    return tuple(float(x) for x in top + dense + low)


def hdl64_beam_offsets(elevations_deg, lower_from: int | None = None) -> tuple[float, ...]:
    """The HDL-64E's laser heights above its measuring origin (m), one per beam of ``elevations_deg``.

    The sensor's two blocks of 32 lasers sit at different heights, and within a block a laser's height grows
    with its elevation. A published HDL-64E S2 calibration (ros-drivers/velodyne,
    ``velodyne_pointcloud/params/64e_s2.1-sztaki.yaml``, ``vert_offset_correction``) puts the upper block's
    lasers at 0.196-0.213 m and the lower block's at 0.105-0.124 m, each block on a line in the elevation to
    within a millimetre. This fits those lines: 0.2066 + 0.00126 e (upper) and 0.1350 + 0.00119 e (lower), e the
    elevation in degrees.

    Args:
        elevations_deg (sequence of float): the beams' elevations, upper block first.
        lower_from (int, optional): the first beam of the lower block (default: half the beams).
    """
    _check_elevations(elevations_deg)
    e = np.asarray(elevations_deg, dtype=np.float64)
    first = len(e) // 2 if lower_from is None else integer(lower_from, "lower_from", 0, len(e))
    lower = np.arange(len(e)) >= first
    return tuple(float(h) for h in np.where(lower, 0.1350 + 0.00119 * e, 0.2066 + 0.00126 * e))


def hdl64(laser_offsets: bool = False, **overrides) -> SpinningLidar:
    """Velodyne HDL-64E as in KITTI: 64 beams from +2 to -24.9 deg, 10 Hz, 2083 columns per turn
    (about 133k rays, about 120k returns per sweep), 120 m range, 2 cm noise. ``laser_offsets``: each beam
    starts at its laser's height above the origin (:func:`hdl64_beam_offsets`), as on the real sensor."""
    if laser_offsets not in (True, False):
        raise ValueError(f"laser_offsets must be True or False, got {laser_offsets!r}")
    params = dict(name="hdl64", elevations_deg=_hdl64_elevations(), columns_per_rev=2083, rotation_hz=10.0,
                  max_range=120.0, min_range=0.9, range_noise_std=0.02, dropout=0.02)
    params.update(overrides)
    if laser_offsets and "beam_offsets_z" not in overrides:
        params["beam_offsets_z"] = hdl64_beam_offsets(params["elevations_deg"])
    return SpinningLidar(**params)


def pandar64(**overrides) -> SpinningLidar:
    """Hesai Pandar64 as in PandaSet: 64 beams from +15 to -25 deg (dense near the horizon), 10 Hz,
    1800 columns per turn (0.2 deg), 200 m range."""
    params = dict(name="pandar64", elevations_deg=_pandar64_elevations(), columns_per_rev=1800, rotation_hz=10.0,
                  max_range=200.0, min_range=0.3, range_noise_std=0.02, dropout=0.02)
    params.update(overrides)
    return SpinningLidar(**params)


def avia(**overrides) -> RisleyLidar:
    """Livox Avia (non-repetitive scan): 70.4 x 77.2 deg, 240,000 points/s, 6 channels, 100 ms frames,
    320 m range for 80 % reflectivity (about 190 m at 10 %), 2 cm noise."""
    params = dict(name="avia", fov_h_deg=70.4, fov_v_deg=77.2, points_per_s=240_000.0, channels=6,
                  max_range=320.0, min_range=1.0, range_noise_std=0.02, dropout=0.01, frame_period=0.1)
    params.update(overrides)
    return RisleyLidar(**params)


#: Sensor presets by name.
SENSOR_PRESETS = {"hdl64": hdl64, "pandar64": pandar64, "avia": avia}


def make_sensor(sensor: "str | LidarSensor") -> LidarSensor:
    """A sensor from a preset name or an existing sensor object.

    Args:
        sensor (str or LidarSensor): ``"hdl64"``, ``"pandar64"``, ``"avia"`` or a sensor.

    Returns:
        LidarSensor.

    Raises:
        ValueError: for an unknown preset name.
    """
    if isinstance(sensor, LidarSensor):
        return sensor
    try:
        return SENSOR_PRESETS[str(sensor)]()
    except KeyError:
        raise ValueError(f"unknown sensor {sensor!r}; presets are {sorted(SENSOR_PRESETS)}") from None
