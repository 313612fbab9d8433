"""Ray casting against the ground, oriented (moving) boxes, vertical cylinders and foliage ellipsoids.

Two implementations of :func:`cast_rays`:

* **native** (the default when the compiled extension is available): ``torch.ops.lidarops.raycast_scene``
  (csrc/cpu/raycast_kernel.cpp), a C++ loop over the rays, parallel with ``at::parallel_for``.  Each
  primitive's conservative angular window (the bounding vertical cylinder described below, narrowed to
  the footprint's corners for boxes that do not turn) is entered once per call into a grid of azimuth
  bins x elevation bands; a ray tests the labelled objects of its cell, then the other primitives
  nearest first, and stops at the first one that lies beyond its nearest hit so far.  The first call
  in a process imports torch and loads ``lidarops._C`` (about 2 s).
* **NumPy** (the reference, and the fallback without the extension): below.

``LIDAROPS_DATA_NATIVE=0`` (or ``cast_rays(..., backend="numpy")``) forces NumPy, ``=1`` requires the
native kernel; :func:`raycast_backend` tells which one is used.  The native kernel repeats the NumPy
arithmetic of every intersection test operation by operation: box, cylinder and foliage distances are
the same bits, ground distances agree to about 1e-8 relative (the ground's waves are evaluated with
float32 sines: NumPy's SIMD ones are not always correctly rounded, the kernel's vectorised ones are), and
a ray can end on a different surface only at a near tie of its two nearest candidates.  Exact ties go to
the later primitive (boxes, then cylinders, then ellipsoids, by index) in the native kernel and
arbitrarily in NumPy.

Foliage randomness is counter-based: the penetration depth and the incidence cosine of a (ray,
ellipsoid) pair come from a 64-bit hash (MurmurHash3's finaliser) of ``key + ray * G1 + (ellipsoid + 1) * G2``, with one
``key`` drawn from the block's generator per call (only when the scene has ellipsoids), so both
implementations draw the same numbers whatever pairs their culling keeps.  (Until this change the NumPy
code drew two numbers per candidate pair from the generator, so the culling decided the stream.)

NumPy culling: rays are sorted by azimuth once; every primitive gets a bounding vertical cylinder (grown by
its motion during the batch and by the spread of the ray origins), which subtends an azimuth window
and an elevation window seen from the batch's mean origin.  ``searchsorted`` turns each azimuth window
into a slice of the sorted rays, the slices become (ray, primitive) candidate pairs in one vectorised
step, the elevation window thins them, and only the survivors get the exact intersection test.  The
nearest hit per ray wins (``np.minimum.at``), so occlusion is exact.

Boxes whose yaw does not change get the tighter window of their (grown) footprint rectangle, seen
from outside: the angular span of its corners, intersected with the cylinder's window, so the pairs
are a subset of the cylinder's in the same order.  Static axis-aligned boxes (nearly all of them) take
a slab test without rotation or motion terms, in chunks of a few thousand pairs; it gives the same
bits as the general test, and the incidence cosine is only computed for the rays a box wins.

``object_rays`` counts the crossings of each labelled box (the ray's line enters the box) within
``max_distance``, occluded or not; ``object_visible`` the rays whose nearest hit is the object.
"""
from __future__ import annotations

import os
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

__all__ = ["RayHits", "cast_rays", "intersect_ground", "raycast_backend"]

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


_GROUND_ITERATIONS, _GROUND_TOLERANCE = 3, 2e-4


