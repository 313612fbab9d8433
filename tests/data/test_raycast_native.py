"""The native ray caster of the simulator (torch.ops.lidarops.raycast_scene) against the NumPy reference
(lidarops.data._raycast._cast_rays_numpy): random scenes, every scenario preset, empty inputs, moving boxes,
bad input, backend selection.

Agreement rules (see the module docstring of lidarops/data/_raycast.py): box, cylinder and foliage hits are
computed with the same operations in the same order, so their distances agree to ~1e-12; ground hits agree
to 1e-7 relative (the ground's float32 sines: NumPy's SIMD ones and the kernel's differ in the last bit). A ray
may end on a different surface only where its two nearest candidates are that close (a near tie).
"""
from __future__ import annotations

import numpy as np
import pytest

from lidarops.data import _raycast
from lidarops.data.scene import (
    SURFACE_GROUND,
    SURFACE_NONE,
    SURFACE_OBJECT,
    SURFACE_POLE,
    SURFACE_STRUCTURE,
    BoxSet,
    CylinderSet,
    EllipsoidSet,
    Ground,
    SCENARIOS,
)

torch = pytest.importorskip("torch")


def _native_available() -> bool:
    return _raycast._native_op() is not None


pytestmark = pytest.mark.skipif(not _native_available(), reason="lidarops._C with raycast_scene is not built")

GROUND_RTOL = 1e-7  # float32 sines of the ground waves (NumPy's SIMD vs the kernel's; seen: up to 2e-8)
EXACT_RTOL = 1e-12  # boxes, cylinders, ellipsoids, planar ground


# ----------------------------------------------------------------------------- scenes
def random_scene(seed: int, n_boxes=80, n_cyl=30, n_ell=15, waves=True):
    rng = np.random.default_rng(seed)
    center = rng.uniform([-40, -40, -1], [40, 40, 6], size=(n_boxes, 3))
    half = rng.uniform(0.2, 5.0, size=(n_boxes, 3))
    yaw = np.where(rng.random(n_boxes) < 0.6, 0.0, rng.uniform(-np.pi, np.pi, n_boxes))
    moving = rng.random(n_boxes) < 0.25
    velocity = np.where(moving[:, None], rng.normal(0, 5, size=(n_boxes, 3)), 0.0)
    yaw_rate = np.where(moving & (rng.random(n_boxes) < 0.5), rng.normal(0, 1.0, n_boxes), 0.0)
    obj = np.full(n_boxes, -1, np.int32)
    obj[moving] = np.arange(int(moving.sum()))
    kind = np.where(moving, SURFACE_OBJECT, SURFACE_STRUCTURE).astype(np.uint8)
    boxes = BoxSet(center, half, yaw, velocity, yaw_rate, rng.uniform(0.1, 0.9, n_boxes), kind, obj)
    cxy = rng.uniform(-40, 40, size=(n_cyl, 2))
    z0 = rng.uniform(-1, 1, n_cyl)
    cylinders = CylinderSet(cxy, z0, z0 + rng.uniform(0.5, 8, n_cyl), rng.uniform(0.05, 1.5, n_cyl),
                            rng.uniform(0.2, 0.5, n_cyl), np.full(n_cyl, SURFACE_POLE, np.uint8))
    ellipsoids = EllipsoidSet(rng.uniform([-40, -40, 1], [40, 40, 6], size=(n_ell, 3)), rng.uniform(0.8, 4, (n_ell, 3)),
                              rng.uniform(0.1, 1.0, n_ell), rng.uniform(0.4, 0.6, n_ell))
    if waves:
        ground = Ground.random(rng, max_slope=0.02, z0=-0.3)
    else:
        ground = Ground(-0.3, np.array([0.01, -0.005]))
    return ground, boxes, cylinders, ellipsoids, int(moving.sum())


