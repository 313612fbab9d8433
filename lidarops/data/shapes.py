"""The shapes of the objects the simulator labels, inside their labelled boxes (NumPy; the tracer also compiled).

The ray caster sees every labelled object as its box. Real objects are not boxes: a car has a hood and a
trunk below a narrower cabin, rounded corners, wheels and mirrors; a pedestrian is a head, a torso, arms
and walking legs; a cyclist is a rider, upright or leaning forward, on a bicycle whose wheels are thin
rings. A detector trained on boxes expects points on every face of the box and misplaces the boxes of real objects.

Each shape here is a signed distance function in its box's frame (x forward along the heading, y left,
z up, the origin at the box's centre; metres), scaled to the box's size and varied per object by four
uniform numbers ``u`` (a car's beltline and cabin, a pedestrian's stride, legs, coat and shoulders, a
cyclist's pedals and lean, a drone's skids, body, rotors and camera). The shape always lies inside its box, so the
label stays the tight box around it. :func:`trace` follows rays that enter a box onto the shape (sphere tracing);
the simulator sends the rays that miss it on into the scene (``Simulator(..., realism=...)``,
:mod:`lidarops.data.realism`). With the compiled extension the tracing runs in ``torch.ops.lidarops.trace_shapes``
(the same arithmetic; ``LIDAROPS_DATA_NATIVE=0`` keeps NumPy, as for the ray caster; the drone has no compiled
twin), and ``import lidarops.data.shapes`` still needs no torch.
"""
from __future__ import annotations

import numpy as np

__all__ = ["SHAPES", "shape_distance", "trace", "box_exit"]

_HIT, _MIN_STEP, _STEPS, _BISECT = 1e-4, 1e-2, 160, 7
#: shapes whose parts are thin next to the 1 cm step (a drone's arms and rotor discs, 2-3 cm across) step finer
_FINE_STEP = {"Drone": 2.5e-3}


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", v, v))


def _round_box(p, c, b, r):
    """Box of half sizes ``b`` centred at ``c`` with edges rounded by ``r`` (all [N, 3] or [N])."""
    r = np.minimum(r, b.min(axis=1) * 0.999)
    q = np.abs(p - c) - (b - r[:, None])
    return _norm(np.maximum(q, 0.0)) + np.minimum(q.max(axis=1), 0.0) - r


def _capsule(p, a, b, r):
    pa, ba = p - a, b - a
    h = np.clip(np.einsum("ij,ij->i", pa, ba) / np.maximum(np.einsum("ij,ij->i", ba, ba), 1e-12), 0.0, 1.0)
    return _norm(pa - ba * h[:, None]) - r


def _sphere(p, c, r):
    return _norm(p - c) - r


def _wheel(p, c, radius, half_width):
    """A solid wheel: a cylinder about the y axis."""
    d_r = np.hypot(p[:, 0] - c[:, 0], p[:, 2] - c[:, 2]) - radius
    d_y = np.abs(p[:, 1] - c[:, 1]) - half_width
    return np.minimum(np.maximum(d_r, d_y), 0.0) + np.hypot(np.maximum(d_r, 0.0), np.maximum(d_y, 0.0))


def _ring(p, c, radius, tube):
    """A bicycle wheel: a torus about the y axis (tyre and rim; spokes return next to nothing)."""
    q = np.hypot(p[:, 0] - c[:, 0], p[:, 2] - c[:, 2]) - radius
    return np.hypot(q, p[:, 1] - c[:, 1]) - tube


def _plane_xz(p, x0, z0, x1, z1, forward: bool):
    """Half-space behind the line through (x0, z0) and (x1, z1) in the x-z plane; ``forward``: its outside
    faces +x (a windscreen), else -x (a rear window)."""
    dx, dz = x1 - x0, z1 - z0
    n = np.hypot(dx, dz)
    nx, nz = (dz / n, -dx / n) if forward else (-dz / n, dx / n)
    return (p[:, 0] - x0) * nx + (p[:, 2] - z0) * nz


def _vec(x, y, z):
    return np.stack(np.broadcast_arrays(x, y, z), axis=1).astype(np.float64)


