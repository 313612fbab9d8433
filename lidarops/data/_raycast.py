"""Vectorised ray casting against the ground, oriented (moving) boxes, vertical cylinders and foliage
ellipsoids (NumPy only).

Culling: rays are sorted by azimuth once; every primitive gets a bounding vertical cylinder (grown by
its motion during the batch and by the spread of the ray origins), which subtends an azimuth window
and an elevation window seen from the batch's mean origin.  ``searchsorted`` turns each azimuth window
into a slice of the sorted rays, the slices become (ray, primitive) candidate pairs in one vectorised
step, the elevation window thins them, and only the survivors get the exact intersection test.  The
nearest hit per ray wins (``np.minimum.at``), so occlusion is exact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidarops.data.scene import (
    SURFACE_GROUND,
    SURFACE_NONE,
    SURFACE_VEGETATION,
    BoxSet,
    CylinderSet,
    EllipsoidSet,
    Ground,
)

__all__ = ["RayHits", "cast_rays", "intersect_ground"]

_EMPTY_I = np.zeros(0, dtype=np.int64)


@dataclass
class RayHits:
    """Nearest hit of every ray.

    Attributes:
        distance (float64[N]): distance along the ray (``inf``: no hit).
        surface (uint8[N]): surface code of the hit (``SURFACE_NONE`` for no hit).
        object_index (int32[N]): labelled object hit (-1 otherwise).
        cos_incidence (float64[N]): |cos| of the angle between ray and surface normal.
        reflectivity (float64[N]): reflectivity of the surface hit.
        extra_dropout (float64[N]): material-specific dropout probability (water...).
        object_rays (int64[K]), object_visible (int64[K]): per labelled object, rays whose line crosses
            its box, and rays whose nearest hit is the object (for visibility / occlusion levels).
    """

    distance: np.ndarray
    surface: np.ndarray
    object_index: np.ndarray
    cos_incidence: np.ndarray
    reflectivity: np.ndarray
    extra_dropout: np.ndarray
    object_rays: np.ndarray
    object_visible: np.ndarray


def intersect_ground(origins: np.ndarray, dirs: np.ndarray, ground: Ground, max_distance: float,
                     iterations: int = 3, tolerance: float = 2e-4) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with the ground height field.

    Starts from the intersection with the ground's plane part and refines with Newton steps on
    ``f(s) = o_z + s d_z - g(o_xy + s d_xy)``; rays that do not converge to ``|f| < tolerance`` (very
    grazing rays) get no ground hit.

    Args:
        origins (ndarray float64[N, 3]), dirs (ndarray float64[N, 3]): rays (unit directions).
        ground (Ground): height field.
        max_distance (float): farther hits are ignored.
        iterations (int): Newton steps.
        tolerance (float): accepted |height error| in metres.

    Returns:
        distance (ndarray float64[N], inf for no hit), cos_incidence (ndarray float64[N]).
    """
    n = origins.shape[0]
    distance = np.full(n, np.inf)
    cos_inc = np.zeros(n)
    a, b = ground.slope
    denom = dirs[:, 2] - a * dirs[:, 0] - b * dirs[:, 1]
    h0 = ground.linear(origins[:, 0], origins[:, 1]) - origins[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_plane = h0 / denom
    idx = np.flatnonzero((denom < -1e-9) & (s_plane > 0) & (s_plane < max_distance * 1.2))
    if idx.size == 0:
        return distance, cos_inc
    o = np.take(origins, idx, axis=0)
    d = np.take(dirs, idx, axis=0)
    s = s_plane[idx]
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    # Newton on the rays not yet converged; |f| < tolerance is the convergence test
    gx = np.empty(idx.size)
    gy = np.empty(idx.size)
    converged = np.zeros(idx.size, dtype=bool)
    active = None  # None: all rays (saves the gathers while nothing has converged)
    for step in range(iterations + 1):
        if active is None:
            zg, gxa, gya = ground.height_and_gradient(ox + s * dx, oy + s * dy)
            f = oz + s * dz - zg
            gx[:], gy[:] = gxa, gya
            done = np.abs(f) < tolerance
            converged |= done
            todo = np.flatnonzero(~done)
        else:
            sa = s[active]
            zg, gxa, gya = ground.height_and_gradient(ox[active] + sa * dx[active], oy[active] + sa * dy[active])
            f = oz[active] + sa * dz[active] - zg
            gx[active] = gxa
            gy[active] = gya
            done = np.abs(f) < tolerance
            converged[active[done]] = True
            todo = active[~done]
            f = f[~done]
        if step == iterations or not ground.wave_amp.size or todo.size == 0:
            break
        if active is None:
            f = f[todo]
        active = todo
        fp = np.minimum(dz[active] - gx[active] * dx[active] - gy[active] * dy[active], -1e-6)
        s[active] = s[active] - f / fp
    ok = converged & (s > 0) & (s <= max_distance)
    normal_norm = np.sqrt(gx * gx + gy * gy + 1.0)
    cos = np.abs(-gx * dx - gy * dy + dz) / normal_norm
    distance[idx[ok]] = s[ok]
    cos_inc[idx[ok]] = cos[ok]
    return distance, cos_inc


@dataclass
class _RayIndex:
    """Rays sorted by (elevation band, azimuth): ``key = band * 8 + azimuth + pi`` (azimuth + pi < 8)."""

    key_sorted: np.ndarray
    order: np.ndarray
    elevation: np.ndarray
    el_min: float
    band_width: float
    bands: int

    @staticmethod
    def build(azimuth: np.ndarray, elevation: np.ndarray, bands: int = 16) -> "_RayIndex":
        el_min, el_max = float(elevation.min()), float(elevation.max())
        width = max((el_max - el_min) / bands, 1e-6)
        band = np.minimum(((elevation - el_min) / width).astype(np.int64), bands - 1)
        key = band * 8.0 + (azimuth.astype(np.float64) + np.pi)
        order = np.argsort(key)
        return _RayIndex(key[order], order, elevation, el_min, width, bands)

    def band_of(self, el: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((el - self.el_min) / self.band_width), 0, self.bands - 1).astype(np.int64)


def _candidate_pairs(
    index: _RayIndex,
    center_xy: np.ndarray,
    radius_xy: np.ndarray,
    z_lo: np.ndarray,
    z_hi: np.ndarray,
    origin: np.ndarray,
    max_distance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(ray, primitive) pairs whose ray direction falls in the primitive's angular window."""
    p = center_xy.shape[0]
    if p == 0 or index.order.size == 0:
        return _EMPTY_I, _EMPTY_I
    rel = center_xy - origin[:2]
    dist_h = np.hypot(rel[:, 0], rel[:, 1])
    phi = np.arctan2(rel[:, 1], rel[:, 0])
    ratio = radius_xy / np.maximum(dist_h, 1e-12)
    full = ratio >= 1.0
    half_width = np.where(full, np.pi, np.arcsin(np.minimum(ratio, 1.0)))
    d_min = np.maximum(dist_h - radius_xy, 0.0)
    d_max = dist_h + radius_xy
    dz_hi = z_hi - origin[2]
    dz_lo = z_lo - origin[2]
    el_hi = np.arctan2(dz_hi, np.where(dz_hi >= 0, d_min, d_max)) + 1e-5
    el_lo = np.arctan2(dz_lo, np.where(dz_lo >= 0, d_max, d_min)) - 1e-5
    gap_z = np.maximum(np.maximum(dz_lo, -dz_hi), 0.0)
    live = np.flatnonzero(np.hypot(d_min, gap_z) <= max_distance)
    if live.size == 0:
        return _EMPTY_I, _EMPTY_I
    # one window per (primitive, elevation band it overlaps)
    b_lo = index.band_of(el_lo[live])
    b_hi = index.band_of(el_hi[live])
    n_bands = b_hi - b_lo + 1
    prim_b = np.repeat(live, n_bands)
    band = np.repeat(b_lo - np.cumsum(n_bands) + n_bands, n_bands) + np.arange(int(n_bands.sum()))
    base = band * 8.0 + np.pi
    lo = np.where(full[prim_b], -4.0, phi[prim_b] - half_width[prim_b] - 1e-5)
    hi = np.where(full[prim_b], 4.0, phi[prim_b] + half_width[prim_b] + 1e-5)
    # the window itself (clipped to the band), plus the parts that wrap around +-pi
    win_lo = np.concatenate([base + np.maximum(lo, -np.pi - 1e-3), np.where(lo < -np.pi, base + lo + 2 * np.pi, np.inf),
                             base - np.pi - 1e-3])
    win_hi = np.concatenate([base + np.minimum(hi, np.pi + 1e-3), base + np.pi + 1e-3,
                             np.where(hi > np.pi, base + hi - 2 * np.pi, -np.inf)])
    starts = np.searchsorted(index.key_sorted, win_lo, side="left")
    ends = np.searchsorted(index.key_sorted, win_hi, side="right")
    counts = np.maximum(ends - starts, 0)
    total = int(counts.sum())
    if total == 0:
        return _EMPTY_I, _EMPTY_I
    prim = np.repeat(np.tile(prim_b, 3), counts)
    offsets = np.cumsum(counts) - counts
    pos = np.arange(total) - np.repeat(offsets - starts, counts)
    ray = np.take(index.order, pos)
    el = np.take(index.elevation, ray)
    ok = (el >= np.take(el_lo, prim)) & (el <= np.take(el_hi, prim))
    return ray[ok], prim[ok]


def _slab(lo: np.ndarray, ld: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    inv = 1.0 / np.where(ld == 0.0, 1e-300, ld)
    a = (-half - lo) * inv
    b = (half - lo) * inv
    return np.minimum(a, b), np.maximum(a, b)


def _intersect_boxes(o, d, t, boxes: BoxSet, prim, cos_yaw, sin_yaw):
    """Slab test in the box frame at each ray's time. Returns (distance or inf, cos_incidence).

    ``cos_yaw``/``sin_yaw`` hold the per-box trigonometry of the initial yaw; boxes with a yaw rate get
    theirs recomputed per pair.
    """
    vel = np.take(boxes.velocity, prim, axis=0)
    center = np.take(boxes.center, prim, axis=0)
    cy, sy = np.take(cos_yaw, prim), np.take(sin_yaw, prim)
    rate = np.take(boxes.yaw_rate, prim)
    turning = np.flatnonzero(rate != 0.0)
    if turning.size:
        yaw = boxes.yaw[prim[turning]] + rate[turning] * t[turning]
        cy[turning] = np.cos(yaw)
        sy[turning] = np.sin(yaw)
    px = o[:, 0] - (center[:, 0] + vel[:, 0] * t)
    py = o[:, 1] - (center[:, 1] + vel[:, 1] * t)
    pz = o[:, 2] - (center[:, 2] + vel[:, 2] * t)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    ldx = cy * dx + sy * dy
    ldy = cy * dy - sy * dx
    half = np.take(boxes.half, prim, axis=0)
    nx, fx = _slab(cy * px + sy * py, ldx, half[:, 0])
    ny, fy = _slab(cy * py - sy * px, ldy, half[:, 1])
    nz, fz = _slab(pz, dz, half[:, 2])
    t_near = np.maximum(np.maximum(nx, ny), nz)
    t_far = np.minimum(np.minimum(fx, fy), fz)
    hit = (t_near <= t_far) & (t_near > 0)
    cos = np.where(t_near == nx, np.abs(ldx), np.where(t_near == ny, np.abs(ldy), np.abs(dz)))
    return np.where(hit, t_near, np.inf), cos


def _intersect_cylinders(o, d, cyl: CylinderSet, prim):
    """Vertical finite cylinders with caps. Returns (distance or inf, cos_incidence)."""
    cx = np.take(cyl.center_xy, prim, axis=0)
    lx, ly = o[:, 0] - cx[:, 0], o[:, 1] - cx[:, 1]
    r = np.take(cyl.radius, prim)
    z0, z1 = np.take(cyl.z_min, prim), np.take(cyl.z_max, prim)
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    bh = lx * d[:, 0] + ly * d[:, 1]
    cc = lx * lx + ly * ly - r * r
    disc = bh * bh - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        s_side = (-bh - np.sqrt(np.maximum(disc, 0.0))) / np.maximum(a, 1e-18)
    z_side = o[:, 2] + s_side * d[:, 2]
    side_ok = (disc >= 0) & (a > 1e-18) & (s_side > 0) & (z_side >= z0) & (z_side <= z1)
    s = np.where(side_ok, s_side, np.inf)
    with np.errstate(invalid="ignore"):
        cos = np.where(side_ok, np.abs((lx + s_side * d[:, 0]) * d[:, 0] + (ly + s_side * d[:, 1]) * d[:, 1]) / r, 0.0)
    # caps (top seen from above, bottom from below)
    dz = np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    for zc, sign in ((z1, 1.0), (z0, -1.0)):
        s_cap = (zc - o[:, 2]) / dz
        px, py = lx + s_cap * d[:, 0], ly + s_cap * d[:, 1]
        cap_ok = (sign * (o[:, 2] - zc) > 0) & (s_cap > 0) & (px * px + py * py <= r * r) & (s_cap < s)
        s = np.where(cap_ok, s_cap, s)
        cos = np.where(cap_ok, np.abs(d[:, 2]), cos)
    return s, cos


def _intersect_ellipsoids(o, d, ell: EllipsoidSet, prim, rng: np.random.Generator):
    """Foliage: first return after an exponential free path inside the ellipsoid."""
    radii = np.take(ell.radii, prim, axis=0)
    u = (o - np.take(ell.center, prim, axis=0)) / radii
    v = d / radii
    a = (v * v).sum(axis=1)
    b = (u * v).sum(axis=1)
    c = (u * u).sum(axis=1) - 1.0
    disc = b * b - a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    s_in = np.maximum((-b - root) / a, 0.0)
    s_out = (-b + root) / a
    depth = rng.standard_exponential(prim.shape[0]) * np.take(ell.mean_free_path, prim)
    s = s_in + depth
    hit = (disc > 0) & (s_out > 0) & (s < s_out)
    cos = 0.3 + 0.7 * rng.random(prim.shape[0])
    return np.where(hit, s, np.inf), cos


def cast_rays(
    origins: np.ndarray,
    dirs: np.ndarray,
    times: np.ndarray,
    ground: Ground,
    boxes: BoxSet,
    cylinders: CylinderSet,
    ellipsoids: EllipsoidSet,
    max_distance: float,
    rng: np.random.Generator,
    num_objects: int,
    origin_samples: np.ndarray | None = None,
) -> RayHits:
    """Nearest hit of each ray against the whole scene.

    Args:
        origins (ndarray float64[N, 3]): ray origins (world).
        dirs (ndarray float64[N, 3]): unit directions (world).
        times (ndarray float64[N]): ray times (moving boxes are taken at these times).
        ground (Ground): the ground.
        boxes (BoxSet): static and moving boxes (``object_index >= 0`` for labelled objects).
        cylinders (CylinderSet), ellipsoids (EllipsoidSet): static primitives.
        max_distance (float): hits farther than this are ignored.
        rng (Generator): randomness for foliage penetration.
        num_objects (int): number of labelled objects (length of the per-object counters).
        origin_samples (ndarray float64[K, 3] or None): the distinct ray origins (e.g. one per firing),
            used to bound the origin spread cheaply; default ``origins``.

    Returns:
        RayHits.
    """
    n = origins.shape[0]
    best, ground_cos = intersect_ground(origins, dirs, ground, max_distance)
    if n == 0:
        z = np.zeros(0)
        return RayHits(z, np.zeros(0, np.uint8), np.zeros(0, np.int32), z, z, z,
                       np.zeros(num_objects, np.int64), np.zeros(num_objects, np.int64))
    # float32 angles are plenty for culling (the windows get a 1e-5 rad margin)
    d32 = dirs.astype(np.float32)
    azimuth = np.arctan2(d32[:, 1], d32[:, 0])
    elevation = np.arcsin(np.clip(d32[:, 2], -1.0, 1.0))
    index = _RayIndex.build(azimuth, elevation)
    samples = origins if origin_samples is None else origin_samples
    origin = samples.mean(axis=0)
    spread_xy = float(np.max(np.hypot(samples[:, 0] - origin[0], samples[:, 1] - origin[1]))) + 1e-6
    spread_z = float(np.max(np.abs(samples[:, 2] - origin[2]))) + 1e-6
    t_mid = 0.5 * (float(times.min()) + float(times.max()))
    half_span = 0.5 * (float(times.max()) - float(times.min()))

    ray_parts, s_parts, cos_parts, src_parts, prim_parts = [], [], [], [], []

    # boxes (static + moving)
    if len(boxes):
        center = boxes.center + boxes.velocity * t_mid
        grow_xy = np.hypot(boxes.velocity[:, 0], boxes.velocity[:, 1]) * half_span + spread_xy
        grow_z = np.abs(boxes.velocity[:, 2]) * half_span + spread_z
        ray, prim = _candidate_pairs(
            index, center[:, :2], np.hypot(boxes.half[:, 0], boxes.half[:, 1]) + grow_xy,
            center[:, 2] - boxes.half[:, 2] - grow_z, center[:, 2] + boxes.half[:, 2] + grow_z, origin, max_distance,
        )
        if ray.size:
            s, cos = _intersect_boxes(np.take(origins, ray, axis=0), np.take(dirs, ray, axis=0), np.take(times, ray), boxes, prim, np.cos(boxes.yaw),
                                      np.sin(boxes.yaw))
            keep = np.isfinite(s)
            ray_parts.append(ray[keep]); s_parts.append(s[keep]); cos_parts.append(cos[keep])
            src_parts.append(np.zeros(int(keep.sum()), np.int8)); prim_parts.append(prim[keep])
    if len(cylinders):
        ray, prim = _candidate_pairs(
            index, cylinders.center_xy, cylinders.radius + spread_xy,
            cylinders.z_min - spread_z, cylinders.z_max + spread_z, origin, max_distance,
        )
        if ray.size:
            s, cos = _intersect_cylinders(np.take(origins, ray, axis=0), np.take(dirs, ray, axis=0), cylinders, prim)
            keep = np.isfinite(s)
            ray_parts.append(ray[keep]); s_parts.append(s[keep]); cos_parts.append(cos[keep])
            src_parts.append(np.ones(int(keep.sum()), np.int8)); prim_parts.append(prim[keep])
    if len(ellipsoids):
        ray, prim = _candidate_pairs(
            index, ellipsoids.center[:, :2],
            np.maximum(ellipsoids.radii[:, 0], ellipsoids.radii[:, 1]) + spread_xy,
            ellipsoids.center[:, 2] - ellipsoids.radii[:, 2] - spread_z,
            ellipsoids.center[:, 2] + ellipsoids.radii[:, 2] + spread_z, origin, max_distance,
        )
        if ray.size:
            s, cos = _intersect_ellipsoids(np.take(origins, ray, axis=0), np.take(dirs, ray, axis=0), ellipsoids, prim, rng)
            keep = np.isfinite(s)
            ray_parts.append(ray[keep]); s_parts.append(s[keep]); cos_parts.append(cos[keep])
            src_parts.append(np.full(int(keep.sum()), 2, np.int8)); prim_parts.append(prim[keep])

    surface = np.where(np.isfinite(best), SURFACE_GROUND, SURFACE_NONE).astype(np.uint8)
    object_index = np.full(n, -1, dtype=np.int32)
    cos_inc = ground_cos
    reflectivity = np.zeros(n)
    extra_dropout = np.zeros(n)
    object_rays = np.zeros(num_objects, np.int64)
    object_visible = np.zeros(num_objects, np.int64)
    if ray_parts:
        ray = np.concatenate(ray_parts)
        s = np.concatenate(s_parts)
        cos = np.concatenate(cos_parts)
        src = np.concatenate(src_parts)
        prim = np.concatenate(prim_parts)
        s_candidates = s
        np.minimum.at(best, ray, s_candidates)
        win = (s == best[ray]) & (s <= max_distance)
        wr, ws, wp, wc = ray[win], src[win], prim[win], cos[win]
        kind = np.empty(wr.shape[0], np.uint8)
        refl = np.empty(wr.shape[0])
        obj = np.full(wr.shape[0], -1, np.int32)
        m = ws == 0
        kind[m] = boxes.kind[wp[m]]
        refl[m] = boxes.reflectivity[wp[m]]
        obj[m] = boxes.object_index[wp[m]]
        m = ws == 1
        kind[m] = cylinders.kind[wp[m]]
        refl[m] = cylinders.reflectivity[wp[m]]
        m = ws == 2
        kind[m] = SURFACE_VEGETATION
        refl[m] = ellipsoids.reflectivity[wp[m]]
        surface[wr] = kind
        object_index[wr] = obj
        cos_inc = cos_inc.copy()
        cos_inc[wr] = wc
        reflectivity[wr] = refl
        if num_objects:
            is_obj = src == 0
            ids = boxes.object_index[prim[is_obj]]
            ids = ids[ids >= 0]
            object_rays = np.bincount(ids, minlength=num_objects).astype(np.int64)
            vis = obj[obj >= 0]
            object_visible = np.bincount(vis, minlength=num_objects).astype(np.int64)
    is_ground = surface == SURFACE_GROUND
    if is_ground.any():
        g = np.flatnonzero(is_ground)
        hit = np.take(origins, g, axis=0) + best[g, None] * np.take(dirs, g, axis=0)
        refl_g, drop_g = ground.material(hit[:, 0], hit[:, 1])
        reflectivity[g] = refl_g
        extra_dropout[g] = drop_g
    best = np.where(surface == SURFACE_NONE, np.inf, best)
    return RayHits(best, surface, object_index, cos_inc, reflectivity, extra_dropout, object_rays, object_visible)