def random_rays(seed: int, n: int, boxes: BoxSet, cylinders: CylinderSet, firings: int = 500):
    """Rays from a few hundred firing positions along a short path, most aimed near some primitive."""
    rng = np.random.default_rng(seed + 1000)
    pos = np.column_stack([np.linspace(0, 1.5, firings), rng.normal(0, 0.05, firings), 1.7 + rng.normal(0, 0.02, firings)])
    firing = np.sort(rng.integers(0, firings, n))
    origins = pos[firing]
    times = firing * (0.05 / firings)
    targets = np.concatenate([boxes.center, np.column_stack([cylinders.center_xy, cylinders.z_max - 0.5])])
    aim = targets[rng.integers(0, len(targets), n)] + rng.normal(0, 2.0, (n, 3))
    dirs = np.where(rng.random((n, 1)) < 0.75, aim - origins, rng.normal(size=(n, 3)))
    dirs[rng.random(n) < 0.03, 2] = 0.0  # exactly horizontal rays: the 1 / 0 branch of the slab test
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins, dirs, times, pos


def both(origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance, num_objects, samples, seed=0):
    out = []
    for backend in ("numpy", "native"):
        out.append(_raycast.cast_rays(origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance,
                                      np.random.default_rng(seed), num_objects, origin_samples=samples, backend=backend))
    return out


# ----------------------------------------------------------------------------- comparison
def candidate_distances(i, origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance, key):
    """Every hit distance of ray ``i`` (ground, all boxes, cylinders, ellipsoids: no culling), sorted."""
    o, d, t = origins[i:i + 1], dirs[i:i + 1], times[i:i + 1]
    found = [_raycast.intersect_ground(o, d, ground, max_distance)[0]]
    if len(boxes):
        p = np.arange(len(boxes))
        found.append(_raycast._intersect_boxes(np.repeat(o, p.size, 0), np.repeat(d, p.size, 0), np.repeat(t, p.size),
                                               boxes, p, np.cos(boxes.yaw), np.sin(boxes.yaw))[0])
    if len(cylinders):
        p = np.arange(len(cylinders))
        found.append(_raycast._intersect_cylinders(np.repeat(o, p.size, 0), np.repeat(d, p.size, 0), cylinders, p)[0])
    if len(ellipsoids):
        p = np.arange(len(ellipsoids))
        found.append(_raycast._intersect_ellipsoids(np.repeat(o, p.size, 0), np.repeat(d, p.size, 0), ellipsoids, p,
                                                    np.full(p.size, i), key)[0])
    s = np.sort(np.concatenate(found))
    return s[np.isfinite(s) & (s <= max_distance)]


def assert_hits_agree(ref, nat, rays, scene, max_distance, key, max_flip_share=1e-3):
    origins, dirs, times = rays
    ground, boxes, cylinders, ellipsoids = scene
    n = ref.distance.shape[0]
    same = (ref.surface == nat.surface) & (ref.object_index == nat.object_index)
    flips = np.flatnonzero(~same)
    # a ray may end elsewhere only at a near tie of its two nearest candidates (or at the ground's tolerance)
    for i in flips:
        s = candidate_distances(i, origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance, key)
        near_ground = SURFACE_GROUND in (ref.surface[i], nat.surface[i]) or SURFACE_NONE in (ref.surface[i], nat.surface[i])
        tol = GROUND_RTOL if near_ground else 1e-9
        assert s.size >= 1, f"ray {i}: surfaces {ref.surface[i]} vs {nat.surface[i]} but no candidate hit"
        tie = s.size >= 2 and s[1] - s[0] <= tol * s[1]
        assert tie or near_ground, (f"ray {i}: numpy {ref.surface[i]}/{ref.object_index[i]} at {ref.distance[i]}, "
                                    f"native {nat.surface[i]}/{nat.object_index[i]} at {nat.distance[i]}; candidates {s[:4]}")
    assert flips.size <= max(1, max_flip_share * n), f"{flips.size} of {n} rays end on different surfaces"
    ground_hit = same & (ref.surface == SURFACE_GROUND)
    other = same & ~ground_hit & (ref.surface != SURFACE_NONE)
    for mask, rtol, what in ((ground_hit, GROUND_RTOL, "ground"), (other, EXACT_RTOL, "primitive")):
        if mask.any():
            err = np.abs(nat.distance[mask] - ref.distance[mask]) / ref.distance[mask]
            worst = int(np.argmax(err))
            assert err[worst] <= rtol, f"{what} distance: rel. error {err[worst]:.3g} at ray {np.flatnonzero(mask)[worst]}"
            np.testing.assert_allclose(nat.cos_incidence[mask], ref.cos_incidence[mask], rtol=0, atol=1e3 * rtol)
    assert np.all(np.isinf(nat.distance[same & (ref.surface == SURFACE_NONE)]))
    np.testing.assert_array_equal(nat.reflectivity[same], ref.reflectivity[same])
    np.testing.assert_array_equal(nat.extra_dropout[same], ref.extra_dropout[same])
    # crossings do not depend on the ground; visible counts move only with the rays that flipped
    np.testing.assert_array_equal(nat.object_rays, ref.object_rays)
    assert np.abs(nat.object_visible - ref.object_visible).sum() <= flips.size
    return flips.size