def _car(p, h, u):
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H, L = -hz, 2 * hz, 2 * hx
    belt = z0 + H * (0.56 + 0.08 * u[:, 0])
    clear = 0.11 * H
    zero = np.zeros_like(hx)
    bz = (belt - z0 - clear) / 2
    body = _round_box(p, _vec(zero, zero, z0 + clear + bz), _vec(hx - 0.03, hy - 0.07, bz), np.minimum(0.25, 0.8 * bz))
    rw = np.minimum(0.33, 0.21 * H)
    wx, wy = hx - np.minimum(0.9, 0.21 * L), hy - 0.17
    wheels = np.minimum.reduce([_wheel(p, _vec(sx * wx, sy * wy, z0 + rw), rw, 0.1)
                                for sx in (-1, 1) for sy in (-1, 1)])
    # the cabin: from c0 to c1 of the length (from the rear) at the beltline, shorter at the roof
    c0, c1 = 0.18 + 0.06 * u[:, 1], 0.74 + 0.08 * u[:, 2]
    x_c0, x_c1 = (c0 - 0.5) * L, (c1 - 0.5) * L
    x_r0, x_r1 = x_c0 + 0.13 * L, x_c1 - 0.2 * L
    cz = (hz - belt + 0.05) / 2
    cabin = np.maximum.reduce([
        _round_box(p, _vec((x_c0 + x_c1) / 2, zero, belt - 0.05 + cz), _vec((x_c1 - x_c0) / 2, 0.82 * (hy - 0.07), cz),
                   np.full_like(hx, 0.12)),
        _plane_xz(p, x_c1, belt, x_r1, hz, forward=True),
        _plane_xz(p, x_c0, belt, x_r0, hz, forward=False)])
    mirrors = np.minimum.reduce([_round_box(p, _vec(x_c1 - 0.1, s * (hy - 0.07), belt + 0.06),
                                            _vec(np.full_like(hx, 0.06), np.full_like(hx, 0.06), np.full_like(hx, 0.05)),
                                            np.full_like(hx, 0.02)) for s in (-1, 1)])
    return np.minimum.reduce([body, wheels, cabin, mirrors])


def _truck(p, h, u):
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H, L = -hz, 2 * hz, 2 * hx
    zero = np.zeros_like(hx)
    cab = np.clip(0.2 * L, 1.6, 2.4) * (0.9 + 0.2 * u[:, 0])
    cab_top = z0 + H * (0.78 + 0.1 * u[:, 1])
    clear = 0.12 * H
    cab_z = (cab_top - z0 - clear) / 2
    cabin = _round_box(p, _vec(hx - cab / 2, zero, z0 + clear + cab_z), _vec(cab / 2, hy - 0.04, cab_z), np.full_like(hx, 0.2))
    floor = z0 + 0.24 * H
    cargo_len = L - cab - 0.15
    cz = (hz - floor) / 2
    cargo = _round_box(p, _vec(-hx + cargo_len / 2, zero, floor + cz), _vec(cargo_len / 2, hy - 0.01, cz), np.full_like(hx, 0.06))
    chassis = _round_box(p, _vec(zero, zero, z0 + 0.18 * H), _vec(hx - 0.3, 0.5 * hy, 0.05 * H), np.full_like(hx, 0.03))
    rw = np.minimum(0.52, 0.16 * H)
    wheels = np.minimum.reduce([_wheel(p, _vec(x, s * (hy - 0.2), z0 + rw), rw, 0.15)
                                for x in (hx - 0.6 * cab, -hx + 0.22 * L) for s in (-1, 1)])
    return np.minimum.reduce([cabin, cargo, chassis, wheels])


def _bus(p, h, u):
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H = -hz, 2 * hz
    zero = np.zeros_like(hx)
    clear = 0.1 * H
    bz = (H - clear) / 2
    body = _round_box(p, _vec(zero, zero, z0 + clear + bz), _vec(hx - 0.02, hy - 0.03, bz), np.full_like(hx, 0.25 + 0.1 * u[:, 0]))
    rw = np.minimum(0.5, 0.15 * H)
    wheels = np.minimum.reduce([_wheel(p, _vec(x, s * (hy - 0.2), z0 + rw), rw, 0.15)
                                for x in (hx - 0.2 * 2 * hx, -hx + 0.25 * 2 * hx) for s in (-1, 1)])
    return np.minimum(body, wheels)