def intersect_ground(origins: np.ndarray, dirs: np.ndarray, ground: Ground, max_distance: float,
                     iterations: int = _GROUND_ITERATIONS,
                     tolerance: float = _GROUND_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
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
    # contiguous components: the Newton loop below gathers and multiplies them several times
    ox, oy, oz = np.ascontiguousarray(np.take(origins, idx, axis=0).T)
    dx, dy, dz = np.ascontiguousarray(np.take(dirs, idx, axis=0).T)
    s = s_plane[idx]
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
    elevation: np.ndarray  # in sorted order (elevation of ray ``order[i]``)
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
        return _RayIndex(key[order], order, elevation[order], el_min, width, bands)

    def band_of(self, el: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((el - self.el_min) / self.band_width), 0, self.bands - 1).astype(np.int64)


def _rect_windows(rel: np.ndarray, half_xy: np.ndarray, yaw: np.ndarray, phi: np.ndarray):
    """Angular extent of upright rectangles seen from the origin (``rel``: centre minus origin).

    Returns the azimuths of the extreme corners relative to ``phi`` (the direction of the centre), the
    nearest and farthest horizontal distances, and whether the origin lies outside the rectangle (only
    then is the corner window valid: a convex outline seen from outside spans less than pi).
    """
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey = half_xy[:, 0], half_xy[:, 1]
    # the origin in the rectangle's frame
    qx = -(c * rel[:, 0] + s * rel[:, 1])
    qy = -(c * rel[:, 1] - s * rel[:, 0])
    outside = (np.abs(qx) > ex + 1e-3) | (np.abs(qy) > ey + 1e-3)  # margin: rounding of q
    sx = np.array([1.0, -1.0, -1.0, 1.0])
    sy = np.array([1.0, 1.0, -1.0, -1.0])
    lx, ly = sx * ex[:, None], sy * ey[:, None]
    cx = rel[:, 0:1] + c[:, None] * lx - s[:, None] * ly
    cy = rel[:, 1:2] + s[:, None] * lx + c[:, None] * ly
    dphi = np.mod(np.arctan2(cy, cx) - phi[:, None] + np.pi, 2 * np.pi) - np.pi
    d_min = np.hypot(np.maximum(np.abs(qx) - ex, 0.0), np.maximum(np.abs(qy) - ey, 0.0))
    d_max = np.hypot(np.abs(qx) + ex, np.abs(qy) + ey)
    return dphi.min(axis=1), dphi.max(axis=1), d_min, d_max, outside


def _candidate_pairs(
    index: _RayIndex,
    center_xy: np.ndarray,
    radius_xy: np.ndarray,
    z_lo: np.ndarray,
    z_hi: np.ndarray,
    origin: np.ndarray,
    max_distance: float,
    rect: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(ray, primitive) pairs whose ray direction falls in the primitive's angular window.

    The window is that of the primitive's bounding vertical cylinder.  With ``rect = (half_xy, yaw,
    usable)`` (upright rectangles of the same centres, already grown like ``radius_xy``), the windows
    of the ``usable`` primitives are narrowed to the rectangle's: the intersection of two conservative
    windows, so the pairs are a subset of the cylinder's, in the same order, and only pairs that cannot
    hit are dropped.
    """
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
    narrow = None
    if rect is not None:
        half_xy, yaw, usable = rect
        r_lo, r_hi, r_dmin, r_dmax, outside = _rect_windows(rel, half_xy, yaw, phi)
        narrow = usable & outside & ~full
        r_dmin = np.maximum(r_dmin, d_min)
        r_dmax = np.minimum(r_dmax, d_max)
        r_el_hi = np.arctan2(dz_hi, np.where(dz_hi >= 0, r_dmin, r_dmax)) + 1e-5
        r_el_lo = np.arctan2(dz_lo, np.where(dz_lo >= 0, r_dmax, r_dmin)) - 1e-5
        el_hi = np.where(narrow, np.minimum(el_hi, r_el_hi), el_hi)
        el_lo = np.where(narrow, np.maximum(el_lo, r_el_lo), el_lo)
    # one window per (primitive, elevation band it overlaps)
    b_lo = index.band_of(el_lo[live])
    b_hi = index.band_of(el_hi[live])
    n_bands = b_hi - b_lo + 1
    prim_b = np.repeat(live, n_bands)
    band = np.repeat(b_lo - np.cumsum(n_bands) + n_bands, n_bands) + np.arange(int(n_bands.sum()))
    base = band * 8.0 + np.pi
    lo = np.where(full[prim_b], -4.0, phi[prim_b] - half_width[prim_b] - 1e-5)
    hi = np.where(full[prim_b], 4.0, phi[prim_b] + half_width[prim_b] + 1e-5)
    if narrow is not None:
        nb = narrow[prim_b]
        lo = np.where(nb, np.maximum(lo, phi[prim_b] + r_lo[prim_b] - 1e-5), lo)
        hi = np.where(nb, np.minimum(hi, phi[prim_b] + r_hi[prim_b] + 1e-5), hi)
    # the window itself (clipped to the band), plus the parts that wrap around +-pi (none for full windows,
    # whose clipped window already holds every ray of the band: a wrapped part would repeat pairs)
    full_b = full[prim_b]
    win_lo = np.concatenate([base + np.maximum(lo, -np.pi - 1e-3),
                             np.where((lo < -np.pi) & ~full_b, base + lo + 2 * np.pi, np.inf), base - np.pi - 1e-3])
    win_hi = np.concatenate([base + np.minimum(hi, np.pi + 1e-3), base + np.pi + 1e-3,
                             np.where((hi > np.pi) & ~full_b, base + hi - 2 * np.pi, -np.inf)])
    starts = np.searchsorted(index.key_sorted, win_lo, side="left")
    ends = np.searchsorted(index.key_sorted, win_hi, side="right")
    counts = np.maximum(ends - starts, 0)
    total = int(counts.sum())
    if total == 0:
        return _EMPTY_I, _EMPTY_I
    prim = np.repeat(np.tile(prim_b, 3), counts)
    offsets = np.cumsum(counts) - counts
    pos = np.arange(total) - np.repeat(offsets - starts, counts)
    el = np.take(index.elevation, pos)
    ok = np.flatnonzero((el >= np.take(el_lo, prim)) & (el <= np.take(el_hi, prim)))
    return np.take(index.order, np.take(pos, ok)), np.take(prim, ok)


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


_PAIR_CHUNK = 4096  # pairs per step of the box test: its temporaries stay in cache and are reused


def _box_distances(origins, dirs, times, boxes: BoxSet, ray, prim, cos_yaw, sin_yaw) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each (ray, box) pair (``inf``: no hit), bit for bit that of :func:`_intersect_boxes`,
    and the face it enters by (int8: 0, 1, 2 for the box's x, y, z slab; -1: not computed).

    Most boxes are static and axis-aligned; there the box frame is the world frame shifted (``cos yaw =
    1``, ``sin yaw = 0`` and zero velocity leave every product exact, up to the sign of a zero that the
    slab test does not see), so their slab test needs neither rotation nor motion: about half the
    arithmetic and gathers.  The other pairs go through :func:`_intersect_boxes`.  Pairs are processed
    in chunks of ``_PAIR_CHUNK`` so the temporaries stay in cache and are reused, instead of growing the
    heap by megabytes per batch (fresh pages cost a page fault each).

    Args:
        origins (float64[N, 3]), dirs (float64[N, 3]), times (float64[N]): the rays.
        boxes (BoxSet): the boxes.
        ray (int64[P]), prim (int64[P]): the pairs.
        cos_yaw, sin_yaw (float64[B]): per-box trigonometry of the yaw.

    Returns:
        distance (float64[P]), face (int8[P]).
    """
    n_pairs = ray.shape[0]
    s = np.empty(n_pairs)
    face = np.empty(n_pairs, np.int8)
    simple = (boxes.yaw == 0.0) & (boxes.yaw_rate == 0.0) & ~(boxes.velocity != 0.0).any(axis=1)
    neg_half = -boxes.half
    for c0 in range(0, n_pairs, _PAIR_CHUNK):
        r, p = ray[c0:c0 + _PAIR_CHUNK], prim[c0:c0 + _PAIR_CHUNK]
        # [C, 3] rows: x, y, z of the ray origin relative to the box centre, 1 / direction, slab ends
        rel = np.take(origins, r, axis=0)
        rel -= np.take(boxes.center, p, axis=0)
        inv = np.take(dirs, r, axis=0)
        inv[inv == 0.0] = 1e-300
        np.divide(1.0, inv, out=inv)
        a = np.take(neg_half, p, axis=0)
        a -= rel
        a *= inv
        b = np.take(boxes.half, p, axis=0)
        b -= rel
        b *= inv
        near = np.minimum(a, b)
        far = np.maximum(a, b, out=b)
        t_near = np.maximum(near[:, 0], near[:, 1])
        np.maximum(t_near, near[:, 2], out=t_near)
        t_far = np.minimum(far[:, 0], far[:, 1])
        np.minimum(t_far, far[:, 2], out=t_far)
        hit = t_near <= t_far
        hit &= t_near > 0
        out = s[c0:c0 + _PAIR_CHUNK]
        out.fill(np.inf)
        np.copyto(out, t_near, where=hit)
        # the face hit: 0 (x), 1 (y) or 2 (z), tested in the order of _intersect_boxes' incidence
        not_x = np.not_equal(t_near, near[:, 0]).view(np.int8)
        np.add(not_x, (not_x & np.not_equal(t_near, near[:, 1]).view(np.int8)), out=face[c0:c0 + _PAIR_CHUNK])
    general = np.flatnonzero(~simple[prim])
    if general.size:
        rg = ray[general]
        s[general] = _intersect_boxes(np.take(origins, rg, axis=0), np.take(dirs, rg, axis=0), np.take(times, rg),
                                      boxes, prim[general], cos_yaw, sin_yaw)[0]
        face[general] = -1
    return s, face


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


# Counter-based randomness of the foliage, shared with the native kernel (csrc/cpu/raycast_kernel.cpp): the
# uniforms of a (ray, ellipsoid) pair are the 64-bit finaliser ``mix64`` (MurmurHash3's fmix64, csrc/include/
# lidarops/common.h) of ``key + ray * G1 + (ellipsoid + 1) * G2`` and of that plus G3, so they do not depend on
# which pairs the culling keeps nor on their order.
_G1, _G2, _G3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xD1B54A32D192ED03), np.uint64(0x632BE59BD9B4E019)
_M1, _M2, _S = np.uint64(0xFF51AFD7ED558CCD), np.uint64(0xC4CEB9FE1A85EC53), np.uint64(33)