# ----------------------------------------------------------------------------- random scenes
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("waves", [True, False])
def test_random_scenes_match_numpy(seed, waves):
    ground, boxes, cylinders, ellipsoids, n_obj = random_scene(seed, waves=waves)
    origins, dirs, times, pos = random_rays(seed, 20_000, boxes, cylinders)
    ref, nat = both(origins, dirs, times, ground, boxes, cylinders, ellipsoids, 60.0, n_obj, pos, seed)
    kinds = np.bincount(ref.surface, minlength=6)
    assert kinds[SURFACE_GROUND] > 1000 and kinds[SURFACE_STRUCTURE] > 1000 and kinds[SURFACE_OBJECT] > 300
    assert kinds[4] > 50 and kinds[SURFACE_POLE] > 50 and kinds[SURFACE_NONE] > 100
    assert ref.object_rays.sum() > ref.object_visible.sum() > 0  # some crossings are occluded
    key = int(np.random.default_rng(seed).integers(1 << 63))
    flips = assert_hits_agree(ref, nat, (origins, dirs, times), (ground, boxes, cylinders, ellipsoids), 60.0, key)
    if not waves:
        assert flips == 0


def test_results_do_not_depend_on_threads():
    ground, boxes, cylinders, ellipsoids, n_obj = random_scene(3)
    origins, dirs, times, pos = random_rays(3, 30_000, boxes, cylinders)
    threads = torch.get_num_threads()
    runs = []
    try:
        for k in (1, max(2, threads)):
            torch.set_num_threads(k)
            runs.append(_raycast.cast_rays(origins, dirs, times, ground, boxes, cylinders, ellipsoids, 60.0,
                                           np.random.default_rng(0), n_obj, origin_samples=pos, backend="native"))
    finally:
        torch.set_num_threads(threads)
    for name in ("distance", "surface", "object_index", "cos_incidence", "object_rays", "object_visible"):
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name), err_msg=name)


# ----------------------------------------------------------------------------- scenario presets
def block_inputs(name: str, seed: int, blocks, monkeypatch):
    """The arguments the simulator passes to cast_rays for some blocks of a scenario."""
    from lidarops.data import synthetic

    captured = []

    def spy(*args, **kwargs):
        captured.append((args, kwargs))
        return _raycast.cast_rays(*args, **kwargs)

    monkeypatch.setattr(synthetic, "cast_rays", spy)
    sim = synthetic.Simulator(name, seed=seed)
    for b in blocks:
        sim._block(b)
    monkeypatch.undo()
    return captured


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_blocks_match_numpy(name, monkeypatch):
    total_flips = total_rays = 0
    for args, kwargs in block_inputs(name, 4, (0, 7), monkeypatch):
        origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance, _, num_objects = args
        samples = kwargs["origin_samples"]
        ref, nat = both(origins, dirs, times, ground, boxes, cylinders, ellipsoids, max_distance, num_objects, samples, 9)
        assert (ref.surface != SURFACE_NONE).sum() > 0.2 * origins.shape[0]
        key = int(np.random.default_rng(9).integers(1 << 63)) if len(ellipsoids) else 0
        total_flips += assert_hits_agree(ref, nat, (origins, dirs, times), (ground, boxes, cylinders, ellipsoids),
                                         max_distance, key)
        total_rays += origins.shape[0]
    assert total_flips <= 1e-4 * total_rays