def _pedestrian(p, h, u):
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H = -hz, 2 * hz
    zero = np.zeros_like(hx)
    stride = np.minimum(hx - 0.07, 0.32) * np.sin(2 * np.pi * u[:, 0])  # the walking phase
    # u[:, 1]: legs up to twice as thick (trousers, boots); u[:, 2]: a coat's hem up to 0.18 H below the hip;
    # u[:, 3]: shoulders up to a quarter narrower, the arms at the body's sides (all 0: the plain shape)
    sw = np.minimum(0.1 * H, hy - 0.1) * (1 - 0.25 * u[:, 3])  # half the shoulders' width
    hip_z, foot_z = z0 + 0.52 * H, z0 + 0.06
    leg_r, hem = 0.035 * H * (1 + u[:, 1]), 0.18 * H * u[:, 2]
    legs = np.minimum.reduce([_capsule(p, _vec(zero, s * 0.09, hip_z), _vec(s * stride, s * 0.1, foot_z), leg_r)
                              for s in (-1, 1)])
    torso = _round_box(p, _vec(zero, zero, z0 + 0.70 * H - hem / 2), _vec(0.065 * H, sw, 0.16 * H + hem / 2),
                       0.045 * H)
    head = _sphere(p, _vec(0.02 + zero, zero, z0 + 0.935 * H), 0.065 * H)
    arms = np.minimum.reduce([_capsule(p, _vec(zero, s * (sw + 0.02), z0 + 0.80 * H),
                                       _vec(-0.6 * s * stride, s * (sw + 0.04), z0 + 0.47 * H), 0.028 * H)
                              for s in (-1, 1)])
    return np.minimum.reduce([legs, torso, head, arms])


def _cyclist(p, h, u):
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H = -hz, 2 * hz
    zero = np.zeros_like(hx)
    R = np.minimum(0.34, 0.42 * hx)
    xr, xf = -hx + R + 0.02, hx - R - 0.02
    D = xf - xr
    hub_r, hub_f = _vec(xr, zero, z0 + R), _vec(xf, zero, z0 + R)
    wheels = np.minimum(_ring(p, hub_r, R, 0.03), _ring(p, hub_f, R, 0.03))
    seat, bar = _vec(xr + 0.32 * D, zero, z0 + 2.4 * R), _vec(xr + 0.86 * D, zero, z0 + 2.7 * R)
    bb, head_tube = _vec(xr + 0.42 * D, zero, z0 + 0.85 * R), _vec(xr + 0.84 * D, zero, z0 + 2.1 * R)
    tube = np.full_like(hx, 0.025)
    frame = np.minimum.reduce([_capsule(p, a, b, tube) for a, b in
                               ((hub_r, bb), (hub_r, seat), (bb, seat), (seat, head_tube), (bb, head_tube),
                                (head_tube, hub_f), (head_tube, bar))])
    hip = _vec(xr + 0.3 * D, zero, z0 + 0.53 * H)
    # u[:, 1]: the rider's lean, from upright to reaching forward; real riders' heads are behind the box's centre
    # on average (KITTI's cyclists: 0.06 of half the length), over the saddle rather than the handlebars
    shoulder = _vec(xr + (0.37 + 0.2 * u[:, 1]) * D, zero, z0 + 0.79 * H)
    torso = _capsule(p, hip, shoulder, 0.07 * H)
    head = _sphere(p, shoulder + _vec(0.04 + zero, zero, 0.12 * H), 0.062 * H)
    sw = np.minimum(0.17, hy - 0.08)
    arms = np.minimum.reduce([_capsule(p, shoulder + _vec(zero, s * sw, zero), bar + _vec(zero, s * (sw + 0.03), zero), 0.024 * H)
                              for s in (-1, 1)])
    phase = 2 * np.pi * u[:, 0]  # the pedals' angle
    legs = []
    for s, ph in ((1, phase), (-1, phase + np.pi)):
        pedal = bb + _vec(0.17 * np.cos(ph), s * 0.1 + zero, 0.17 * np.sin(ph))
        hip_s = hip + _vec(zero, s * 0.1 + zero, zero)
        knee = (hip_s + pedal) / 2 + _vec(0.18 + zero, zero, 0.1 + zero)
        legs += [_capsule(p, hip_s, knee, 0.034 * H), _capsule(p, knee, pedal, 0.028 * H)]
    return np.minimum.reduce([wheels, frame, torso, head, arms, *legs])


def _disc(p, c, radius, half_thickness):
    """A flat disc about the z axis (a spinning rotor's swept disc)."""
    d_r = np.hypot(p[:, 0] - c[:, 0], p[:, 1] - c[:, 1]) - radius
    d_z = np.abs(p[:, 2] - c[:, 2]) - half_thickness
    return np.minimum(np.maximum(d_r, d_z), 0.0) + np.hypot(np.maximum(d_r, 0.0), np.maximum(d_z, 0.0))


