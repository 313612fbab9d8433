"""Fuzz: the simulator's realism profile (lidarops.data.realism). Any parameter in its documented range gives
intensities in [0, 1] on the quantum's grid, zero wherever a return is weak or reads zero, and a keep mask that
never drops a return below the greenhouse (nor below a drone's rotors); a parameter out of range (negative, above its
bound, NaN, infinite) raises a ValueError naming it; a Simulator refuses what is not a profile. The roadside
structures stay in their zones (clear of every labelled lane) for any seed, tile and density, and a bad density is
named; crossing groups never overlap. An object set's REALISM gives each scenario a profile or names the field, and
any checkpoint recipe gives the stream a profile or none.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from lidarops.data.realism import Realism, make_realism
from lidarops.data.shapes import _NATIVE_KIND, SHAPES, box_exit, shape_distance, trace

from tests.helpers.scenes import STRUCTURE_ZONES, in_zones, primitive_extents

from .fuzzing import assert_clear_error, assert_no_error, fuzz, outcome

UNIT = ("greenhouse_from", "greenhouse_keep", "greenhouse_zero", "dark_paint", "dark_zero", "light_zero",
        "tyre_band", "tyre_zero", "weak_from", "rotor_keep", "rotor_from")


@st.composite
def profiles(draw):
    kw = {name: draw(st.floats(0, 1), name) for name in UNIT}
    kw["beam_gain_std"] = draw(st.floats(0, 1), "beam_gain_std")
    kw["quantum"] = draw(st.sampled_from([0.0, 0.01, 0.05, 0.5]), "quantum")
    kw["surface_gain"] = tuple(draw(st.lists(st.floats(0, 100), min_size=6, max_size=6), "surface_gain"))
    return Realism(**kw)


@fuzz
@given(profile=profiles(), n=st.integers(0, 300), seed=st.integers(0, 2**16))
def test_any_profile_gives_intensities_on_its_grid(profile, n, seed):
    rng = np.random.default_rng(seed)
    raw = rng.random(n, dtype=np.float32) * rng.choice([0.1, 1.0, 3.0])
    surface = rng.integers(0, 6, n)
    beams = profile.beam_gains(rng, 64)
    assert ((beams >= 0.5) & (beams <= 1.5)).all()
    weak, zero = rng.random(n) < 0.2, rng.random(n) < 0.2
    out, err = outcome(profile.intensity, raw, surface, beams[rng.integers(0, 64, n)], weak, zero)
    assert_no_error(err, "intensity")
    assert out.shape == (n,) and out.dtype == np.float32 and np.isfinite(out).all()
    assert ((out >= 0) & (out <= 1)).all() and (out[weak | zero] == 0).all()
    if profile.quantum > 0:
        steps = out / profile.quantum
        assert np.allclose(steps, np.round(steps), atol=1e-3)
    height, dark = rng.random(n), rng.random(n) < 0.5
    keep, reads_zero = profile.vehicle_returns(rng, height, dark)
    assert keep.dtype == bool and reads_zero.dtype == bool and keep.shape == reads_zero.shape == (n,)
    assert keep[height < profile.greenhouse_from].all()
    rotors = profile.rotor_returns(rng, height)
    assert rotors.dtype == bool and rotors.shape == (n,) and rotors[height < profile.rotor_from].all()


UPPER = {"quantum": 0.5, "street_clutter": 10.0, "low_clutter": 10.0, "roadside_structures": 10.0,
         "ground_slope": 0.1, "ground_slope_bias": 0.05}  # others: 1


@fuzz
@given(name=st.sampled_from(UNIT + ("beam_gain_std", "quantum", "street_clutter", "low_clutter", "roadside_structures",
                                    "pedestrian_build", "hair_dropout", "crossing_pedestrians",
                                    "crossing_cyclists", "crossing_groups", "parking_lots", "open_ground",
                                    "ground_slope", "ground_slope_bias")),
       value=st.sampled_from([-0.5, "above", "far above", float("nan"), float("inf"), -float("inf")]))
def test_out_of_range_parameters_are_named(name, value):
    if isinstance(value, str):  # just above the parameter's range, or twice its end
        value = UPPER.get(name, 1.0) * (1.5 if value == "above" else 2.0)
    _, err = outcome(dataclasses.replace, Realism(), **{name: value})
    assert_clear_error(err, ValueError, [name], f"Realism({name}={value})")


@fuzz
@given(value=st.one_of(st.integers(), st.text(max_size=8), st.floats(allow_nan=True), st.none()))
def test_make_realism_takes_profiles_and_names_only(value):
    out, err = outcome(make_realism, value)
    if value is None:
        assert_no_error(err, "make_realism(None)")
        assert out is None
    elif value == "kitti":
        assert out == Realism()
    else:
        assert_clear_error(err, ValueError, ["realism"], f"make_realism({value!r})")


# ---- the transfer augmentations of lidarops.data.detection ----
@fuzz
@given(n=st.integers(0, 400), seed=st.integers(0, 2**16), p=st.floats(0, 1), scale=st.floats(0, 3),
       jitter=st.floats(0, 1), zero=st.floats(0, 1), bin_deg=st.floats(0.05, 10), parity=st.integers(0, 1))
def test_transfer_augmentations_keep_rows_and_ranges(n, seed, p, scale, jitter, zero, bin_deg, parity):
    from lidarops.data.detection import drop_alternate_beams, drop_points, perturb_intensity

    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.normal(0, 20, (n, 3)), rng.random((n, 1))], 1).astype(np.float32)
    rows = {tuple(r): i for i, r in enumerate(pts.tolist())}
    for out in (drop_points(pts, p, rng), drop_alternate_beams(pts, bin_deg, parity)):
        idx = [rows[tuple(r)] for r in out.tolist()]
        assert out.dtype == pts.dtype and out.shape[1] == 4 and idx == sorted(set(idx))
    if p == 0:
        assert drop_points(pts, p, rng).shape == pts.shape
    out = perturb_intensity(pts, scale, jitter, zero, rng)
    assert out.shape == pts.shape and out.dtype == pts.dtype
    np.testing.assert_array_equal(out[:, :3], pts[:, :3])
    assert ((out[:, 3] >= 0) & (out[:, 3] <= 1)).all()


def _face_rays(rng, n: int, scale: float, spread: float):
    """Boxes of random half sizes (times ``scale``), rays entering them from a random point of a random face, aimed
    at the centre give or take ``spread``, and the per-object numbers u: (entry, d, half, u)."""
    half = rng.uniform(0.05, 1.0, (n, 3)) * scale + 0.01
    face = rng.integers(0, 3, n)
    entry = rng.uniform(-1, 1, (n, 3)) * half
    entry[np.arange(n), face] = np.where(rng.random(n) < 0.5, -1, 1) * half[np.arange(n), face]
    d = -entry / np.maximum(np.linalg.norm(entry, axis=1, keepdims=True), 1e-12) + rng.normal(0, spread, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return entry, d, half, rng.random((n, 4))


@fuzz
@given(name=st.sampled_from(sorted(SHAPES)), n=st.integers(0, 60), seed=st.integers(0, 2**16),
       scale=st.floats(0.05, 8.0))
def test_any_box_and_rays_give_hits_on_the_shape_inside_the_box(name, n, seed, scale):
    """Boxes of any size (including ones far from the class's own), rays from anywhere on their faces: a hit
    lies in the box and on the shape, before the ray leaves the box; cos in [0, 1]."""
    rng = np.random.default_rng(seed)
    entry, d, half, u = _face_rays(rng, n, scale, 0.3)
    out, err = outcome(trace, name, entry, d, half, u)
    assert_no_error(err, f"trace({name!r}, {n} rays)")
    t, hit, cos = out
    assert t.shape == hit.shape == cos.shape == (n,)
    assert np.isfinite(t).all() and ((cos >= 0) & (cos <= 1)).all()
    assert (t[hit] <= box_exit(entry[hit], d[hit], half[hit]) + 1e-9).all()
    p = entry[hit] + d[hit] * t[hit, None]
    assert (np.abs(p) <= half[hit] + 1e-6).all()
    assert (np.abs(shape_distance(name, p, half[hit], u[hit])) < 2e-3).all()


@fuzz
@given(name=st.sampled_from(sorted(_NATIVE_KIND)), n=st.integers(0, 40), seed=st.integers(0, 2**16),
       scale=st.floats(0.05, 8.0), spread=st.floats(0.0, 2.0))
def test_compiled_tracer_equals_the_numpy_one(name, n, seed, scale, spread):
    """The compiled shape tracer (when built) follows the NumPy reference: the same hits, distances and cosines to
    rounding, for boxes of any size and rays from anywhere on their faces."""
    from lidarops.data.shapes import _native_op, _trace_numpy
    if _native_op() is None:
        return
    import torch
    rng = np.random.default_rng(seed)
    entry, d, half, u = _face_rays(rng, n, scale, spread + 1e-3)
    t, hit, cos = _trace_numpy(name, entry, d, half, u)
    nt, nhit, ncos = (a.numpy() for a in _native_op()(_NATIVE_KIND[name],
                                                       *(torch.from_numpy(a) for a in (entry, d, half, u))))
    same = nhit == hit  # a ray within rounding of the hit tolerance may go either way: rare
    assert n < 20 or same.mean() >= 0.95, (name, int((~same).sum()), n)
    both = hit & nhit
    assert np.allclose(nt[both], t[both], rtol=0, atol=1e-8) and np.allclose(ncos[both], cos[both], rtol=0, atol=1e-7)


@fuzz
@given(name=st.sampled_from(sorted(SHAPES) + ["Boat", ""]), bad=st.sampled_from(["nan", "inf", "shape", "half"]))
def test_bad_shape_inputs_are_named(name, bad):
    p, half, u = np.zeros((3, 3)), np.ones((3, 3)), np.zeros((3, 4))
    if bad == "nan":
        p[1, 2] = np.nan
    elif bad == "inf":
        u[0, 0] = np.inf
    elif bad == "shape":
        half = np.ones((3, 2))
    else:
        half[2, 1] = 0.0
    expect = "name" if name not in SHAPES else {"nan": "p", "inf": "u", "shape": "half", "half": "half"}[bad]
    _, err = outcome(shape_distance, name, p, half, u)
    assert_clear_error(err, ValueError, [expect], f"shape_distance({name!r}, {bad})")
    _, err = outcome(trace, name, p, np.full((3, 3), 3 ** -0.5), half, u)
    assert_clear_error(err, ValueError, ["entry" if expect == "p" else expect], f"trace({name!r}, {bad})")


# ---- the lasers' heights of a spinning sensor (lidarops.data.sensors) ----
@fuzz
@given(elevations=st.lists(st.floats(-90, 90), min_size=1, max_size=80), split=st.none() | st.integers(-2, 90),
       shift=st.floats(-2, 2))
def test_laser_heights_make_sensors_or_name_the_bad_value(elevations, split, shift):
    """hdl64_beam_offsets gives one height per beam of any table (within 0.02 and 0.33 m for elevations within
    90 degrees) or names lower_from; a spinning sensor takes heights within 1 m of the origin, one per beam, and
    names the first that is not."""
    from lidarops.data.sensors import SpinningLidar, hdl64_beam_offsets
    out, err = outcome(hdl64_beam_offsets, elevations, split)
    if split is not None and not 0 <= split <= len(elevations):
        return assert_clear_error(err, ValueError, ["lower_from"], f"hdl64_beam_offsets(lower_from={split})")
    assert_no_error(err, "hdl64_beam_offsets")
    assert len(out) == len(elevations) and all(0.02 < h < 0.33 for h in out)
    heights = tuple(h + shift for h in out)
    sensor, err = outcome(SpinningLidar, elevations_deg=tuple(elevations), beam_offsets_z=heights, columns_per_rev=8)
    bad = [i for i, h in enumerate(heights) if not -1 <= h <= 1]
    if bad:
        return assert_clear_error(err, ValueError, [f"beam_offsets_z[{bad[0]}]"], "SpinningLidar(beam_offsets_z=...)")
    assert_no_error(err, "SpinningLidar(beam_offsets_z=...)")
    origins = sensor.beam_origins()
    assert origins.shape == (len(elevations), 3) and np.array_equal(origins[:, 2], heights)
    assert not origins[:, :2].any()


@fuzz
@given(bad=st.sampled_from([float("nan"), float("inf"), 91.0, "x", None]), at=st.integers(0, 3))
def test_laser_heights_refuse_bad_elevations(bad, at):
    from lidarops.data.sensors import hdl64_beam_offsets
    table = [2.0, -1.0, -9.0, -20.0]
    table[at] = bad
    _, err = outcome(hdl64_beam_offsets, table)
    assert_clear_error(err, ValueError, [f"elevations_deg[{at}]"], f"hdl64_beam_offsets({table})")


@fuzz
@given(scenario=st.sampled_from(sorted(STRUCTURE_ZONES)), seed=st.integers(0, 2**31 - 1), k=st.integers(-50, 50),
       density=st.floats(0.05, 10.0))
def test_roadside_structures_stay_in_their_zones(scenario, seed, k, density):
    from lidarops.data.scenarios import _roadside_structures
    from lidarops.data.scene import Ground, _rng

    ground = Ground.random(_rng(seed, "fuzz", "ground"))
    ext = primitive_extents(_roadside_structures(scenario)(ground, seed, density, k, 40.0 * k, 40.0 * (k + 1)))
    inside = in_zones(ext[:, 0], ext[:, 1], STRUCTURE_ZONES[scenario])
    assert inside.all(), ext[~inside]


@fuzz
@given(scenario=st.sampled_from(sorted(STRUCTURE_ZONES)),
       value=st.sampled_from([-0.1, 10.5, float("nan"), float("inf"), "dense", None, True]))
def test_bad_roadside_structures_density_is_named(scenario, value):
    from lidarops.data.scenarios import build_scenario

    _, err = outcome(build_scenario, scenario, 0, roadside_structures=value)
    assert_clear_error(err, (ValueError, TypeError), ["roadside_structures"], f"roadside_structures={value!r}")


FIELD_NAMES = [f.name for f in dataclasses.fields(Realism)]


@fuzz
@given(preset=st.sampled_from(["kitti", "kitti_dr", "carla", ""]),
       items=st.lists(st.tuples(st.sampled_from(FIELD_NAMES + ["nope", ""]),
                                st.sampled_from(["0.5", "0", "1.5", "-1", "nan", "x", "true", "false", "32/64",
                                                 "Car/Truck", "", "()"])), min_size=1, max_size=3))
def test_profile_strings_give_a_profile_or_name_the_field(preset, items):
    """``preset:field=value,...``: a Realism with exactly those fields changed, or a ValueError naming the text (and
    the field, when it is one that does not exist or a value it cannot take)."""
    text = preset + ":" + ",".join(f"{k}={v}" for k, v in items)
    got, err = outcome(make_realism, text)
    if err is None:
        assert isinstance(got, Realism)
        base = make_realism(preset)
        for k, _ in items:
            assert k in FIELD_NAMES
        assert {f for f in FIELD_NAMES if getattr(got, f) != getattr(base, f)} <= {k for k, _ in items}
    else:
        assert_clear_error(err, ValueError, [text, *(k for k, _ in items if k)], f"make_realism({text!r})")


@fuzz
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8), groups=st.floats(0.0, 1.0))
def test_crossing_groups_never_overlap(seed, n, groups):
    """Any seed, crosser count and group probability: at most ``n`` pedestrians, every footprint inside the
    crosswalk's reserved 6 m and within 0.5 m of the road, no two overlapping in bird's-eye view."""
    import torch

    from lidarops import box_iou_bev
    from lidarops.data.scenarios import _Placed, _place_crossing_groups
    from lidarops.data.scene import Ground, _rng

    placed = _Placed()
    ground = Ground.random(_rng(seed, "fuzz", "ground"))
    done = _place_crossing_groups(_rng(seed, "fuzz", "crossing"), _rng(seed, "fuzz", "groups"), ground, n, placed,
                                  17.0, (-10.0, 10.0), groups)
    assert 1 <= done <= n and len(placed.center) == done
    c, half = np.asarray(placed.center), np.asarray(placed.half)
    # each footprint (within its circumscribed circle) inside the crosswalk's 6 m and 0.5 m of the road's edges
    reach = np.hypot(half[:, 0], half[:, 1])
    assert (np.abs(c[:, 0] - 17.0) + reach <= 3.0 + 1e-9).all() and (np.abs(c[:, 1]) + reach <= 10.5 + 1e-9).all()
    boxes = torch.as_tensor(np.concatenate([c, 2 * half, np.asarray(placed.yaw)[:, None]], 1), dtype=torch.float64)
    iou = box_iou_bev(boxes, boxes).numpy()
    np.fill_diagonal(iou, 0.0)
    assert (iou <= 1e-9).all(), iou


@fuzz
@given(option=st.sampled_from(["crossing_pedestrians", "crossing_groups", "crossing_cyclists", "parking_lots",
                                        "open_ground"]),
       value=st.sampled_from([-0.1, 1.5, float("nan"), float("inf"), "often", None, True]))
def test_bad_crossing_probability_is_named(option, value):
    from lidarops.data.scenarios import build_scenario

    _, err = outcome(build_scenario, "driving_city", 0, **{option: value})
    assert_clear_error(err, (ValueError, TypeError), [option], f"{option}={value!r}")


@fuzz
@given(scenario=st.sampled_from(["driving_city", "driving_highway"]),
       value=st.sampled_from([-0.01, 0.11, 1.0, float("nan"), float("inf"), "steep", True]))
def test_bad_ground_slope_is_named(scenario, value):
    from lidarops.data.scenarios import build_scenario

    _, err = outcome(build_scenario, scenario, 0, ground_slope=value)
    assert_clear_error(err, (ValueError, TypeError), ["ground_slope"], f"{scenario}: ground_slope={value!r}")


@fuzz
@given(scenario=st.sampled_from(["driving_city", "driving_highway"]),
       value=st.sampled_from([-0.06, 0.051, 1.0, float("nan"), -float("inf"), "uphill", True]))
def test_bad_ground_slope_bias_is_named(scenario, value):
    from lidarops.data.scenarios import build_scenario

    _, err = outcome(build_scenario, scenario, 0, ground_slope_bias=value)
    assert_clear_error(err, (ValueError, TypeError), ["ground_slope_bias"], f"{scenario}: ground_slope_bias={value!r}")


# ---- the object sets' REALISM (lidarops.data.object_sets.ObjectSetRecipe) ----
_PROFILE_NAMES = ("kitti", "kitti_dr", "avia", "kitti:rotor_keep=0.5", "avia:nope=1", "kitty", "", None)


@fuzz
@given(value=st.one_of(st.sampled_from(_PROFILE_NAMES), st.integers(), st.lists(st.text(max_size=4), max_size=2),
                       st.dictionaries(st.sampled_from(["driving_city", "drone_lock", "drone_bridge", "mars"]),
                                       st.one_of(st.sampled_from(_PROFILE_NAMES), st.integers()), max_size=3)))
def test_object_set_realism_gives_a_profile_per_scenario_or_names_the_field(value):
    from lidarops.data.object_sets import ObjectSetRecipe

    scenarios = {"driving_city": 1, "drone_lock": 2}
    out, err = outcome(ObjectSetRecipe, scenarios, realism=value)
    if err is not None:
        assert_clear_error(err, ValueError, ["realism"], f"ObjectSetRecipe(realism={value!r})")
        return
    for name in scenarios:  # what each scenario is made with: a profile make_realism takes, or ray-cast
        profile = out.profile(name)
        assert profile is None or make_realism(profile) is not None
        if isinstance(value, str):
            assert profile == value
        elif isinstance(value, dict):
            assert profile == value.get(name)
    assert out.key() == ObjectSetRecipe.from_dict(out.to_dict()).key()  # the key survives the cache's JSON


# ---- what a checkpoint's data recipe says (lidarops.models.weights.trained_realism, trained_scenarios) ----
_ENTRY_VALUES = st.one_of(st.none(), st.sampled_from(["avia", "kitti", "kitti:quantum=0.01"]), st.integers(),
                          st.lists(st.integers(), max_size=2))


@fuzz
@given(recipe=st.one_of(
    st.none(), st.integers(), st.text(max_size=4),
    st.fixed_dictionaries({}, optional={
        "realism": _ENTRY_VALUES,
        "scenarios": st.one_of(st.integers(), st.lists(st.one_of(st.integers(), st.fixed_dictionaries(
            {"scenario": st.sampled_from(["drone_bridge", "drone_lock", "driving_city", 3])},
            optional={"realism": _ENTRY_VALUES})), max_size=4))})),
    scenario=st.sampled_from(["drone_bridge", "drone_lock"]))
def test_trained_realism_reads_any_recipe_without_raising(recipe, scenario):
    """Whatever a checkpoint's data recipe holds, the profile is a string or None and the scenarios a list of
    names: a malformed recipe is never an error for the stream that asks (it falls back to ray-cast, driving_city)."""
    import tempfile
    from pathlib import Path

    from lidarops.checkpoint import save_checkpoint
    from lidarops.models import weights

    record = _aerial_record()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "c.pth"
        save_checkpoint({**record, "data_recipe": recipe}, path)
        out, err = outcome(weights.trained_realism, path, scenario)
        names, names_err = outcome(weights.trained_scenarios, path)
    assert_no_error(err, f"trained_realism({recipe!r}, {scenario!r})")
    assert_no_error(names_err, f"trained_scenarios({recipe!r})")
    assert isinstance(names, list) and all(isinstance(n, str) for n in names)
    assert out is None or isinstance(out, str)
    entries = [e for e in (recipe or {}).get("scenarios", []) if isinstance(e, dict)] \
        if isinstance(recipe, dict) and isinstance(recipe.get("scenarios"), list) else []
    first = next((e for e in entries if e.get("scenario") == scenario), None)
    if first is None:
        assert out is None
    else:
        want = first["realism"] if "realism" in first else recipe.get("realism")
        assert out == (want if isinstance(want, str) else None)


_RECORD: dict = {}


def _aerial_record() -> dict:
    """The shipped Aerial-PointPillars' record, read once (the fuzz examples change only its data recipe)."""
    if not _RECORD:
        from lidarops.checkpoint import read_checkpoint
        from lidarops.models import weights

        _RECORD.update(read_checkpoint(weights.path("aerial_pointpillars")))
    return _RECORD


# ---- data synth --realism: one profile, or one per --scenario (lidarops.cli.data) ----
@fuzz
@given(scenarios=st.lists(st.sampled_from(["driving_city", "drone_lock", "drone_bridge"]), min_size=1, max_size=4),
       given_=st.one_of(st.none(), st.lists(st.sampled_from(["avia", "kitti", "none", "kitti:quantum=0.01"]),
                                            min_size=1, max_size=5)))
def test_synth_realism_gives_one_profile_per_scenario_or_names_the_option(scenarios, given_):
    import argparse

    from lidarops.cli import data as data_cli

    args = argparse.Namespace(scenario=scenarios, realism=given_)
    out, err = outcome(data_cli._realism_per_scenario, args)
    if given_ is not None and len(given_) not in (1, len(scenarios)):
        assert_clear_error(err, ValueError, ["--realism", f"({len(scenarios)})"], f"--realism {given_}")
        return
    assert_no_error(err, f"--realism {given_} for {scenarios}")
    want = [None] * len(scenarios) if given_ is None else \
        [None if g == "none" else g for g in (given_ * len(scenarios) if len(given_) == 1 else given_)]
    assert out == want
    recorded = data_cli._recipe_realism(args)  # what recipe.json keeps: None, the one profile, or the list
    assert recorded == (None if all(w is None for w in want) else want[0] if len(set(want)) == 1 else want)