@pytest.mark.parametrize("name", ["drone_lock", "driving_highway"])
def test_sweeps_agree_between_backends(name, monkeypatch):
    from lidarops.data.synthetic import Simulator

    frames = {}
    for env in ("0", "1"):
        monkeypatch.setenv("LIDAROPS_DATA_NATIVE", env)
        frames[env] = Simulator(name, seed=2).sweep(1)
    a, b = frames["0"], frames["1"]
    assert abs(a.num_points - b.num_points) <= 1e-4 * a.num_points + 1
    if a.num_points == b.num_points:
        np.testing.assert_allclose(a.points[:, :3], b.points[:, :3], rtol=0, atol=1e-3)
        np.testing.assert_array_equal(a.surface, b.surface)
    np.testing.assert_array_equal(a.num_points_in_box, b.num_points_in_box)


# ----------------------------------------------------------------------------- specific cases
def test_empty_inputs():
    ground, boxes, cylinders, ellipsoids, n_obj = random_scene(0)
    z3, z = np.zeros((0, 3)), np.zeros(0)
    for backend in ("numpy", "native"):
        hits = _raycast.cast_rays(z3, z3, z, ground, boxes, cylinders, ellipsoids, 50.0, np.random.default_rng(0), n_obj,
                                  backend=backend)
        assert hits.distance.shape == hits.surface.shape == hits.object_index.shape == (0,)
        assert hits.object_rays.shape == hits.object_visible.shape == (n_obj,) and not hits.object_rays.any()
    # rays but no primitives, no waves, no objects
    origins, dirs, times, pos = random_rays(0, 2000, boxes, cylinders)
    flat = Ground(-0.3, np.array([0.0, 0.0]))
    ref, nat = both(origins, dirs, times, flat, BoxSet.empty(), CylinderSet.empty(), EllipsoidSet.empty(), 50.0, 0, pos)
    assert set(np.unique(nat.surface)) == {SURFACE_NONE, SURFACE_GROUND}
    np.testing.assert_array_equal(nat.surface, ref.surface)
    np.testing.assert_allclose(nat.distance, ref.distance, rtol=EXACT_RTOL)
    assert nat.object_rays.shape == (0,)


def test_moving_box_is_hit_where_it_is_at_the_ray_time():
    """A box crossing the rays' line of sight: only the rays fired while it is there hit it (checked against the
    box's position, not against the NumPy code)."""
    n = 1000
    times = np.linspace(0.0, 1.0, n)
    origins = np.zeros((n, 3))
    dirs = np.tile([1.0, 0.0, 0.0], (n, 1))
    # 2 x 1 x 2 box at x = 20 crossing y = 0 at t = 0.5, 4 m/s along y, turning
    boxes = BoxSet(np.array([[20.0, -2.0, 0.0]]), np.array([[1.0, 0.5, 1.0]]), np.zeros(1), np.array([[0.0, 4.0, 0.0]]),
                   np.array([0.3]), np.array([0.5]), np.array([SURFACE_OBJECT], np.uint8), np.array([0], np.int32))
    flat = Ground(-10.0, np.zeros(2))
    hits = _raycast.cast_rays(origins, dirs, times, flat, boxes, CylinderSet.empty(), EllipsoidSet.empty(), 100.0,
                              np.random.default_rng(0), 1, backend="native")
    y = -2.0 + 4.0 * times
    yaw = 0.3 * times
    # the ray (y = 0) meets the turning box iff its line crosses the rotated footprint; the near face is at
    # x = 20 - (half-extent along x of the rotated rectangle at height y = 0)
    inside = np.abs(y) <= np.abs(np.cos(yaw)) * 0.5 + np.abs(np.sin(yaw)) * 1.0 - 1e-9
    clear = np.abs(y) >= np.abs(np.cos(yaw)) * 0.5 + np.abs(np.sin(yaw)) * 1.0 + 1e-9
    assert inside.sum() > 100 and clear.sum() > 600
    assert np.all(hits.object_index[inside] == 0) and np.all(hits.surface[inside] == SURFACE_OBJECT)
    assert np.all(hits.object_index[clear] == -1)
    # where the ray enters the box at its time, by sampling x along the ray (step 1e-4) in the box's frame
    x = np.arange(18.0, 22.0, 1e-4)
    ii = np.flatnonzero(inside)
    dx, dy = x[None, :] - 20.0, -y[ii, None]
    c, s = np.cos(yaw[ii, None]), np.sin(yaw[ii, None])
    within = (np.abs(c * dx + s * dy) <= 1.0) & (np.abs(-s * dx + c * dy) <= 0.5)
    entry = x[np.argmax(within, axis=1)]
    assert within.any(axis=1).all()
    np.testing.assert_allclose(hits.distance[ii], entry, atol=2e-4)
    assert hits.object_rays[0] == hits.object_visible[0] == int((hits.object_index == 0).sum())