def _drone(p, h, u):
    """A quadcopter in X layout: a rounded body, four arms out to motors under four rotor discs at the top of the
    box, skids below on three drones in five and a camera under the nose on half. The discs stand for rotors
    spinning too fast to see: the realism profile keeps only some of their returns (``rotor_keep``)."""
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    z0, H = -hz, 2 * hz
    zero = np.zeros_like(hx)
    m = np.minimum(hx, hy)
    R = (0.30 + 0.08 * u[:, 2]) * m
    z_rotor = z0 + 0.9 * H
    a, b = hx - R - 0.01 * m, hy - R - 0.01 * m
    body_c = _vec(zero, zero, z0 + 0.55 * H)
    body_b = _vec((0.26 + 0.1 * u[:, 1]) * hx, (0.2 + 0.06 * u[:, 1]) * hy, 0.22 * H)
    parts = [_round_box(p, body_c, body_b, 0.4 * np.minimum(body_b[:, 1], body_b[:, 2]))]
    z_arm = z0 + 0.62 * H
    for sx in (-1, 1):
        for sy in (-1, 1):
            hub = _vec(sx * a, sy * b, z_rotor)
            parts += [_disc(p, hub, R, 0.035 * H),
                      _capsule(p, _vec(zero, zero, z_arm), _vec(sx * a, sy * b, z_arm), 0.05 * H),
                      _capsule(p, _vec(sx * a, sy * b, z_arm), hub, 0.06 * m)]
    skids = u[:, 0] < 0.6
    far = np.full_like(hx, 10.0)  # a part a drone lacks: far away, never the nearest
    for sy in (-1, 1):
        y = sy * 0.55 * hy
        skid = _capsule(p, _vec(-0.5 * hx, y, z0 + 0.06 * H), _vec(0.5 * hx, y, z0 + 0.06 * H), 0.05 * H)
        struts = np.minimum.reduce([_capsule(p, _vec(sx * 0.25 * hx, y, z0 + 0.06 * H),
                                             _vec(sx * 0.15 * hx, sy * 0.5 * body_b[:, 1], z0 + 0.4 * H), 0.04 * H)
                                    for sx in (-1, 1)])
        parts.append(np.where(skids, np.minimum(skid, struts), far))
    camera = _sphere(p, _vec(0.6 * body_b[:, 0], zero, z0 + 0.28 * H), 0.14 * H)
    parts.append(np.where(u[:, 3] < 0.5, camera, far))
    return np.minimum.reduce(parts)


#: The shaped classes and their signed distance functions ``f(points, half_sizes, u)``.
SHAPES = {"Car": _car, "Truck": _truck, "Bus": _bus, "Pedestrian": _pedestrian, "Cyclist": _cyclist, "Drone": _drone}


def _checked(name: str, **arrays) -> list[np.ndarray]:
    if name not in SHAPES:
        raise ValueError(f"name must be one of {sorted(SHAPES)}, got {name!r}")
    out, n = [], None
    for arg, a in arrays.items():
        a = np.asarray(a, np.float64)
        k = 4 if arg == "u" else 3
        n = a.shape[0] if n is None and a.ndim == 2 else n
        if a.ndim != 2 or a.shape[1] != k or a.shape[0] != n:
            raise ValueError(f"{arg} must be [N, {k}] with N = {n}, got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{arg} must be finite")
        out.append(a)
    if (out[-2] <= 0).any():
        raise ValueError("half must be positive (half sizes of the boxes)")
    return out


def _distance(name: str, p: np.ndarray, half: np.ndarray, u: np.ndarray) -> np.ndarray:
    if not len(p):
        return np.zeros(0)
    box = _round_box(p, np.zeros_like(p), half, np.zeros(len(p)))
    return np.maximum(SHAPES[name](p, half, u), box)


