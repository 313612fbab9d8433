"""The simulator's ``avia`` realism profile (a Livox Avia on a drone, lidarops.data.realism): drones shaped as
quadcopters whose spinning rotors return a fraction of their rays, reflectivity reported in 256 steps that does not
fall with range, the sensor's dropout and noise randomised per scene, and frames a function of the seed."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lidarops.data.frame import CLASSES
from lidarops.data.realism import make_realism
from lidarops.data.sensors import avia
from lidarops.data.synthetic import Simulator

DRONE = CLASSES.index("Drone")
KW = dict(object_counts={"Drone": 3})


def _drone_returns(frame):
    """Per return on a drone: its height fraction in its box (0 bottom, 1 top)."""
    on = (frame.instance >= 0) & (frame.labels[np.maximum(frame.instance, 0)] == DRONE)
    box = frame.boxes[frame.instance[on]]
    p = frame.points[on, :3] - box[:, :3]
    return p[:, 2] / box[:, 5] + 0.5


def _frames(realism, seeds=range(8), scenario="drone_lock"):
    return [Simulator(scenario, seed=s, realism=realism, **KW).sweep(0) for s in seeds]


def test_same_seed_same_frame_and_independent_of_request_order():
    a = Simulator("drone_lock", seed=3, realism="avia", **KW)
    b = Simulator("drone_lock", seed=3, realism="avia", **KW)
    f1 = b.sweep(1)
    f0 = b.sweep(0)
    np.testing.assert_array_equal(a.sweep(0).points, f0.points)
    np.testing.assert_array_equal(a.sweep(1).points, f1.points)
    other = Simulator("drone_lock", seed=4, realism="avia", **KW).sweep(0)
    assert other.points.shape != f0.points.shape or not np.array_equal(other.points, f0.points)


def test_shaped_drones_return_less_than_their_boxes():
    """A quadcopter fills a few per cent of its box: from the side or below, its body, arms, motors, skids and the
    rotors' discs return a fraction of what the box did (tests/data/test_shapes.py: the shape lies in its box)."""
    no_rotor_loss = dataclasses.replace(make_realism("avia"), rotor_keep=1.0)
    n_box = sum(_drone_returns(f).size for f in _frames(None))
    n_shape = sum(_drone_returns(f).size for f in _frames(no_rotor_loss))
    assert n_box > 150 and 0.1 * n_box < n_shape < 0.6 * n_box, (n_box, n_shape)


def test_rotor_returns_follow_their_probability():
    r = make_realism("avia")
    height = np.random.default_rng(0).random(200_000)
    keep = r.rotor_returns(np.random.default_rng(1), height)
    top = height >= r.rotor_from
    assert keep[~top].all() and abs(keep[top].mean() - r.rotor_keep) < 0.01


def test_spinning_rotors_lose_returns_from_the_top_of_drones_only():
    """rotor_keep < 1 drops returns on drones, mostly from their boxes' tops, from a random stream of its own: every
    other return lies where it did, and the returns kept are a subset of those with every rotor return kept (without
    mixed pixels, whose draws, as the intensity noise's, run over the returns kept)."""
    base = dataclasses.replace(make_realism("avia"), mixed_pixels=0.0)
    kept, full = dataclasses.replace(base, rotor_keep=0.25), dataclasses.replace(base, rotor_keep=1.0)
    lost_heights, kept_heights = [], []
    for fk, ff in zip(_frames(kept, range(12)), _frames(full, range(12))):
        on_k = (fk.instance >= 0) & (fk.labels[np.maximum(fk.instance, 0)] == DRONE)
        on_f = (ff.instance >= 0) & (ff.labels[np.maximum(ff.instance, 0)] == DRONE)
        np.testing.assert_array_equal(fk.points[~on_k, :3], ff.points[~on_f, :3])
        rows_k = {tuple(p) for p in fk.points[on_k, :3]}
        assert rows_k <= {tuple(p) for p in ff.points[on_f, :3]}
        h = _drone_returns(ff)
        lost = np.array([tuple(p) not in rows_k for p in ff.points[on_f, :3]], bool)
        lost_heights.append(h[lost])
        kept_heights.append(h[~lost])
    lost_h, kept_h = np.concatenate(lost_heights), np.concatenate(kept_heights)
    assert lost_h.size > 20, lost_h.size
    # measured against the label at the frame's time (the drones move): most lost returns near the top
    lost_mid, kept_mid = np.median(lost_h), np.median(kept_h)
    assert lost_mid > 0.75 and lost_mid > kept_mid + 0.15, (lost_mid, kept_mid)


def test_reflectivity_is_reported_in_256_steps_and_does_not_fall_with_range():
    """With reflectivity_output the same returns read brighter than under a raw intensity's exp(-range / 250 m)
    falloff, by a share that grows with range (1 - exp(-range / 250)); diffuse surfaces stay within 0-150 of 255."""
    r = make_realism("avia")
    raw = dataclasses.replace(r, reflectivity_output=False, quantum=0.0)
    flat = dataclasses.replace(r, quantum=0.0)
    for scenario in ("drone_bridge", "drone_lock"):
        f = Simulator(scenario, seed=2, realism="avia").sweep(0)
        steps = f.points[:, 3] * 255
        assert np.allclose(steps, np.round(steps), atol=1e-3) and f.points[:, 3].max() <= 150 / 255 + 1e-6
        a, b = Simulator(scenario, seed=2, realism=raw).sweep(0), Simulator(scenario, seed=2, realism=flat).sweep(0)
        np.testing.assert_array_equal(a.points[:, :3], b.points[:, :3])
        rng = np.linalg.norm(a.points[:, :3], axis=1)
        assert (b.points[:, 3] >= a.points[:, 3] - 1e-6).all()
        lit = b.points[:, 3] > 0.05  # well above the intensity noise (0.02)
        gain, rng = (b.points[lit, 3] - a.points[lit, 3]) / b.points[lit, 3], rng[lit]
        bins = 0
        for lo, hi in ((0, 20), (20, 40), (40, 60), (60, 90), (90, 150)):
            m = (rng >= lo) & (rng < hi)
            if m.sum() > 300:  # the share regained, in each band of range, as the falloff had it
                assert abs(np.median(gain[m]) - (1 - np.exp(-np.median(rng[m]) / 250))) < 0.02, (scenario, lo, hi)
                bins += 1
        assert bins >= 3


def test_scene_sensor_randomises_a_risley_sensors_dropout_and_noise():
    """dropout_max and range_noise_max draw per scene within [the sensor's own, the maximum]; the Avia keeps its
    scan pattern; reflectivity_output turns the range falloff off."""
    r = make_realism("avia")
    seen = []
    for seed in range(10):
        s = Simulator("drone_bridge", seed=seed, realism=r).sensor
        assert s.name == "avia" and s.channels == avia().channels and s.intensity_range_scale >= 1e12
        assert avia().dropout <= s.dropout <= r.dropout_max
        assert avia().range_noise_std <= s.range_noise_std <= r.range_noise_max
        seen.append((s.dropout, s.range_noise_std))
    assert len(set(seen)) == 10
    off = dataclasses.replace(r, dropout_max=0.0, range_noise_max=0.0, reflectivity_output=False)
    assert Simulator("drone_bridge", seed=1, realism=off).sensor == avia()


@pytest.mark.parametrize("field,value", [("rotor_keep", 1.5), ("rotor_keep", float("nan")), ("rotor_from", -0.1),
                                         ("reflectivity_output", "yes")])
def test_bad_parameters_are_named(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(make_realism("avia"), **{field: value})