def test_foliage_depth_is_exponential():
    """Rays through a big foliage ellipsoid return after an exponential free path (mean = mean_free_path)."""
    n = 40_000
    rng = np.random.default_rng(1)
    origins = np.zeros((n, 3))
    dirs = np.column_stack([np.ones(n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.05, 0.05, n)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ell = EllipsoidSet(np.array([[30.0, 0.0, 0.0]]), np.array([[20.0, 20.0, 20.0]]), np.array([0.7]), np.array([0.5]))
    flat = Ground(-50.0, np.zeros(2))
    hits = _raycast.cast_rays(origins, dirs, np.zeros(n), flat, BoxSet.empty(), CylinderSet.empty(), ell, 100.0,
                              np.random.default_rng(2), 0, backend="native")
    assert np.all(hits.surface == 4)
    b = 30.0 * dirs[:, 0]
    depth = hits.distance - (b - np.sqrt(b * b - (30.0**2 - 20.0**2)))  # minus where the ray enters the sphere
    assert abs(depth.mean() - 0.7) < 0.03 and abs(np.median(depth) - 0.7 * np.log(2)) < 0.03
    assert 0.3 <= hits.cos_incidence.min() and hits.cos_incidence.max() < 1.0
    again = _raycast.cast_rays(origins, dirs, np.zeros(n), flat, BoxSet.empty(), CylinderSet.empty(), ell, 100.0,
                               np.random.default_rng(2), 0, backend="native")
    np.testing.assert_array_equal(again.distance, hits.distance)  # a function of the generator's seed
    other = _raycast.cast_rays(origins, dirs, np.zeros(n), flat, BoxSet.empty(), CylinderSet.empty(), ell, 100.0,
                               np.random.default_rng(3), 0, backend="native")
    assert np.mean(other.distance == hits.distance) < 0.01


# ----------------------------------------------------------------------------- errors and backend selection
def _op_args(n=4):
    ground, boxes, cylinders, ellipsoids, n_obj = random_scene(0, 5, 3, 2)
    t = _raycast._f64
    dirs = np.tile([1.0, 0.0, 0.0], (n, 1))
    return dict(origins=t(np.zeros((n, 3))), dirs=t(dirs), times=t(np.zeros(n)), origin_samples=t(np.zeros((1, 3))),
                ground_plane=t(np.array([0.0, 0.0, 0.0])), wave_amp=t(ground.wave_amp), wave_k=t(ground.wave_k),
                wave_phase=t(ground.wave_phase), box_center=t(boxes.center), box_half=t(boxes.half), box_yaw=t(boxes.yaw),
                box_velocity=t(boxes.velocity), box_yaw_rate=t(boxes.yaw_rate), box_reflectivity=t(boxes.reflectivity),
                box_kind=t(boxes.kind, np.uint8), box_object=t(boxes.object_index, np.int32),
                cyl_center_xy=t(cylinders.center_xy), cyl_z_min=t(cylinders.z_min), cyl_z_max=t(cylinders.z_max),
                cyl_radius=t(cylinders.radius), cyl_reflectivity=t(cylinders.reflectivity),
                cyl_kind=t(cylinders.kind, np.uint8), ell_center=t(ellipsoids.center), ell_radii=t(ellipsoids.radii),
                ell_mean_free_path=t(ellipsoids.mean_free_path), ell_reflectivity=t(ellipsoids.reflectivity),
                max_distance=50.0, foliage_key=7, num_objects=n_obj, ground_iterations=3, ground_tolerance=2e-4)


@pytest.mark.parametrize("name, bad, message", [
    ("origins", lambda t: t.float(), "origins must be Double"),
    ("dirs", lambda t: t[:, :2], "dirs must have size 3 in dimension 1"),
    ("times", lambda t: t[:2], "times must have size 4 in dimension 0"),
    ("box_kind", lambda t: t.long(), "box_kind must be Byte"),
    ("box_object", lambda t: t.float(), "box_object must be Int"),
    ("cyl_radius", lambda t: t[None], "cyl_radius must have 1 dimension"),
    ("wave_k", lambda t: t.reshape(-1), "wave_k must have 2 dimension"),
    ("ell_radii", lambda t: t[:1], "ell_radii must have size 2 in dimension 0"),
])
def test_op_errors_name_the_argument(name, bad, message):
    args = _op_args()
    args[name] = bad(args[name])
    with pytest.raises(ValueError, match=message):
        torch.ops.lidarops.raycast_scene(**args)


def test_op_rejects_object_index_out_of_range():
    args = _op_args()
    args["num_objects"] = 0
    args["box_object"] = torch.zeros_like(args["box_object"])
    with pytest.raises(ValueError, match=r"box_object\[0\] = 0 but num_objects = 0"):
        torch.ops.lidarops.raycast_scene(**args)


def test_opcheck():
    args = _op_args(32)
    torch.library.opcheck(torch.ops.lidarops.raycast_scene.default, (), args,
                          test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("backend", ["numpy", "native"])
def test_cast_rays_errors_name_the_argument(backend):
    ground, boxes, cylinders, ellipsoids, n_obj = random_scene(0, 5, 3, 2)
    o, d, t = np.zeros((4, 3)), np.tile([1.0, 0.0, 0.0], (4, 1)), np.zeros(4)
    rest = (ground, boxes, cylinders, ellipsoids, 50.0, np.random.default_rng(0), n_obj)
    with pytest.raises(ValueError, match=r"dirs must have shape \(4, 3\), got \(4, 2\)"):
        _raycast.cast_rays(o, d[:, :2], t, *rest, backend=backend)
    with pytest.raises(ValueError, match=r"times must have shape \(4,\)"):
        _raycast.cast_rays(o, d, t[:3], *rest, backend=backend)
    with pytest.raises(ValueError, match="origins must be a float array, got int64"):
        _raycast.cast_rays(o.astype(np.int64), d, t, *rest, backend=backend)
    with pytest.raises(ValueError, match="backend must be"):
        _raycast.cast_rays(o, d, t, *rest, backend="gpu")


def test_backend_selection(monkeypatch):
    monkeypatch.delenv("LIDAROPS_DATA_NATIVE", raising=False)
    assert _raycast.raycast_backend() == "native"
    monkeypatch.setenv("LIDAROPS_DATA_NATIVE", "0")
    assert _raycast.raycast_backend() == "numpy"
    assert _raycast.raycast_backend("native") == "native"
    monkeypatch.setenv("LIDAROPS_DATA_NATIVE", "1")
    assert _raycast.raycast_backend() == "native"
    monkeypatch.setenv("LIDAROPS_DATA_NATIVE", "maybe")
    with pytest.raises(ValueError, match="LIDAROPS_DATA_NATIVE"):
        _raycast.raycast_backend()


def test_simulator_uses_the_native_caster_by_default(monkeypatch):
    from lidarops.data.synthetic import Simulator

    monkeypatch.delenv("LIDAROPS_DATA_NATIVE", raising=False)

    def fail(*args, **kwargs):
        raise AssertionError("the NumPy caster was used")

    monkeypatch.setattr(_raycast, "_cast_rays_numpy", fail)
    assert Simulator("drone_lock", seed=0).sweep(0).num_points > 1000
    monkeypatch.setenv("LIDAROPS_DATA_NATIVE", "0")
    with pytest.raises(AssertionError, match="NumPy caster"):
        Simulator("drone_lock", seed=0).sweep(0)
