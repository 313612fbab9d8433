"""Object shapes inside their boxes (lidarops.data.shapes) and the simulator's rays traced onto them: sphere
tracing against a brute-force march along each ray, hand-computed hits, and what it changes in frames."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lidarops.data.frame import CLASSES
from lidarops.data.scene import SURFACE_GROUND
from lidarops.data.shapes import SHAPES, box_exit, shape_distance, trace
from lidarops.data.synthetic import Simulator

SIZES = {"Car": (3.9, 1.6, 1.56), "Truck": (8.0, 2.5, 3.2), "Bus": (11.0, 2.6, 3.2), "Pedestrian": (0.8, 0.6, 1.75),
         "Cyclist": (1.76, 0.6, 1.73), "Drone": (0.7, 0.7, 0.3)}
#: share of the box's volume the shape fills: a car is most of its box, a cyclist little of it
FILL = {"Car": (0.45, 0.8), "Truck": (0.6, 0.95), "Bus": (0.8, 1.0), "Pedestrian": (0.08, 0.3), "Cyclist": (0.02, 0.15),
        "Drone": (0.03, 0.12)}


def _rays_into_box(rng, half, n):
    """Rays from outside (a sensor 2-12 m away, 0-3 m up) aimed at random points of the box: their entry
    points on its faces and their directions, for the rays that enter it."""
    o = np.concatenate([rng.uniform(-12, 12, (n, 2)), rng.uniform(-0.5, 3.0, (n, 1))], 1)
    o[:, :2] += np.sign(o[:, :2]) * half[:2] * 1.5
    aim = rng.uniform(-1, 1, (n, 3)) * half
    d = aim - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    near = np.minimum(t1, t2).max(1)
    return o + d * near[:, None], d


def _march(name, entry, d, half, u, step=5e-4):
    """First point along each ray inside the shape, by evaluating it every ``step`` metres (float64)."""
    exit_t = box_exit(entry, d, half)
    t = np.full(len(entry), np.inf)
    for k in range(int(exit_t.max() / step) + 2):
        s = k * step
        live = np.isinf(t) & (s <= exit_t)
        if not live.any():
            break
        i = np.flatnonzero(live)
        inside = shape_distance(name, entry[i] + d[i] * s, half[i], u[i]) <= 0
        t[i[inside]] = s
    return t


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_sphere_tracing_finds_what_a_fine_march_finds(name):
    rng = np.random.default_rng(list(SHAPES).index(name))
    half = np.asarray(SIZES[name]) / 2
    entry, d = _rays_into_box(rng, half, 1500)
    halves, u = np.tile(half, (len(entry), 1)), rng.random((len(entry), 4))
    t, hit, cos = trace(name, entry, d, halves, u)
    ref = _march(name, entry, d, halves, u)
    ref_hit = np.isfinite(ref)
    assert 0.02 < ref_hit.mean() < 1.0  # rays both meet and miss every shape
    agree = hit == ref_hit
    # a ray grazing a thin part within a centimetre may count either way
    assert agree.mean() > 0.985, f"{name}: {100 * (1 - agree.mean()):.1f} % of the rays disagree"
    both = hit & ref_hit
    err = np.abs(t[both] - ref[both])
    # within a bisection's 0.1 mm, but for the rare ray whose 1 cm step crosses a thin part's edge; a drone's rotor
    # discs are flat faces often met at grazing angles, where a hit within 0.1 mm of the face lies 0.1 mm / cos
    # along the ray (a few mm)
    q99 = 3e-3 if name == "Drone" else 1e-3
    assert np.quantile(err, 0.99) < q99 and (err > 0.012).mean() < 0.005, (name, np.quantile(err, 0.99), err.max())
    assert ((cos >= 0) & (cos <= 1)).all() and (cos[~hit] == 0).all()


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_each_shape_lies_in_its_box_and_fills_a_plausible_share(name):
    rng = np.random.default_rng(5)
    half = np.asarray(SIZES[name]) / 2
    p = rng.uniform(-1.2, 1.2, (200_000, 3)) * half
    inside = shape_distance(name, p, np.tile(half, (len(p), 1)), rng.random((len(p), 4))) <= 0
    assert (np.abs(p[inside]) <= half + 1e-9).all()
    in_box = (np.abs(p) <= half).all(1)
    lo, hi = FILL[name]
    assert lo < inside.sum() / in_box.sum() < hi, (name, inside.sum() / in_box.sum())


def test_hand_computed_hits():
    u = np.array([[0.5, 0.5, 0.5, 0.5]])
    car = np.array([[2.0, 0.8, 0.75]])  # a 4 x 1.6 x 1.5 m car: belt at z = -0.75 + 1.5 * 0.6 = 0.15
    level = np.array([[-1.0, 0.0, 0.0]])
    # the bumper's middle (below the belt, above the clearance): the body's front, 3 cm inside the box
    t, hit, cos = trace("Car", np.array([[2.0, 0.0, -0.2]]), level, car, u)
    assert hit[0] and abs(t[0] - 0.03) < _STEP_TOL and cos[0] > 0.99
    # the side of the body: 7 cm in
    t, hit, _ = trace("Car", np.array([[0.0, 0.8, -0.2]]), np.array([[0.0, -1.0, 0.0]]), car, u)
    assert hit[0] and abs(t[0] - 0.07) < _STEP_TOL
    # level above the hood, 0.4 m up: over the hood onto the windscreen through (x_c1, belt) and
    # (x_c1 - 0.2 L, top) with x_c1 = (0.78 - 0.5) * 4 = 1.12: at z = 0.4, x = 1.12 - 0.8 * (0.25 / 0.6)
    t, hit, cos = trace("Car", np.array([[2.0, 0.0, 0.4]]), level, car, u)
    x_hit = 1.12 - 0.8 * (0.4 - 0.15) / (0.75 - 0.15)
    assert hit[0] and abs((2.0 - t[0]) - x_hit) < _STEP_TOL, (2.0 - t[0], x_hit)
    assert 0.4 < cos[0] < 0.8  # a sloped windscreen
    # a pedestrian in mid-stride-free pose (phase 0: legs straight down at y = +-0.09..0.1, radius 0.035 H):
    # at knee height between the legs the ray misses; on a leg's axis it meets the leg's front
    ped = np.array([[0.4, 0.3, 0.875]])
    knee = -0.875 + 0.3
    t, hit, _ = trace("Pedestrian", np.array([[0.4, 0.0, knee]]), level, ped, np.zeros((1, 4)))
    assert not hit[0]
    y_leg = 0.09 + 0.01 * (0.52 * 1.75 - 0.3) / (0.52 * 1.75 - 0.06)
    t, hit, _ = trace("Pedestrian", np.array([[0.4, y_leg, knee]]), level, ped, np.zeros((1, 4)))
    assert hit[0] and abs(t[0] - (0.4 - 0.035 * 1.75)) < _STEP_TOL


_STEP_TOL = 1e-3  # hits are bisected to 0.1 mm


def test_pedestrian_builds_by_hand():
    """u[:, 1] = 1 doubles a pedestrian's legs (radius 0.07 H); u[:, 2] = 1 hangs a coat's hem 0.18 H below the
    torso's bottom (0.54 H), where a level ray between the legs now meets the coat's front (0.065 H from the axis);
    u[:, 3] = 1 brings the shoulders a quarter in."""
    level, ped, H = np.array([[-1.0, 0.0, 0.0]]), np.array([[0.4, 0.3, 0.875]]), 1.75
    knee = -0.875 + 0.3
    y_leg = 0.09 + 0.01 * (0.52 * H - 0.3) / (0.52 * H - 0.06)
    t, hit, _ = trace("Pedestrian", np.array([[0.4, y_leg, knee]]), level, ped, np.array([[0.0, 1.0, 0.0, 0.0]]))
    assert hit[0] and abs(t[0] - (0.4 - 0.07 * H)) < _STEP_TOL
    thigh = -0.875 + 0.45 * H  # below the plain torso (0.54 H), above the coat's hem (0.36 H)
    t, hit, _ = trace("Pedestrian", np.array([[0.4, 0.0, thigh]]), level, ped, np.zeros((1, 4)))
    assert not hit[0]
    t, hit, _ = trace("Pedestrian", np.array([[0.4, 0.0, thigh]]), level, ped, np.array([[0.0, 0.0, 1.0, 0.0]]))
    assert hit[0] and abs(t[0] - (0.4 - 0.065 * H)) < _STEP_TOL
    # from the side at chest height: the shoulders' half width 0.1 H (0.175 m), or a quarter less
    chest, side = -0.875 + 0.72 * H, np.array([[0.0, -1.0, 0.0]])
    for u3, half_width in ((0.0, 0.1 * H), (1.0, 0.075 * H)):
        t, hit, _ = trace("Pedestrian", np.array([[0.0, 0.3, chest]]), side, ped, np.array([[0.0, 0.0, 0.0, u3]]))
        assert hit[0] and 0.3 - t[0] < half_width + 0.05 * H, (u3, 0.3 - t[0])  # the arm lies just outside
        assert 0.3 - t[0] > half_width - _STEP_TOL, (u3, 0.3 - t[0])


def test_cyclist_lean_by_hand():
    """u[:, 1] places the rider's shoulders over the wheelbase: with R = min(0.34, 0.42 hx) = 0.34 the rear hub is at
    xr = -hx + R + 0.02 and the front at -xr (D = -2 xr); the shoulders are at xr + (0.37 + 0.2 u1) D, 0.79 H up,
    the head's centre 0.04 m ahead of them and 0.12 H above. A level ray from the front at the head's centre meets
    the head's front (radius 0.062 H); upright (u1 = 0) that is behind the box's centre, as the real riders' are."""
    half, H = np.array([[0.88, 0.3, 0.865]]), 1.73
    xr = -0.88 + 0.34 + 0.02
    D = -2 * xr
    z_head = -0.865 + 0.79 * H + 0.12 * H
    for u1 in (0.0, 0.5, 1.0):
        x_head = xr + (0.37 + 0.2 * u1) * D + 0.04
        u = np.array([[0.25, u1, 0.0, 0.0]])  # pedals at a quarter turn: both feet clear of the head's height
        t, hit, cos = trace("Cyclist", np.array([[0.88, 0.0, z_head]]), np.array([[-1.0, 0.0, 0.0]]), half, u)
        assert hit[0] and abs((0.88 - t[0]) - (x_head + 0.062 * H)) < _STEP_TOL, (u1, 0.88 - t[0])
        assert cos[0] > 0.99
    assert xr + 0.37 * D + 0.04 + 0.062 * H < 0.05 and xr + 0.37 * D + 0.04 < 0  # upright: the head behind


