"""The simulator's realism profile (lidarops.data.realism): frames without it unchanged, frames with it a
function of the seed, and the statistics it is calibrated for moved the way real KITTI scans have them
(benchmarks/bm_sim2real.py measures them against the real scans themselves)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lidarops.data.frame import CLASSES
from lidarops.data.realism import Realism, make_realism
from lidarops.data.scene import SURFACE_GROUND, SURFACE_OBJECT
from lidarops.data.synthetic import Simulator
from tests.helpers.scenes import STRUCTURE_ZONES, in_zones, primitive_extents

SEED = 7

#: every effect off: the returns and their intensities as cast (below the knee at 0.6)
NEUTRAL = Realism(shaped_classes=(), street_clutter=0.0, greenhouse_keep=1.0, roof_keep=1.0, greenhouse_zero=0.0, dark_zero=0.0, light_zero=0.0, tyre_zero=0.0,
                  surface_gain=(1.0,) * 6, beam_gain_std=0.0, weak_from=1.0, quantum=0.0)


@pytest.fixture(scope="module")
def sweeps():
    kw = dict(object_counts="dense")
    return {name: Simulator("driving_city", seed=SEED, realism=r, **kw).sweep(0)
            for name, r in (("cast", None), ("neutral", NEUTRAL), ("kitti", "kitti"))}


def _vehicle_stats(frame):
    """Per vehicle return: its height fraction in its box, and its intensity."""
    on = (frame.instance >= 0) & np.isin(frame.labels[np.maximum(frame.instance, 0)],
                                         [CLASSES.index(c) for c in ("Car", "Truck", "Bus")])
    box = frame.boxes[frame.instance[on]]
    height = (frame.points[on, 2] - (box[:, 2] - box[:, 5] / 2)) / box[:, 5]
    return np.clip(height, 0, 0.999), frame.points[on, 3]


def test_without_realism_the_frames_are_those_of_before(sweeps):
    """A neutral profile draws its own random numbers: the same returns, in the same order, with the same
    positions and (below its knee) intensities as no profile at all."""
    cast, neutral = sweeps["cast"], sweeps["neutral"]
    np.testing.assert_array_equal(cast.points[:, :3], neutral.points[:, :3])
    low = cast.points[:, 3] < 0.6
    np.testing.assert_allclose(cast.points[low, 3], neutral.points[low, 3], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(cast.instance, neutral.instance)


@pytest.mark.parametrize("profile", ["kitti", "kitti_dr"])  # kitti_dr: laser heights, pedestrians' builds...
def test_same_seed_same_frame_and_independent_of_request_order(profile):
    a = Simulator("driving_city", seed=SEED, realism=profile)
    b = Simulator("driving_city", seed=SEED, realism=profile)
    f1 = b.sweep(1)  # b generates frame 1 first
    f0 = b.sweep(0)
    np.testing.assert_array_equal(a.sweep(0).points, f0.points)
    np.testing.assert_array_equal(a.sweep(1).points, f1.points)
    other = Simulator("driving_city", seed=SEED + 1, realism=profile).sweep(0)
    assert other.points.shape != f0.points.shape or not np.array_equal(other.points, f0.points)


def test_pedestrian_build_varies_legs_coats_and_shoulders_only_where_asked():
    """kitti: every pedestrian has the plain shape (its shape numbers u[:, 1:] are 0); kitti_dr
    (pedestrian_build 1): they vary per pedestrian over [0, 1), and more of a pedestrian's returns fall below its
    hips, as in real scans (real KITTI: half of a pedestrian's points)."""
    kw = dict(seed=4, object_counts={"Pedestrian": 14, "Car": 8})
    plain, built = Simulator("driving_city", realism="kitti", **kw), Simulator("driving_city", realism="kitti_dr", **kw)
    ped = plain.scenario.object_labels == CLASSES.index("Pedestrian")
    assert ped.sum() >= 10 and not plain._shape_u[ped, 1:].any() and plain._shape_u[~ped, 1:].any()
    assert (built._shape_u[ped, 1:].std(0) > 0.15).all()

    def lower_half(sim):
        f = sim.sweep(0)
        shares = []
        for j in np.flatnonzero(f.labels == CLASSES.index("Pedestrian")):
            z = f.points[f.instance == j, 2]
            if len(z) >= 10:
                b = f.boxes[j]
                shares.append(((z - (b[2] - b[5] / 2)) / b[5] < 0.5).mean())
        return np.mean(shares), len(shares)
    (p, n_p), (b, n_b) = lower_half(plain), lower_half(built)
    assert n_p >= 5 and n_b >= 5 and b > p + 0.03, (p, b)


@pytest.mark.parametrize("hair", [0.0, 1.0])
def test_hair_dropout_loses_the_returns_from_the_top_of_a_pedestrians_head(hair):
    """hair_dropout 1: no pedestrian return above 0.88 of its height (the shape's head reaches the box's top);
    0: some. Heights are measured from the box's bottom (a walker moves, but not up or down)."""
    sim = Simulator("driving_city", seed=4, object_counts={"Pedestrian": 14, "Car": 4}, ego_speed=0.0,
                    realism=dataclasses.replace(make_realism("kitti"), hair_dropout=hair, pedestrian_groups=0.0))
    f = sim.sweep(0)
    top = 0
    for j in np.flatnonzero(f.labels == CLASSES.index("Pedestrian")):
        z, b = f.points[f.instance == j, 2], f.boxes[j]
        top += int(((z - (b[2] - b[5] / 2)) / b[5] > 0.88).sum())
    assert (top == 0) if hair == 1.0 else (top > 5), top


def test_vehicles_lose_their_greenhouse_and_read_zero_as_real_cars_do(sweeps):
    h_cast, i_cast = _vehicle_stats(sweeps["cast"])
    h_real, i_real = _vehicle_stats(sweeps["kitti"])
    top = lambda h: float((h >= 2 / 3).mean())  # noqa: E731
    assert top(h_cast) > 0.28, "the box-shaped vehicles' roofs give many returns"
    assert top(h_real) < min(0.2, top(h_cast) / 2), \
        f"top third {top(h_real):.2f} (cast {top(h_cast):.2f}): glass and round roofs return little"
    assert (i_cast == 0).mean() < 0.05
    assert 0.3 < (i_real == 0).mean() < 0.7, "dark paint, glass and tyres read 0 on about half the returns"
    assert len(h_real) < len(h_cast)  # the greenhouse returns dropped, not moved


def test_intensity_is_calibrated_quantised_and_zero_when_weak(sweeps):
    cast, real = sweeps["cast"], sweeps["kitti"]
    i = real.points[:, 3]
    assert ((i >= 0) & (i <= 1)).all()
    np.testing.assert_allclose(i * 100, np.round(i * 100), atol=1e-3)  # steps of 0.01
    ground_cast = np.median(cast.points[cast.surface == SURFACE_GROUND, 3])
    ground_real = np.median(i[real.surface == SURFACE_GROUND])
    assert ground_cast < 0.1 and 0.15 < ground_real < 0.4, (ground_cast, ground_real)
    r = np.hypot(real.points[:, 0], real.points[:, 1])
    far = (r > 45) & (real.surface == SURFACE_GROUND)
    assert far.any() and (i[far] == 0).mean() > (i[(r < 15) & (real.surface == SURFACE_GROUND)] == 0).mean()
    assert (i[real.surface == SURFACE_OBJECT] == 1.0).mean() < 0.01


def test_vehicle_returns_follow_their_probabilities():
    r = Realism()
    rng = np.random.default_rng(0)
    n = 200_000
    height = rng.random(n)
    dark = rng.random(n) < 0.5
    keep, zero = r.vehicle_returns(np.random.default_rng(1), height, dark)
    glass = height >= r.greenhouse_from
    roof = height >= 0.98
    assert keep[~glass].all()
    assert abs(keep[glass & ~roof].mean() - r.greenhouse_keep) < 0.01
    assert abs(keep[roof].mean() - r.roof_keep) < 0.03
    body = ~glass & (height >= r.tyre_band)
    assert abs(zero[body & dark].mean() - r.dark_zero) < 0.01
    assert abs(zero[body & ~dark].mean() - r.light_zero) < 0.01
    tyre = height < r.tyre_band
    assert abs(zero[tyre & ~dark].mean() - max(r.light_zero, r.tyre_zero)) < 0.01
    assert abs(zero[glass].mean() - r.greenhouse_zero) < 0.01


@pytest.mark.parametrize("field,value", [("greenhouse_keep", 1.5), ("dark_paint", -0.1), ("weak_from", float("nan")),
                                         ("quantum", 0.9), ("beam_gain_std", 2.0), ("mixed_pixels", 1.1),
                                         ("mixed_gap", 0.0), ("mount_height_jitter", 0.8),
                                         ("intensity_scale_jitter", float("inf")), ("label_tightness", 0.6),
                                         ("pedestrian_groups", -0.1), ("beam_choices", (64, 0)),
                                         ("beam_choices", [64]), ("beam_choices", (True,)), ("dropout_max", 0.95),
                                         ("range_noise_max", -1.0), ("pedestrian_build", 1.5),
                                         ("pedestrian_build", float("nan")), ("laser_offsets", "yes"),
                                         ("hair_dropout", 1.2)])
def test_bad_parameters_are_named(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(Realism(), **{field: value})


def test_bad_profiles_are_refused():
    with pytest.raises(ValueError, match="surface_gain"):
        Realism(surface_gain=(1.0, 2.0))
    with pytest.raises(ValueError, match="vehicle_classes"):
        Realism(vehicle_classes=())
    with pytest.raises(ValueError, match="shaped_classes"):
        Realism(shaped_classes=(1,))
    for shaped in (("Car", "Boat"), ["Car"], ("Barrier",)):
        with pytest.raises(ValueError, match="shaped_classes"):
            Realism(shaped_classes=shaped)
    with pytest.raises(ValueError, match="kitti"):
        make_realism("carla")
    with pytest.raises(ValueError, match="realism"):
        Simulator("driving_city", seed=0, realism=3)
    assert make_realism(None) is None
    for bad, named in (("kitti:nope=1", "nope"), ("kitti:parking_lots=often", "parking_lots"),
                       ("kitti:parking_lots", "parking_lots"), ("carla:parking_lots=1", "carla"),
                       ("kitti:laser_offsets=yes", "laser_offsets"), ("kitti:beam_choices=32/x", "beam_choices"),
                       ("kitti:parking_lots=2", "parking_lots")):
        with pytest.raises(ValueError, match=named):
            make_realism(bad)
    assert make_realism("kitti") == Realism(crossing_pedestrians=0.4, parking_lots=0.4, open_ground=0.3, low_clutter=2.0,
                                            roadside_structures=0.7)


def test_profile_strings_change_the_fields_they_name():
    """``preset:field=value,...``: the preset with those fields changed, each read as its field's type (a number,
    a flag, a tuple joined by ``/``), the others the preset's; the simulator and ``data synth`` take it, and the
    recipe records it as written."""
    got = make_realism("kitti:crossing_groups=0.6, crossing_cyclists=0.2,laser_offsets=true,beam_choices=32/64")
    assert got == dataclasses.replace(make_realism("kitti"), crossing_groups=0.6, crossing_cyclists=0.2,
                                      laser_offsets=True, beam_choices=(32, 64))
    assert make_realism("kitti_dr:beam_choices=()").beam_choices == ()
    assert make_realism("kitti:shaped_classes=Car/Pedestrian").shaped_classes == ("Car", "Pedestrian")
    a = Simulator("driving_city", seed=2, realism="kitti:crossing_pedestrians=1,crossing_groups=1").scenario
    b = Simulator("driving_city", seed=2, realism=dataclasses.replace(make_realism("kitti"), crossing_pedestrians=1.0,
                                                                      crossing_groups=1.0)).scenario
    np.testing.assert_array_equal(a.objects.center, b.objects.center)


def test_mixed_pixels_move_edge_returns_along_their_rays_toward_the_background():
    """Every effect off but mixed pixels (all edges mixed): the same returns in the same order, except those whose
    beam neighbour (one firing before or after) hit something at least ``mixed_gap`` farther. Those keep their ray,
    move back by less than the depth step, and belong to no object."""
    mixed = dataclasses.replace(NEUTRAL, mixed_pixels=1.0)
    a = Simulator("driving_city", seed=SEED, realism=NEUTRAL, object_counts="dense").sweep(0)
    b = Simulator("driving_city", seed=SEED, realism=mixed, object_counts="dense").sweep(0)
    assert a.points.shape == b.points.shape
    ra, rb = np.linalg.norm(a.points[:, :3], axis=1), np.linalg.norm(b.points[:, :3], axis=1)
    moved = np.abs(rb - ra) > 1e-4
    assert 0.005 < moved.mean() < 0.3, moved.mean()  # edges: some returns, not most
    np.testing.assert_array_equal(a.points[~moved], b.points[~moved])
    assert (rb[moved] > ra[moved]).all()  # toward what lies behind
    cos = (a.points[moved, :3] * b.points[moved, :3]).sum(1) / (ra[moved] * rb[moved])
    assert (cos > 1 - 1e-6).all()  # along the same ray
    assert (b.instance[moved] == -1).all() and (a.instance[moved] >= 0).any()  # off the objects they left
    assert (rb[moved] - ra[moved]).max() < 120.0


def test_scene_randomisation_draws_a_sensor_height_and_an_intensity_scale_per_seed():
    """kitti_dr: each scene's sensor height within 0.2 m of 1.73 (the ground under the sensor follows) and its
    intensity gain within [1 / 1.3, 1.3] (the intensities follow); kitti draws neither."""
    heights, gains = [], []
    plain = dataclasses.replace(make_realism("kitti"), shaped_classes=(), street_clutter=0.0)
    for seed in range(4):
        sim = Simulator("driving_city", seed=seed, realism=dataclasses.replace(plain, mount_height_jitter=0.2,
                                                                               intensity_scale_jitter=0.3))
        ref = Simulator("driving_city", seed=seed, realism=plain)
        ego = sim.scenario.ego.position0
        height = float(ego[2] - sim.scenario.ground.height(np.array([ego[0]]), np.array([ego[1]]))[0])
        f, g = sim.sweep(0), ref.sweep(0)
        near = lambda fr: (np.hypot(fr.points[:, 0], fr.points[:, 1]) < 12) & (fr.instance < 0)  # noqa: E731
        assert abs(float(np.median(f.points[near(f), 2])) + height) < 0.1, seed
        mid = lambda fr: fr.points[(fr.points[:, 3] > 0.02) & (fr.points[:, 3] < 0.45), 3]  # noqa: E731
        ratio = float(np.median(mid(f)) / np.median(mid(g)))
        assert abs(ratio / sim._intensity_scale - 1) < 0.1, (seed, ratio, sim._intensity_scale)
        heights.append(height)
        gains.append(sim._intensity_scale)
        ref_ego = ref.scenario.ego.position0
        assert abs(ref_ego[2] - ref.scenario.ground.height(np.array([ref_ego[0]]), np.array([ref_ego[1]]))[0]
                   - 1.73) < 1e-9 and ref._intensity_scale == 1.0
    assert all(abs(h - 1.73) <= 0.2 for h in heights) and max(heights) - min(heights) > 0.05
    assert all(1 / 1.3 <= k <= 1.3 for k in gains) and max(gains) - min(gains) > 0.02
    assert make_realism("kitti_dr").mixed_pixels > 0 and Realism().mixed_pixels == 0
    high = Simulator("driving_highway", seed=1, sensor_height=2.5).scenario
    assert abs(high.ego.position0[2] - high.ground.height(high.ego.position0[:1], high.ego.position0[1:2])[0]
               - 2.5) < 1e-9
    for bad in (0.2, float("nan"), 6.0):
        with pytest.raises(ValueError, match="sensor_height"):
            Simulator("driving_city", seed=1, sensor_height=bad)
    with pytest.raises(TypeError, match="sensor_height"):
        Simulator("drone_bridge", seed=1, sensor_height=2.0)


def _pedestrians_near(sim, within=1.5):
    """(pedestrians ahead of the car, those with another within ``within`` m), from the scene's labels."""
    objects, labels = sim.scenario.objects, sim.scenario.object_labels
    xy = objects.center[labels == CLASSES.index("Pedestrian")][:, :2]
    xy = xy[(xy[:, 0] > 0) & (xy[:, 0] < 70)]
    if len(xy) < 2:
        return len(xy), 0
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return len(xy), int((d.min(1) < within).sum())


def test_pedestrian_groups_walk_in_single_file_without_overlaps():
    """driving_city's pedestrian_groups (kitti_dr: 0.3): many more pedestrians have another within 1.5 m (the
    real frames: 54 %), the scene's pedestrian count is kept, no two pedestrians overlap now or 3 s later, and
    with groups off the scene is the one of before."""
    counts = [0, 0, 0, 0]
    for seed in range(12):
        off = Simulator("driving_city", seed=seed)
        on = Simulator("driving_city", seed=seed, pedestrian_groups=0.3)
        n0, near0 = _pedestrians_near(off)
        n1, near1 = _pedestrians_near(on)
        counts = [counts[0] + n0, counts[1] + near0, counts[2] + n1, counts[3] + near1]
        ped = CLASSES.index("Pedestrian")
        assert (on.scenario.object_labels == ped).sum() == (off.scenario.object_labels == ped).sum()
        ground = on.scenario.object_labels == ped  # the walkers' lanes hold pedestrians only
        for t in (0.0, 3.0):
            boxes = on.scenario.objects
            centre = (boxes.center[:, :2] + boxes.velocity[:, :2] * t)[ground]
            half, yaw = boxes.half[ground, :2], boxes.yaw[ground]
            # axis-aligned bounds of each box (yaw within a few degrees of the lanes' headings): no two overlap
            ext = np.abs(np.cos(yaw))[:, None] * half + np.abs(np.sin(yaw))[:, None] * half[:, ::-1]
            lo, hi = centre - ext, centre + ext
            overlap = (lo[:, None] < hi[None] - 1e-6).all(2) & (lo[None] < hi[:, None] - 1e-6).all(2)
            np.fill_diagonal(overlap, False)
            assert not overlap.any(), (seed, t, np.argwhere(overlap)[:3])
    assert counts[1] / counts[0] < 0.15 and counts[3] / counts[2] > 0.4, counts
    same = Simulator("driving_city", seed=3, pedestrian_groups=0.0).scenario.objects.center
    np.testing.assert_array_equal(same, Simulator("driving_city", seed=3).scenario.objects.center)
    with pytest.raises(ValueError, match="pedestrian_groups"):
        Simulator("driving_city", seed=3, pedestrian_groups=1.5)
    with pytest.raises(TypeError, match="pedestrian_groups"):
        Simulator("driving_highway", seed=3, pedestrian_groups=0.3)


def _assert_clear(scenario, rows, seed):
    """No labelled box of ``rows`` overlaps another object's in bird's-eye view (shapely's intersection of the
    rotated footprints)."""
    import shapely

    from lidarops.data.geometry import box_corners

    b = scenario.objects
    footprints = shapely.polygons(box_corners(np.concatenate([b.center, 2 * b.half, b.yaw[:, None]], axis=1))[:, :4, :2])
    for i in np.flatnonzero(rows):
        shared = shapely.area(shapely.intersection(footprints[i], footprints))
        shared[i] = 0.0
        assert (shared < 1e-9).all(), (seed, i, np.flatnonzero(shared >= 1e-9), scenario.object_labels[shared >= 1e-9])


def _assert_city_option_checked(option):
    """``option`` at 0 leaves driving_city's scene as it was; a value above 1 and the option on the highway are
    named."""
    np.testing.assert_array_equal(Simulator("driving_city", seed=3, **{option: 0.0}).scenario.objects.center,
                                  Simulator("driving_city", seed=3).scenario.objects.center)
    with pytest.raises(ValueError, match=option):
        Simulator("driving_city", seed=3, **{option: 1.5})
    with pytest.raises(TypeError, match=option):
        Simulator("driving_highway", seed=3, **{option: 0.3})


def test_crossing_pedestrians_cross_ahead_without_overlaps():
    """driving_city's crossing_pedestrians (kitti, kitti_dr: 0.4): pedestrians on the road ahead, walking across
    it, none overlapping another object in bird's-eye view (shapely's intersection of the rotated footprints), the
    scene's pedestrian count kept (an ``object_counts`` of 2 too), and with the option off the scene of before."""
    pytest.importorskip("shapely")
    ped = CLASSES.index("Pedestrian")
    crossing, across = 0, []
    for seed in range(40):
        on = Simulator("driving_city", seed=seed, crossing_pedestrians=1.0).scenario
        off = Simulator("driving_city", seed=seed).scenario
        assert (on.object_labels == ped).sum() == (off.object_labels == ped).sum()
        b = on.objects
        road = (on.object_labels == ped) & (np.abs(b.center[:, 1]) < 10.5)
        crossing += road.sum()
        if road.any():  # one crosswalk 3 m wide, 5-30 m ahead; heading across the road
            x = b.center[road, 0]
            assert x.min() >= 3.5 - 1e-9 and x.max() <= 31.5 + 1e-9 and x.max() - x.min() <= 3.0 + 1e-9
            across.extend(np.abs(np.cos(b.yaw[road])))  # 0 when walking straight across
        _assert_clear(on, road, seed)
    assert crossing >= 30, crossing
    assert np.mean(np.asarray(across) < np.cos(np.pi / 2 - 0.75)) > 0.9, np.round(across, 2)
    two = Simulator("driving_city", seed=1, crossing_pedestrians=1.0, object_counts={"Pedestrian": 2}).scenario
    assert (two.object_labels == ped).sum() <= 2
    _assert_city_option_checked("crossing_pedestrians")


def test_crossing_groups_walk_close_together_without_overlaps():
    """driving_city's crossing_groups: crossing pedestrians walking with others, side by side or in file, so their
    nearest neighbours stand much nearer than pedestrians placed one by one (the real scans' crossing groups: centres
    0.6-0.9 m apart), a companion at its group's heading and speed, no two footprints overlapping (shapely), the
    scene's pedestrian count kept, the same scene for the same seed, and with the option off the scene of before."""
    pytest.importorskip("shapely")
    ped = CLASSES.index("Pedestrian")
    nearest = {0.0: [], 1.0: []}
    paired = 0
    for seed in range(30):
        off = Simulator("driving_city", seed=seed, crossing_pedestrians=1.0).scenario
        for groups in (0.0, 1.0):
            sc = Simulator("driving_city", seed=seed, crossing_pedestrians=1.0, crossing_groups=groups).scenario
            assert (sc.object_labels == ped).sum() == (off.object_labels == ped).sum()
            b = sc.objects
            road = np.flatnonzero((sc.object_labels == ped) & (np.abs(b.center[:, 1]) < 10.5))
            _assert_clear(sc, np.isin(np.arange(len(b.center)), road), seed)
            if len(road) > 1:
                c = b.center[road, :2]
                d = np.hypot(*(c[:, None] - c[None]).transpose(2, 0, 1))
                np.fill_diagonal(d, np.inf)
                nearest[groups] += list(d.min(1))
                if groups:
                    x = b.center[road, 0]  # the crosswalk, widened by a group walking abreast along it
                    assert x.max() - x.min() <= 6.0 + 1e-9, x
                    for i, j in zip(road, road[d.argmin(1)]):
                        if np.hypot(*(b.center[i, :2] - b.center[j, :2])) < 1.0:  # companions
                            paired += 1
                            assert b.yaw[i] == b.yaw[j] and np.array_equal(b.velocity[i], b.velocity[j]), (seed, i, j)
    near, apart = np.median(nearest[1.0]), np.median(nearest[0.0])
    assert near < 1.2 < 1.5 < apart, (near, apart)
    assert paired >= 20, paired
    same = Simulator("driving_city", seed=4, crossing_pedestrians=1.0, crossing_groups=0.7).scenario.objects.center
    np.testing.assert_array_equal(
        same, Simulator("driving_city", seed=4, crossing_pedestrians=1.0, crossing_groups=0.7).scenario.objects.center)
    _assert_city_option_checked("crossing_groups")


def test_crossing_cyclists_ride_across_ahead_without_overlaps():
    """driving_city's crossing_cyclists: one to three of the scene's cyclists on the road 6-40 m ahead, heading
    across it (seen broadside), none overlapping another object in bird's-eye view (shapely, the rotated footprints;
    crossing pedestrians on too), the scene's cyclist count kept, and with the option off the scene of before."""
    pytest.importorskip("shapely")
    cyc = CLASSES.index("Cyclist")
    riding, across, scenes = 0, [], 0
    for seed in range(40):
        on = Simulator("driving_city", seed=seed, crossing_cyclists=1.0, crossing_pedestrians=1.0).scenario
        off = Simulator("driving_city", seed=seed, crossing_pedestrians=1.0).scenario
        assert (on.object_labels == cyc).sum() == (off.object_labels == cyc).sum()
        b = on.objects
        # the bicycle lanes are at |y| = 7.75 heading along x; a crossing cyclist heads across
        road = (on.object_labels == cyc) & (np.abs(np.cos(b.yaw)) < 0.95)
        riding += road.sum()
        scenes += road.any()
        if road.any():
            assert road.sum() <= 3
            assert (b.center[road, 0] >= 6.0 - 1e-9).all() and (b.center[road, 0] <= 40.0 + 1e-9).all()
            assert (np.abs(b.center[road, 1]) <= 10.0 + 1e-9).all()
            across.extend(np.abs(np.cos(b.yaw[road])))
            speed = np.hypot(b.velocity[road, 0], b.velocity[road, 1])
            assert (speed >= 3.0 - 1e-9).all() and (speed <= 6.0 + 1e-9).all()
        _assert_clear(on, road, seed)
    assert scenes >= 20 and riding >= 30, (scenes, riding)
    assert np.mean(np.asarray(across) < np.cos(np.pi / 2 - 0.75)) > 0.9, np.round(across, 2)
    _assert_city_option_checked("crossing_cyclists")


def test_parking_lots_hold_cars_at_every_heading_clear_of_everything_else():
    """driving_city's parking_lots: a lot beside the street beyond the walkway whose cars stand across the street,
    at a slant or along it side by side; no labelled box overlaps another (shapely, the rotated footprints), no
    return of anything but the car itself or the ground falls in a lot car's box (the clutter, the structures and
    the lot's trees on too: buildings stand behind the lot, crowns above the roofs), the lot cars are seen, the same
    frame for the same seed, and with the option off the scene of before."""
    pytest.importorskip("shapely")
    import torch

    from lidarops import points_in_boxes

    car = CLASSES.index("Car")
    headings, lots, seen, own, foreign = [], 0, 0, 0, 0
    busy = dict(street_clutter=1.0, low_clutter=2.0, roadside_structures=0.7)
    for seed in range(24):
        sim = Simulator("driving_city", seed=seed, parking_lots=1.0, **busy)
        sc = sim.scenario
        b = sc.objects
        lot = (sc.object_labels == car) & (np.abs(b.center[:, 1]) > 16.2)
        lots += lot.any()
        headings.extend(np.abs(np.cos(b.yaw[lot])))
        _assert_clear(sc, lot, seed)
        if seed < 8:
            f = sim.sweep(0)
            idx = points_in_boxes(torch.as_tensor(f.points[:, :3], dtype=torch.float64),
                                  torch.as_tensor(f.boxes, dtype=torch.float64)).numpy()
            in_lot = (idx >= 0) & (np.abs(f.boxes[np.maximum(idx, 0), 1]) > 16.2) & (f.surface != SURFACE_GROUND)
            own += (in_lot & (f.instance == idx)).sum()
            foreign += (in_lot & (f.instance != idx)).sum()
            seen += int((np.bincount(idx[in_lot], minlength=len(f.boxes)) >= 30).sum())
        if seed < 3:
            np.testing.assert_array_equal(
                Simulator("driving_city", seed=seed, parking_lots=0.0, **busy).sweep(0).points,
                Simulator("driving_city", seed=seed, **busy).sweep(0).points)
    assert 12 <= lots < 24, lots  # every scene has a lot; one in five is empty
    headings = np.asarray(headings)
    # across the street, at a slant and along it: each a good share
    assert (headings < 0.2).mean() > 0.15 and ((headings > 0.3) & (headings < 0.85)).mean() > 0.1 \
        and (headings > 0.98).mean() > 0.15, np.histogram(headings, bins=5, range=(0, 1))
    assert seen >= 10 and own > 1000, (seen, own)
    assert foreign <= 0.002 * own, (foreign, own)
    f1 = Simulator("driving_city", seed=5, parking_lots=1.0).sweep(0)
    np.testing.assert_array_equal(Simulator("driving_city", seed=5, parking_lots=1.0).sweep(0).points, f1.points)
    _assert_city_option_checked("parking_lots")


def test_open_ground_raises_flat_ground_before_the_buildings_clear_of_the_lanes():
    """driving_city's open_ground: low wide terraces (0.15-0.9 m above the street) before the buildings, from
    |y| = 16 m outwards (clear of every labelled lane), their flat tops returning; the same frame for the same seed;
    off, the scene of before."""
    on = Simulator("driving_city", seed=SEED, open_ground=1.0)
    tiles = [on.scenario.tile(k) for k in range(3)]
    low = [(c, h) for t in tiles for c, h in zip(t.boxes.center, t.boxes.half)
           if 2 * h[2] < 1.1 and 2 * h[1] >= 4.0 and 2 * h[0] >= 3.0]
    assert len(low) >= 3, len(low)
    for c, h in low:
        assert abs(c[1]) - h[1] >= 16.0 - 1e-6, (c, h)
    f = on.sweep(0)
    y, z = np.abs(f.points[:, 1]), f.points[:, 2]
    flat = (y > 16.0) & (y < 30.0) & (f.surface != SURFACE_GROUND) & (z < -1.73 + 1.0) & (z > -1.73 + 0.1)
    plain = Simulator("driving_city", seed=SEED).sweep(0)
    yp, zp = np.abs(plain.points[:, 1]), plain.points[:, 2]
    flat_plain = (yp > 16.0) & (yp < 30.0) & (plain.surface != SURFACE_GROUND) & (zp < -1.73 + 1.0) & (zp > -1.73 + 0.1)
    assert flat.sum() > flat_plain.sum() + 200, (flat.sum(), flat_plain.sum())
    np.testing.assert_array_equal(Simulator("driving_city", seed=SEED, open_ground=1.0).sweep(0).points, f.points)
    np.testing.assert_array_equal(Simulator("driving_city", seed=SEED, open_ground=0.0).sweep(0).points, plain.points)
    _assert_city_option_checked("open_ground")


@pytest.mark.parametrize("scenario, default", [("driving_city", 0.015), ("driving_highway", 0.02)])
def test_ground_slope_tilts_the_road_ahead_in_the_sensors_frame(scenario, default):
    """ground_slope (the scenarios' option, a profile's field): the scene's grade drawn up to it instead of the
    scenario's own (the same draw, scaled); the level sensor sees the ground ahead rise by the grade times the
    distance (its ray-cast returns), the objects' labels standing on that ground; the same frame for the same seed;
    the default value gives the scene of before; values outside [0, 0.1] are named."""
    steep = Simulator(scenario, seed=SEED, ground_slope=0.04, object_counts="dense")
    plain = Simulator(scenario, seed=SEED, object_counts="dense")
    np.testing.assert_allclose(steep.scenario.ground.slope, plain.scenario.ground.slope * 0.04 / default, rtol=1e-12)
    grade = float(steep.scenario.ground.slope[0])
    f = steep.sweep(0)
    x, y, z = f.points[:, 0], f.points[:, 1], f.points[:, 2]
    road = (f.surface == SURFACE_GROUND) & (np.abs(y) < 8)

    def ground_at(x0):
        near = road & (np.abs(x - x0) < 2.0)
        assert near.sum() >= 20, (x0, near.sum())
        return float(np.median(z[near]))

    rise = ground_at(25.0) - ground_at(5.0)
    assert abs(grade) > 0.005, grade  # this seed's scene slopes enough to tell
    # the cross slope and the waves move the ground by up to about 0.1 m
    assert abs(rise - 20.0 * grade) < 0.15, (rise, 20.0 * grade)
    ahead = (f.boxes[:, 0] > 5) & (f.boxes[:, 0] < 40) & (f.num_points_in_box >= 20)
    checked = 0
    for b in f.boxes[ahead]:  # each label's bottom on the ground returns around it (where the road shows)
        ring = (f.surface == SURFACE_GROUND) & (np.hypot(x - b[0], y - b[1]) < b[3] / 2 + 3.0)
        if ring.sum() >= 5:
            assert abs((b[2] - b[5] / 2) - np.median(z[ring])) < 0.25, b
            checked += 1
    assert checked >= 3, checked
    for slope, want in ((0.04, f), (default, plain.sweep(0))):
        again = Simulator(scenario, seed=SEED, ground_slope=slope, object_counts="dense").sweep(0)
        np.testing.assert_array_equal(again.points, want.points)
    profiled = Simulator(scenario, seed=SEED, realism="kitti:ground_slope=0.04")
    np.testing.assert_array_equal(profiled.scenario.ground.slope, steep.scenario.ground.slope)
    np.testing.assert_array_equal(Simulator(scenario, seed=SEED, realism="kitti").scenario.ground.slope,
                                  plain.scenario.ground.slope)
    for bad in (-0.01, 0.2, float("nan")):
        with pytest.raises(ValueError, match="ground_slope"):
            Simulator(scenario, seed=SEED, ground_slope=bad)
    with pytest.raises(ValueError, match="ground_slope"):
        Realism(ground_slope=0.5)
    # ground_slope_bias: the grade along the road shifted by it, across it kept; a profile's field passes it on
    for bias in (0.012, -0.02):
        shifted = Simulator(scenario, seed=SEED, ground_slope=0.04, ground_slope_bias=bias)
        np.testing.assert_allclose(shifted.scenario.ground.slope, steep.scenario.ground.slope + [bias, 0.0], atol=1e-15)
        profiled = Simulator(scenario, seed=SEED, realism=f"kitti:ground_slope=0.04,ground_slope_bias={bias}")
        np.testing.assert_array_equal(profiled.scenario.ground.slope, shifted.scenario.ground.slope)
    for bad in (0.06, -0.06, float("inf")):
        with pytest.raises(ValueError, match="ground_slope_bias"):
            Simulator(scenario, seed=SEED, ground_slope_bias=bad)


def test_label_tightness_draws_vehicle_labels_inside_their_bodies():
    """label_tightness: the same returns; vehicles' labels shorter and narrower by up to twice the tightness (each
    side), at the same centre, height and heading; other classes' labels unchanged."""
    base = dataclasses.replace(make_realism("kitti"), street_clutter=0.0)
    a = Simulator("driving_city", seed=SEED, realism=base, object_counts="dense").sweep(0)
    b = Simulator("driving_city", seed=SEED, realism=dataclasses.replace(base, label_tightness=0.1),
                  object_counts="dense").sweep(0)
    np.testing.assert_array_equal(a.points, b.points)
    vehicle = np.isin(a.labels, [CLASSES.index(c) for c in ("Car", "Truck", "Bus")])
    assert vehicle.sum() >= 5 and (~vehicle).sum() >= 5
    np.testing.assert_array_equal(a.boxes[~vehicle], b.boxes[~vehicle])
    np.testing.assert_array_equal(a.boxes[:, [0, 1, 2, 5, 6]], b.boxes[:, [0, 1, 2, 5, 6]])
    shrink = a.boxes[vehicle, 3:5] - b.boxes[vehicle, 3:5]
    assert (shrink >= 0).all() and (shrink <= 0.2 + 1e-5).all() and shrink.std() > 0.02
    assert (b.num_points_in_box[vehicle] <= a.num_points_in_box[vehicle]).all()
    assert b.num_points_in_box[vehicle].sum() < a.num_points_in_box[vehicle].sum()


def test_scene_sensor_randomises_beams_dropout_and_range_noise():
    """beam_choices, dropout_max, range_noise_max: per seed the HDL-64E halved (32 beams), as it is, or with a beam
    between each two (127), its dropout and noise within [its own, the maximum]; the returns follow the beams;
    kitti leaves the sensor as it is."""
    from lidarops.data.sensors import hdl64

    r = dataclasses.replace(NEUTRAL, beam_choices=(32, 64, 128), dropout_max=0.2, range_noise_max=0.06)
    seen, points = {}, {}
    for seed in range(12):
        sim = Simulator("driving_city", seed=seed, realism=r)
        s = sim.sensor
        beams = len(s.elevations_deg)
        seen[beams] = seen.get(beams, 0) + 1
        assert beams in (32, 64, 127) and max(s.elevations_deg) == 2.0 and -24.9 <= min(s.elevations_deg) < -24.3
        assert np.all(np.diff(s.elevations_deg) < 0)
        assert 0.02 <= s.dropout <= 0.2 and 0.02 <= s.range_noise_std <= 0.06
        if beams not in points and seed < 6:
            f = sim.sweep(0)
            points[beams] = f.points.shape[0] / (1 - s.dropout)
            assert f.ring.max() == beams - 1
    assert set(seen) == {32, 64, 127}
    ratios = {b: points[b] / points[64] for b in points if 64 in points}
    assert all(0.3 < ratios[b] / (b / 64) < 1.7 for b in ratios), ratios
    assert Simulator("driving_city", seed=1, realism="kitti").sensor == hdl64()
    kd = make_realism("kitti_dr")
    assert kd.beam_choices and kd.dropout_max > 0 and kd.range_noise_max > 0


def test_street_clutter_adds_furniture_and_keeps_clear_of_labelled_boxes():
    """City tiles with street clutter: more returns from structures and poles on the pavements, the same
    frame for the same seed, none of it inside labelled boxes (a few points where a parked bus overhangs the
    kerb); density 0 is the scene as it was; the realism profile turns it on."""
    import torch

    from lidarops import points_in_boxes

    plain = Simulator("driving_city", seed=SEED).sweep(0)
    np.testing.assert_array_equal(Simulator("driving_city", seed=SEED, street_clutter=0.0).sweep(0).points,
                                  plain.points)
    busy = Simulator("driving_city", seed=SEED, street_clutter=2.0).sweep(0)
    np.testing.assert_array_equal(Simulator("driving_city", seed=SEED, street_clutter=2.0).sweep(0).points,
                                  busy.points)

    def pavement(f):
        y = np.abs(f.points[:, 1])
        return int(((y > 10.5) & (y < 15.8) & (f.points[:, 2] > -1.5) & np.isin(f.surface, [2, 3, 4])).sum())

    assert pavement(busy) > pavement(plain) + 200
    idx = points_in_boxes(torch.as_tensor(busy.points[:, :3], dtype=torch.float64),
                          torch.as_tensor(busy.boxes, dtype=torch.float64)).numpy()
    foreign = (idx >= 0) & (busy.instance != idx) & (busy.surface != SURFACE_GROUND)
    assert foreign.sum() <= 0.002 * (idx >= 0).sum()
    kitti = Simulator("driving_city", seed=SEED, realism="kitti")
    assert kitti.scenario.tile(0).cylinders.center_xy.shape[0] > Simulator("driving_city", seed=SEED).scenario.tile(0) \
        .cylinders.center_xy.shape[0]
    with pytest.raises(ValueError, match="street_clutter"):
        Simulator("driving_city", seed=SEED, street_clutter=-1.0)
    with pytest.raises(TypeError, match="street_clutter"):  # a driving option, as an unexpected keyword is
        Simulator("drone_bridge", seed=SEED, street_clutter=1.0)


@pytest.mark.parametrize("scenario", ["driving_city", "driving_highway"])
def test_low_clutter_adds_low_wide_objects_clear_of_labelled_boxes(scenario):
    """The low clutter (planters, low walls, bushes, stones, berms): more non-ground returns below 1.2 m above the
    ground beside the road, the same frame for the same seed, none inside labelled boxes, the scene as it was at
    density 0, on in both profiles, and a bad density named."""
    import torch

    from lidarops import points_in_boxes

    plain = Simulator(scenario, seed=SEED, street_clutter=1.0).sweep(0)
    np.testing.assert_array_equal(Simulator(scenario, seed=SEED, street_clutter=1.0, low_clutter=0.0).sweep(0).points,
                                  plain.points)
    low = Simulator(scenario, seed=SEED, street_clutter=1.0, low_clutter=3.0).sweep(0)
    np.testing.assert_array_equal(Simulator(scenario, seed=SEED, street_clutter=1.0, low_clutter=3.0).sweep(0).points,
                                  low.points)
    ground_z = float(Simulator(scenario, seed=SEED).scenario.ground.z0)

    def low_beside_the_road(f):
        y, z = np.abs(f.points[:, 1]), f.points[:, 2]
        return int(((y > 10.7) & (y < 20.0) & (z < ground_z + 1.2) & (f.surface != SURFACE_GROUND)).sum())

    assert low_beside_the_road(low) > low_beside_the_road(plain) + 100, (low_beside_the_road(low),
                                                                        low_beside_the_road(plain))
    idx = points_in_boxes(torch.as_tensor(low.points[:, :3], dtype=torch.float64),
                          torch.as_tensor(low.boxes, dtype=torch.float64)).numpy()
    foreign = (idx >= 0) & (low.instance != idx) & (low.surface != SURFACE_GROUND)
    plain_idx = points_in_boxes(torch.as_tensor(plain.points[:, :3], dtype=torch.float64),
                                torch.as_tensor(plain.boxes, dtype=torch.float64)).numpy()
    plain_foreign = (plain_idx >= 0) & (plain.instance != plain_idx) & (plain.surface != SURFACE_GROUND)
    assert foreign.sum() <= plain_foreign.sum(), "the low clutter stands in no labelled box"
    assert make_realism("kitti").low_clutter > 0 and make_realism("kitti_dr").low_clutter > 0
    with pytest.raises(ValueError, match="low_clutter"):
        Simulator(scenario, seed=SEED, low_clutter=11.0)
    with pytest.raises(TypeError, match="low_clutter"):
        Simulator("drone_bridge", seed=SEED, low_clutter=1.0)


@pytest.mark.parametrize("scenario", ["driving_city", "driving_highway"])
def test_roadside_structures_stand_in_their_zones_and_cast_returns(scenario):
    """Guard rails, railings, walls with bins, bar fences and person-sized objects: every primitive within the
    roadside zones (so no labelled box holds one), their kinds all drawn, more non-ground returns in the zones, the
    same frame for the same seed, the scene as it was at density 0, on in both profiles, and a bad density named."""
    import torch

    from lidarops import points_in_boxes
    from lidarops.data.scenarios import _roadside_structures

    sim = Simulator(scenario, seed=SEED)
    build = _roadside_structures(scenario)
    heights, radii, rails, crowns = [], [], [], []
    for k in range(4):
        prims = build(sim.scenario.ground, SEED, 3.0, k, 40.0 * k, 40.0 * (k + 1))
        ext = primitive_extents(prims)
        assert len(ext) > 10
        inside = in_zones(ext[:, 0], ext[:, 1], STRUCTURE_ZONES[scenario])
        assert inside.all(), ext[~inside]
        heights += [h for h, yaw in zip(2 * prims.boxes.half[:, 2], prims.boxes.yaw) if yaw != 0]  # bins turn
        radii += list(prims.cylinders.radius)
        rails += [h for h in 2 * prims.boxes.half[:, 2] if abs(h - 0.31) < 1e-9]  # a guard rail's beam
        crowns += list(prims.ellipsoids.radii[:, 2])
    radii = np.asarray(radii)
    assert (radii < 0.02).sum() > 50, "bar fences: thin bars"
    assert (radii >= 0.03).any(), "and their posts"
    assert (radii >= 0.15).any() and len(crowns) > 2, "person-sized columns, shrubs and young trees"
    if scenario == "driving_city":
        assert rails, "guard rails: a 0.31 m beam"
        assert any(0.9 < h < 1.6 for h in heights), "wheelie bins"

    plain = Simulator(scenario, seed=SEED).sweep(0)
    np.testing.assert_array_equal(Simulator(scenario, seed=SEED, roadside_structures=0.0).sweep(0).points,
                                  plain.points)
    busy = Simulator(scenario, seed=SEED, roadside_structures=2.0)
    frame = busy.sweep(0)
    np.testing.assert_array_equal(Simulator(scenario, seed=SEED, roadside_structures=2.0).sweep(0).points, frame.points)

    def returns_in_zones(f):
        y = f.points[:, 1] + busy.scenario.ego.position0[1]  # the sensor's frame to the road's
        return int((in_zones(y, y, STRUCTURE_ZONES[scenario]) & (f.surface != SURFACE_GROUND)).sum())

    assert returns_in_zones(frame) > returns_in_zones(plain) + 500, (returns_in_zones(frame), returns_in_zones(plain))
    idx = points_in_boxes(torch.as_tensor(frame.points[:, :3], dtype=torch.float64),
                          torch.as_tensor(frame.boxes, dtype=torch.float64)).numpy()
    assert not ((idx >= 0) & (frame.instance != idx) & (frame.surface != SURFACE_GROUND)).any()
    assert make_realism("kitti").roadside_structures > 0 and make_realism("kitti_dr").roadside_structures > 0
    with pytest.raises(ValueError, match="roadside_structures"):
        Simulator(scenario, seed=SEED, roadside_structures=11.0)
    with pytest.raises(TypeError, match="roadside_structures"):
        Simulator("drone_lock", seed=SEED, roadside_structures=1.0)


def test_highway_verges_get_shrubs_and_posts_clear_of_the_lanes():
    """The highway's clutter (beyond the barrier lane and the rails): more vegetation and pole returns,
    none inside labelled boxes, the scene as it was at density 0, and on with the realism profile."""
    import torch

    from lidarops import points_in_boxes
    from lidarops.data.scene import SURFACE_POLE, SURFACE_VEGETATION

    plain = Simulator("driving_highway", seed=SEED).sweep(0)
    np.testing.assert_array_equal(Simulator("driving_highway", seed=SEED, street_clutter=0.0).sweep(0).points,
                                  plain.points)
    busy = Simulator("driving_highway", seed=SEED, street_clutter=2.0).sweep(0)
    verge = lambda f: int(np.isin(f.surface, [SURFACE_POLE, SURFACE_VEGETATION]).sum())  # noqa: E731
    assert verge(busy) > verge(plain) + 300, (verge(busy), verge(plain))
    idx = points_in_boxes(torch.as_tensor(busy.points[:, :3], dtype=torch.float64),
                          torch.as_tensor(busy.boxes, dtype=torch.float64)).numpy()
    assert ((idx >= 0) & (busy.instance != idx) & (busy.surface != SURFACE_GROUND)).sum() == 0
    kitti = Simulator("driving_highway", seed=SEED, realism="kitti")
    assert kitti.scenario.tile(0).ellipsoids.center.shape[0] > Simulator("driving_highway", seed=SEED).scenario \
        .tile(0).ellipsoids.center.shape[0]