def shape_distance(name: str, p: np.ndarray, half: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Signed distance (m; negative inside) from points ``p`` [N, 3] in their boxes' frames to the shape of
    class ``name`` in boxes of half sizes ``half`` [N, 3], per-object numbers ``u`` [N, 4] in [0, 1). The
    shape is cut to its box."""
    return _distance(name, *_checked(name, p=p, half=half, u=u))


def box_exit(p: np.ndarray, d: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Distance along unit directions ``d`` from points ``p`` inside or on boxes (half sizes ``half``, box
    frame) to where the rays leave them."""
    with np.errstate(divide="ignore", invalid="ignore"):
        far = np.where(d > 0, (half - p) / d, np.where(d < 0, (-half - p) / d, np.inf))
    return np.maximum(far.min(axis=1), 0.0)


def trace(name: str, entry: np.ndarray, d: np.ndarray, half: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Follows rays from where they enter their boxes (``entry`` [N, 3], unit directions ``d``, box frame) to
    the shape of class ``name``.

    Returns:
        t (float64[N]): distance from the entry to the shape (where ``hit``).
        hit (bool[N]): whether the ray meets the shape before it leaves the box.
        cos (float64[N]): |cos| of the angle between the ray and the shape's normal there.
    """
    entry, d, half, u = _checked(name, entry=entry, d=d, half=half, u=u)
    if len(d) and np.abs(_norm(d) - 1.0).max() > 1e-6:
        raise ValueError("d must hold unit directions (rows of length 1)")
    return _trace(name, entry, d, half, u)


# the shape kinds of torch.ops.lidarops.trace_shapes (csrc/cpu/shapes_kernel.cpp)
_NATIVE_KIND = {"Car": 0, "Truck": 1, "Bus": 2, "Pedestrian": 3, "Cyclist": 4}


def _native_op():
    """``torch.ops.lidarops.trace_shapes`` when the ray caster's backend is native (the compiled extension loads,
    ``LIDAROPS_DATA_NATIVE`` does not force NumPy) and the extension holds the op, else None."""
    from lidarops.data import _raycast

    return _raycast._native_op("trace_shapes") if _raycast.raycast_backend() == "native" else None


def _trace(name, entry, d, half, u):
    """:func:`trace` on checked float64 arrays (the simulator's own calls): the compiled tracer when there is one
    (the same arithmetic, about ten times faster), else :func:`_trace_numpy`."""
    # a shape without a compiled twin (the drone: few rays a frame meet one) is traced in NumPy
    op = _native_op() if len(entry) and name in _NATIVE_KIND else None
    if op is None:
        return _trace_numpy(name, entry, d, half, u)
    import torch

    t, hit, cos = op(_NATIVE_KIND[name], *(torch.from_numpy(np.ascontiguousarray(a, np.float64))
                                           for a in (entry, d, half, u)))
    return t.numpy(), hit.numpy(), cos.numpy()


def _trace_numpy(name, entry, d, half, u):
    """The NumPy reference of the tracer (csrc/cpu/shapes_kernel.cpp follows it operation by operation)."""
    n = len(entry)
    t, before, hit = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    exit_t = box_exit(entry, d, half)
    active = np.arange(n)
    min_step = _FINE_STEP.get(name, _MIN_STEP)
    for _ in range(int(_STEPS * _MIN_STEP / min_step)):
        if not active.size:
            break
        dist = _distance(name, entry[active] + d[active] * t[active, None], half[active], u[active])
        on = dist < _HIT
        hit[active[on]] = True
        # steps of at least 1 cm (a thin-parted shape's finer step), so that grazing rays finish; a step can sink
        # that far into the shape, which the bisection below takes back
        before[active] = np.where(on, before[active], t[active])
        t[active] += np.where(on, 0.0, np.maximum(dist, min_step))
        active = active[~on & (t[active] <= exit_t[active])]
    k = np.flatnonzero(hit)
    lo, hi = before[k], t[k]
    for _ in range(_BISECT):
        mid = (lo + hi) / 2
        inside = _distance(name, entry[k] + d[k] * mid[:, None], half[k], u[k]) <= 0
        lo, hi = np.where(inside, lo, mid), np.where(inside, mid, hi)
    t[k] = hi
    cos = np.zeros(n)
    if k.size:
        p, e = entry[k] + d[k] * t[k, None], 5e-3
        grad = np.stack([_distance(name, p + e * ax, half[k], u[k]) - _distance(name, p - e * ax, half[k], u[k])
                         for ax in np.eye(3)], axis=1)
        norm = _norm(grad)
        cos = np.zeros(n)
        cos[k] = np.where(norm > 0, np.abs(np.einsum("ij,ij->i", grad, d[k])) / np.maximum(norm, 1e-12), 1.0)
    return t, hit, np.clip(cos, 0.0, 1.0)