def test_drone_by_hand():
    """A 0.7 x 0.7 x 0.3 m drone (m = 0.35): rotor discs of radius R = (0.30 + 0.08 u2) m about hubs at
    (+-(hx - R - 0.01 m), +-(hy - R - 0.01 m), z0 + 0.9 H), 0.035 H thick each side; the body a rounded box of half
    sizes (0.26 + 0.1 u1) hx, (0.2 + 0.06 u1) hy, 0.22 H about z0 + 0.55 H; with u3 < 0.5 a camera (radius 0.14 H)
    under the nose at (0.6 x the body's half length, 0, z0 + 0.28 H); with u0 < 0.6 skids."""
    half, H = np.array([[0.35, 0.35, 0.15]]), 0.3
    R = 0.30 * 0.35
    hub = 0.35 - R - 0.0035
    down, level = np.array([[0.0, 0.0, -1.0]]), np.array([[-1.0, 0.0, 0.0]])
    bare = np.array([[0.9, 0.0, 0.0, 0.9]])  # no skids, no camera
    # from above, half way out along a rotor's disc: its top face, clear of the motor's cap
    t, hit, cos = trace("Drone", np.array([[hub + 0.5 * R, hub, 0.15]]), down, half, bare)
    assert hit[0] and abs(t[0] - (0.15 - (-0.15 + 0.9 * H + 0.035 * H))) < _STEP_TOL and cos[0] > 0.99
    # from above, just beyond a disc's rim and outside the arms: nothing
    t, hit, _ = trace("Drone", np.array([[hub + R + 0.004, 0.0, 0.15]]), down, half, bare)
    assert not hit[0]
    # level from the front at the body's middle height: its flat front face at 0.26 hx
    t, hit, cos = trace("Drone", np.array([[0.35, 0.0, -0.15 + 0.55 * H]]), level, half, bare)
    assert hit[0] and abs(t[0] - (0.35 - 0.26 * 0.35)) < _STEP_TOL and cos[0] > 0.99
    # below the body, at the camera's centre height: nothing bare, the camera's front with u3 < 0.5
    z_cam = -0.15 + 0.28 * H
    t, hit, _ = trace("Drone", np.array([[0.35, 0.0, z_cam]]), level, half, bare)
    assert not hit[0]
    t, hit, _ = trace("Drone", np.array([[0.35, 0.0, z_cam]]), level, half, np.array([[0.9, 0.0, 0.0, 0.1]]))
    assert hit[0] and abs(t[0] - (0.35 - (0.6 * 0.26 * 0.35 + 0.14 * H))) < _STEP_TOL


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="name"):
        shape_distance("Boat", np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 4)))
    with pytest.raises(ValueError, match="half"):
        shape_distance("Car", np.zeros((2, 3)), np.ones((1, 3)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="u must"):
        shape_distance("Car", np.zeros((2, 3)), np.ones((2, 3)), np.zeros((2, 3)))
    assert shape_distance("Car", np.zeros((0, 3)), np.ones((0, 3)), np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match="d must hold unit directions"):
        trace("Car", np.zeros((1, 3)), np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 4)))
    t, hit, cos = trace("Cyclist", np.zeros((0, 3)), np.zeros((0, 3)), np.ones((0, 3)), np.zeros((0, 4)))
    assert t.shape == hit.shape == cos.shape == (0,)


