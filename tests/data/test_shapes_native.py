"""The compiled shape tracer (torch.ops.lidarops.trace_shapes) against the NumPy reference
(lidarops.data.shapes._trace_numpy): random rays into every shape at random builds, rays that graze thin parts,
empty inputs, a whole simulated sweep, bad arguments and the op's schema.

The kernel follows the reference operation by operation in float64: hits agree, and distances and incidence
cosines to rounding (the reference's einsum sums may add in another order).
"""
from __future__ import annotations

import numpy as np
import pytest

from lidarops.data import shapes
from lidarops.data.shapes import SHAPES

torch = pytest.importorskip("torch")


def _op():
    try:
        from lidarops.extension import load

        load()
        return torch.ops.lidarops.trace_shapes
    except Exception:
        return None


pytestmark = pytest.mark.skipif(_op() is None, reason="lidarops._C with trace_shapes is not built")

SIZES = {"Car": (3.9, 1.6, 1.56), "Truck": (8.0, 2.5, 3.2), "Bus": (11.0, 2.6, 3.2), "Pedestrian": (0.8, 0.6, 1.75),
         "Cyclist": (1.76, 0.6, 1.73)}


def _rays(name: str, n: int, seed: int, spread: float = 0.3):
    """Rays entering random faces of boxes around the class's size, aimed roughly at the centre."""
    rng = np.random.default_rng(seed)
    half = np.tile(np.asarray(SIZES[name]) / 2, (n, 1)) * rng.uniform(0.7, 1.3, (n, 3))
    face = rng.integers(0, 3, n)
    entry = rng.uniform(-1, 1, (n, 3)) * half
    entry[np.arange(n), face] = np.where(rng.random(n) < 0.5, -1, 1) * half[np.arange(n), face]
    d = -entry / np.linalg.norm(entry, axis=1, keepdims=True) + rng.normal(0, spread, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return entry, d, half, rng.random((n, 4))


def _native(name, *arrays):
    t, hit, cos = _op()(shapes._NATIVE_KIND[name], *(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays))
    return t.numpy(), hit.numpy(), cos.numpy()


@pytest.mark.parametrize("name", sorted(shapes._NATIVE_KIND))
@pytest.mark.parametrize("spread", [0.3, 1.5])  # 1.5: many rays graze the shape or miss it
def test_native_tracer_equals_the_numpy_reference(name, spread):
    arrays = _rays(name, 6000, seed=len(name), spread=spread)
    t, hit, cos = shapes._trace_numpy(name, *arrays)
    nt, nhit, ncos = _native(name, *arrays)
    assert hit.any() and (~hit).any()
    assert (nhit == hit).mean() > 0.9995, (name, (nhit != hit).sum())
    both = hit & nhit
    np.testing.assert_allclose(nt[both], t[both], rtol=0, atol=1e-9)
    np.testing.assert_allclose(ncos[both], cos[both], rtol=0, atol=1e-9)
    assert (ncos[~nhit] == 0).all() and ((ncos >= 0) & (ncos <= 1)).all()


def test_trace_uses_the_native_tracer_and_the_plain_shape_by_hand():
    """trace() goes to the compiled kernel when it is built, and both give the hand-computed hits of a plain
    pedestrian (u = 0: legs of radius 0.035 H at y = +-0.09..0.1): between the legs a level ray at knee height
    misses, on a leg's axis it meets the leg's front."""
    assert shapes._native_op() is not None
    level, ped, H = np.array([[-1.0, 0.0, 0.0]]), np.array([[0.4, 0.3, 0.875]]), 1.75
    knee = -0.875 + 0.3
    y_leg = 0.09 + 0.01 * (0.52 * H - 0.3) / (0.52 * H - 0.06)
    entry = np.array([[0.4, 0.0, knee], [0.4, y_leg, knee]])
    for tracer in (shapes.trace, shapes._trace_numpy):
        t, hit, _ = tracer("Pedestrian", entry, np.tile(level, (2, 1)), np.tile(ped, (2, 1)), np.zeros((2, 4)))
        assert not hit[0] and hit[1] and abs(t[1] - (0.4 - 0.035 * H)) < 1e-3


def test_a_shape_without_a_compiled_twin_is_traced_in_numpy(monkeypatch):
    """The drone has no kernel: trace() gives the NumPy reference's answer and never calls the op."""
    assert set(SHAPES) - set(shapes._NATIVE_KIND) == {"Drone"}
    entry, d, half, u = _rays("Car", 500, seed=3)
    half = half * np.array([0.18, 0.44, 0.19])  # drone-sized boxes
    entry = entry * np.array([0.18, 0.44, 0.19])
    want = shapes._trace_numpy("Drone", entry, d, half, u)
    monkeypatch.setattr(shapes, "_native_op", lambda: pytest.fail("the op was called for a drone"))
    got = shapes.trace("Drone", entry, d, half, u)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)
    assert want[1].any() and (~want[1]).any()


def test_empty_input():
    out = _native("Car", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)))
    assert [a.shape for a in out] == [(0,), (0,), (0,)]
    assert [a.shape for a in shapes.trace("Car", np.zeros((0, 3)), np.zeros((0, 3)), np.ones((0, 3)),
                                          np.zeros((0, 4)))] == [(0,), (0,), (0,)]


def test_a_simulated_sweep_is_the_same_with_either_tracer(monkeypatch):
    """A kitti_dr sweep (cars, trucks, pedestrians and cyclists traced onto their shapes) with the compiled tracer
    and with the NumPy one: the same points (float32), labels and object ids."""
    from lidarops.data.synthetic import Simulator

    kw = dict(seed=21, object_counts={"Car": 10, "Pedestrian": 8, "Cyclist": 4, "Truck": 1}, realism="kitti_dr")
    native = Simulator("driving_city", **kw).sweep(0)
    monkeypatch.setattr(shapes, "_native_op", lambda: None)
    reference = Simulator("driving_city", **kw).sweep(0)
    assert native.points.shape == reference.points.shape and len(native.points) > 50_000
    np.testing.assert_allclose(native.points, reference.points, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(native.instance, reference.instance)
    np.testing.assert_array_equal(native.boxes, reference.boxes)


@pytest.mark.parametrize("kind, arg, bad, message", [
    (5, None, None, r"kind must be in \[0, 5\), got 5"),
    (-1, None, None, r"kind must be in \[0, 5\), got -1"),
    (0, "entry", lambda a: a.float(), r"entry must be a CPU float64 \(N, 3\) tensor, got \[4, 3\] Float"),
    (0, "d", lambda a: a[:, :2], r"d must be a CPU float64 \(N, 3\)"),
    (0, "half", lambda a: a[:3], r"half must be a CPU float64 \(N, 3\) tensor with N = 4"),
    (0, "u", lambda a: a[:, :3], r"u must be a CPU float64 \(N, 4\)"),
    (0, "entry", lambda a: a.reshape(-1), r"entry must be a CPU float64 \(N, 3\) tensor, got \[12\]"),
])
def test_op_errors_name_the_argument(kind, arg, bad, message):
    args = {k: torch.from_numpy(np.ascontiguousarray(a)) for k, a in zip(("entry", "d", "half", "u"), _rays("Car", 4, 0))}
    if arg is not None:
        args[arg] = bad(args[arg])
    with pytest.raises(ValueError, match=message):
        _op()(kind, args["entry"], args["d"], args["half"], args["u"])


def test_opcheck():
    args = tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in _rays("Cyclist", 16, 1))
    torch.library.opcheck(torch.ops.lidarops.trace_shapes.default, (4, *args), test_utils=("test_schema",
                                                                                             "test_faketensor"))