def _mix64(z: np.ndarray) -> np.ndarray:
    z = z ^ (z >> _S)
    z *= _M1
    z ^= z >> _S
    z *= _M2
    z ^= z >> _S
    return z


def _foliage_uniforms(key: int, ray: np.ndarray, prim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two uniforms in ``[0, 1)`` per (ray, ellipsoid) pair: for the penetration depth and the cosine."""
    h = np.uint64(key) + ray.astype(np.uint64) * _G1 + (prim.astype(np.uint64) + np.uint64(1)) * _G2
    scale = 2.0 ** -53
    return ((_mix64(h) >> np.uint64(11)).astype(np.float64) * scale,
            (_mix64(h + _G3) >> np.uint64(11)).astype(np.float64) * scale)


def _intersect_ellipsoids(o, d, ell: EllipsoidSet, prim, ray, key: int):
    """Foliage: first return after an exponential free path inside the ellipsoid (``ray``: the rays' indices,
    which with ``prim`` and ``key`` pick the pairs' random numbers)."""
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
    u_depth, u_cos = _foliage_uniforms(key, ray, prim)
    depth = -np.log1p(-u_depth) * np.take(ell.mean_free_path, prim)
    s = s_in + depth
    hit = (disc > 0) & (s_out > 0) & (s < s_out)
    cos = 0.3 + 0.7 * u_cos
    return np.where(hit, s, np.inf), cos


_NATIVE_ENV = "LIDAROPS_DATA_NATIVE"
_native: dict = {}  # op name -> the compiled op or None once looked up; "why:" + name: why it is unavailable


def _native_op(name: str = "raycast_scene"):
    """``torch.ops.lidarops.<name>`` (the simulator's compiled ops: ``raycast_scene``, ``trace_shapes``) when torch
    and the compiled extension load, else None (looked up once: the first call imports torch and lidarops._C)."""
    if name not in _native:
        try:
            import torch

            from lidarops.extension import load

            load()
            _native[name] = getattr(torch.ops.lidarops, name)
        except Exception as e:  # no torch, extension not built or built before the op existed
            _native[name], _native["why:" + name] = None, f"{type(e).__name__}: {e}"
    return _native[name]


def raycast_backend(backend: str | None = None) -> str:
    """Which ray caster :func:`cast_rays` uses: ``"native"`` or ``"numpy"``.

    Args:
        backend (str or None): ``"native"``, ``"numpy"`` or ``None`` (automatic: the environment variable
            ``LIDAROPS_DATA_NATIVE=0`` forces NumPy, ``=1`` requires the native kernel; otherwise native
            when the compiled extension is available).

    Raises:
        ValueError: unknown backend name.
        RuntimeError: the native kernel is required but unavailable.
    """
    if backend is None:
        env = os.environ.get(_NATIVE_ENV, "").strip().lower()
        if env in ("0", "false", "no", "off", "numpy"):
            return "numpy"
        if env in ("1", "true", "yes", "on", "native"):
            backend = "native"
        elif env not in ("", "auto"):
            raise ValueError(f"{_NATIVE_ENV} must be 0, 1 or auto, got {env!r}")
        else:
            return "native" if _native_op() is not None else "numpy"
    if backend == "numpy":
        return "numpy"
    if backend != "native":
        raise ValueError(f"backend must be 'native', 'numpy' or None, got {backend!r}")
    if _native_op() is None:
        raise RuntimeError(f"the native ray caster is unavailable ({_native.get('why:raycast_scene')}); build the "
                           "extension (make build) or use backend='numpy' / LIDAROPS_DATA_NATIVE=0")
    return "native"


def _rays_array(name: str, a: np.ndarray, shape: tuple) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != len(shape) or any(want is not None and got != want for got, want in zip(a.shape, shape)):
        want = "(" + ", ".join("N" if w is None else str(w) for w in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be a float array, got {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float64)


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
    backend: str | None = None,
) -> RayHits:
    """Nearest hit of each ray against the whole scene.

    Both backends compute the same thing (the native one follows the NumPy code operation by operation;
    see the module docstring for what may differ by rounding).  ``rng`` is drawn from once, for the key of
    the foliage's random numbers, when there are ellipsoids.

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
        backend (str or None): ``"native"``, ``"numpy"`` or ``None`` (see :func:`raycast_backend`).

    Returns:
        RayHits.

    Raises:
        ValueError: arrays of the wrong shape or dtype (the message names the argument).
    """
    origins = _rays_array("origins", origins, (None, 3))
    n = origins.shape[0]
    dirs = _rays_array("dirs", dirs, (n, 3))
    times = _rays_array("times", times, (n,))
    samples = origins if origin_samples is None else _rays_array("origin_samples", origin_samples, (None, 3))
    if n and samples.shape[0] == 0:
        raise ValueError("origin_samples must not be empty when there are rays")
    key = int(rng.integers(1 << 63)) if len(ellipsoids) else 0
    if raycast_backend(backend) == "native":
        hits = _cast_rays_native(origins, dirs, times, ground, boxes, cylinders, ellipsoids, float(max_distance), key,
                                 int(num_objects), samples)
    else:
        hits = _cast_rays_numpy(origins, dirs, times, ground, boxes, cylinders, ellipsoids, float(max_distance), key,
                                int(num_objects), samples)
    _apply_ground_material(hits, origins, dirs, ground)
    return hits


def _apply_ground_material(hits: RayHits, origins: np.ndarray, dirs: np.ndarray, ground: Ground) -> None:
    """Reflectivity and extra dropout of the ground hits, from the ground's material map (a Python callable)."""
    g = np.flatnonzero(hits.surface == SURFACE_GROUND)
    if g.size:
        s_g = hits.distance[g]
        refl_g, drop_g = ground.material(np.take(origins[:, 0], g) + s_g * np.take(dirs[:, 0], g),
                                         np.take(origins[:, 1], g) + s_g * np.take(dirs[:, 1], g))
        hits.reflectivity[g] = refl_g
        hits.extra_dropout[g] = drop_g


def _f64(a: np.ndarray, dtype=np.float64):
    """A tensor sharing a contiguous, writable array of ``dtype`` (copied only when it must be)."""
    import torch

    a = np.ascontiguousarray(a, dtype=dtype)
    return torch.from_numpy(a if a.flags.writeable else a.copy())


def _cast_rays_native(origins, dirs, times, ground: Ground, boxes: BoxSet, cylinders: CylinderSet,
                      ellipsoids: EllipsoidSet, max_distance: float, key: int, num_objects: int, samples) -> RayHits:
    """cast_rays through ``torch.ops.lidarops.raycast_scene`` (ground material applied by the caller)."""
    t = _f64
    out = _native_op()(
        t(origins), t(dirs), t(times), t(samples), t(np.array([ground.z0, ground.slope[0], ground.slope[1]])),
        t(ground.wave_amp), t(np.reshape(ground.wave_k, (-1, 2))), t(ground.wave_phase),
        t(boxes.center), t(boxes.half), t(boxes.yaw), t(boxes.velocity), t(boxes.yaw_rate), t(boxes.reflectivity),
        t(boxes.kind, np.uint8), t(boxes.object_index, np.int32),
        t(cylinders.center_xy), t(cylinders.z_min), t(cylinders.z_max), t(cylinders.radius),
        t(cylinders.reflectivity), t(cylinders.kind, np.uint8),
        t(ellipsoids.center), t(ellipsoids.radii), t(ellipsoids.mean_free_path), t(ellipsoids.reflectivity),
        max_distance, key, num_objects, _GROUND_ITERATIONS, _GROUND_TOLERANCE)
    distance, surface, object_index, cos_inc, reflectivity, object_rays, object_visible = (x.numpy() for x in out)
    return RayHits(distance, surface, object_index, cos_inc, reflectivity, np.zeros(distance.shape[0]), object_rays,
                   object_visible)


def _cast_rays_numpy(origins, dirs, times, ground: Ground, boxes: BoxSet, cylinders: CylinderSet,
                     ellipsoids: EllipsoidSet, max_distance: float, key: int, num_objects: int, samples) -> RayHits:
    """The NumPy reference of cast_rays (ground material applied by the caller)."""
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
    origin = samples.mean(axis=0)
    spread_xy = float(np.max(np.hypot(samples[:, 0] - origin[0], samples[:, 1] - origin[1]))) + 1e-6
    spread_z = float(np.max(np.abs(samples[:, 2] - origin[2]))) + 1e-6
    t_mid = 0.5 * (float(times.min()) + float(times.max()))
    half_span = 0.5 * (float(times.max()) - float(times.min()))

    ray_parts, s_parts, cos_parts, src_parts, prim_parts = [], [], [], [], []

    # boxes (static + moving)
    if len(boxes):
        cos_yaw, sin_yaw = np.cos(boxes.yaw), np.sin(boxes.yaw)
        center = boxes.center + boxes.velocity * t_mid
        grow_xy = np.hypot(boxes.velocity[:, 0], boxes.velocity[:, 1]) * half_span + spread_xy
        grow_z = np.abs(boxes.velocity[:, 2]) * half_span + spread_z
        ray, prim = _candidate_pairs(
            index, center[:, :2], np.hypot(boxes.half[:, 0], boxes.half[:, 1]) + grow_xy,
            center[:, 2] - boxes.half[:, 2] - grow_z, center[:, 2] + boxes.half[:, 2] + grow_z, origin, max_distance,
            rect=(boxes.half[:, :2] + grow_xy[:, None], boxes.yaw, boxes.yaw_rate == 0.0),
        )
        if ray.size:
            s, face = _box_distances(origins, dirs, times, boxes, ray, prim, cos_yaw, sin_yaw)
            keep = np.flatnonzero(np.isfinite(s))
            # the incidence is only needed where a box wins: computed below for the winners only
            box_face = face[keep]
            ray_parts.append(ray[keep]); s_parts.append(s[keep]); cos_parts.append(np.empty(keep.size))
            src_parts.append(np.zeros(keep.size, np.int8)); prim_parts.append(prim[keep])
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
            s, cos = _intersect_ellipsoids(np.take(origins, ray, axis=0), np.take(dirs, ray, axis=0), ellipsoids, prim,
                                           ray, key)
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
        if m.any():
            # boxes come first in the pairs: a box winner's position indexes box_face
            wb = np.flatnonzero(m)
            fb = box_face[np.flatnonzero(win)[wb]]
            rb = wr[wb]
            wc[wb] = np.abs(np.take(dirs, rb * 3 + fb))  # axis-aligned static box: |d| along the face normal
            gen = np.flatnonzero(fb < 0)
            if gen.size:
                wg, rg = wb[gen], rb[gen]
                wc[wg] = _intersect_boxes(np.take(origins, rg, axis=0), np.take(dirs, rg, axis=0), np.take(times, rg),
                                          boxes, wp[wg], cos_yaw, sin_yaw)[1]
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
            is_obj = (src == 0) & (s <= max_distance)  # crossings within range: independent of the culling
            ids = boxes.object_index[prim[is_obj]]
            ids = ids[ids >= 0]
            object_rays = np.bincount(ids, minlength=num_objects).astype(np.int64)
            vis = obj[obj >= 0]
            object_visible = np.bincount(vis, minlength=num_objects).astype(np.int64)
    best = np.where(surface == SURFACE_NONE, np.inf, best)
    return RayHits(best, surface, object_index, cos_inc, reflectivity, extra_dropout, object_rays, object_visible)