KW = dict(seed=11, object_counts={"Car": 20, "Pedestrian": 15, "Cyclist": 12, "Truck": 2, "Bus": 2})


@pytest.fixture(scope="module")
def frames():
    # the kitti profile without the options that change the scene (crossings, lots): the same objects, cast and shaped
    from lidarops.data.realism import make_realism

    kitti = dataclasses.replace(make_realism("kitti"), crossing_pedestrians=0.0, crossing_cyclists=0.0, parking_lots=0.0)
    return Simulator("driving_city", **KW).sweep(0), Simulator("driving_city", realism=kitti, **KW).sweep(0)


def _points_in_own_box(frame, cls):
    k = CLASSES.index(cls)
    on = (frame.instance >= 0) & (frame.labels[np.maximum(frame.instance, 0)] == k)
    return on.sum(), on


def test_rays_that_miss_a_shape_go_on_into_the_scene(frames):
    """With shapes, returns on pedestrians and cyclists are a fraction of their boxes' returns, the rays
    that pass between a pedestrian's legs or a bicycle's wheels reach what lies behind (the ground
    inside those boxes), and every object return lies in its box."""
    import torch

    from lidarops import points_in_boxes

    cast, shaped = frames
    for cls, most in (("Pedestrian", 0.7), ("Cyclist", 0.45)):
        n_cast, _ = _points_in_own_box(cast, cls)
        n_shaped, _ = _points_in_own_box(shaped, cls)
        assert n_cast > 200 and n_shaped < most * n_cast, (cls, n_cast, n_shaped)
    idx = points_in_boxes(torch.as_tensor(shaped.points[:, :3], dtype=torch.float64),
                          torch.as_tensor(shaped.boxes, dtype=torch.float64)).numpy()
    small = np.isin(shaped.labels, [CLASSES.index("Pedestrian"), CLASSES.index("Cyclist")])
    in_small = (idx >= 0) & small[np.maximum(idx, 0)]
    assert (shaped.surface[in_small] == SURFACE_GROUND).sum() > 20

    def in_own_box(f):  # boxes at the sweep's middle; moving objects' returns are spread over its 100 ms
        grown = f.boxes.astype(np.float64).copy()
        grown[:, 3:6] += 0.15
        idx = points_in_boxes(torch.as_tensor(f.points[:, :3], dtype=torch.float64), torch.as_tensor(grown)).numpy()
        on = f.instance >= 0
        return (idx[on] == f.instance[on]).mean()

    assert in_own_box(shaped) >= in_own_box(cast) - 0.005  # the shapes lie inside the boxes


def test_occlusion_is_judged_by_the_boxes_outline(frames):
    """KITTI's occlusion levels (and so the difficulty of each label) come from the share of an object's
    outline that is seen: a ray between a pedestrian's legs does not make it more occluded."""
    from lidarops.data.realism import Realism

    cast, _ = frames
    shaped = Simulator("driving_city", realism=Realism(street_clutter=0.0), **KW).sweep(0)  # clutter occludes
    np.testing.assert_array_equal(shaped.visibility, cast.visibility)
    assert np.isfinite(cast.visibility).sum() > 20
