"""The value_flags op behind the wrappers' value checks (lidarops/ops/validation.py): NaN/inf and
range flags against NumPy, every dtype, empty and non-contiguous tensors, CPU/CUDA parity, opcheck,
and the wrappers' errors that rely on it."""
import numpy as np
import pytest
import torch

import lidarops
from lidarops.ops.validation import check_values

from helpers.devices import DEVICES

FLOATS = [torch.float32, torch.float64, torch.float16, torch.bfloat16]
INTS = [torch.int64, torch.int32, torch.int16, torch.uint8]


def flags(finite, ranged=(), lo=(), hi=()):
    return torch.ops.lidarops.value_flags(list(finite), list(ranged), list(lo), list(hi)).tolist()


def nonfinite_reference(t):
    return int(not np.isfinite(t.double().cpu().numpy()).all())


def outside_reference(t, lo, hi):
    a = t.cpu().numpy().astype(np.int64)
    return int(bool(((a < lo) | (a > hi)).any()))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", FLOATS)
@pytest.mark.parametrize("n", [0, 1, 7, 1000, 300_001])
def test_nonfinite_flags_match_numpy(device, dtype, n):
    g = torch.Generator().manual_seed(n)
    cases = [torch.randn(n, generator=g) * 100]
    for bad in (float("nan"), float("inf"), float("-inf")):
        for where in ("first", "last", "random"):
            if n == 0:
                continue
            t = torch.randn(n, generator=g) * 100
            pos = {"first": 0, "last": n - 1, "random": int(torch.randint(n, (1,), generator=g))}[where]
            t[pos] = bad
            cases.append(t)
    tensors = [c.to(dtype=dtype, device=device) for c in cases]
    assert flags(tensors) == [nonfinite_reference(t) for t in tensors]


@pytest.mark.parametrize("device", DEVICES)
def test_large_finite_values_are_not_flagged(device):
    # LiDAR coordinates reach +-200 m; float16 holds up to 65504; float32/64 far more
    for dtype, big in [(torch.float16, 65504.0), (torch.bfloat16, 3.0e38), (torch.float32, 3.4e38),
                       (torch.float64, 1.7e308)]:
        t = torch.tensor([big, -big, 0.0, -0.0, 1e-30], dtype=torch.float64).to(dtype).to(device)
        assert flags([t]) == [nonfinite_reference(t)] == [0]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", INTS)
def test_range_flags_match_numpy(device, dtype):
    g = torch.Generator().manual_seed(3)
    hi_max = 200 if dtype == torch.uint8 else 10_000
    lo_min = 0 if dtype == torch.uint8 else -10_000
    base = torch.randint(lo_min, hi_max, (5000,), generator=g)
    tensors, los, his = [], [], []
    for lo, hi in [(lo_min, hi_max), (0, 0), (-1, 4999), (17, 18), (int(base.min()), int(base.max())),
                   (int(base.min()) + 1, int(base.max())), (int(base.min()), int(base.max()) - 1)]:
        tensors.append(base.to(dtype=dtype, device=device))
        los.append(lo)
        his.append(hi)
    tensors.append(torch.empty(0, dtype=dtype, device=device))
    los.append(5)
    his.append(5)
    expect = [outside_reference(t, lo, hi) for t, lo, hi in zip(tensors, los, his)]
    assert flags([], tensors, los, his) == expect
    assert 0 in expect and 1 in expect  # the cases cover both answers


@pytest.mark.parametrize("device", DEVICES)
def test_mixed_lists_and_noncontiguous(device):
    x = torch.randn(6, 5, 3, device=device)[:, ::2]  # non-contiguous
    y = torch.randn(4, 3, device=device).t()
    y[1, 2] = float("nan")
    idx = torch.arange(24, device=device).reshape(4, 6)[:, ::3]
    out = torch.ops.lidarops.value_flags([x, y], [idx, idx], [0, 0], [23, 17])
    assert out.dtype == torch.int32 and out.device.type == torch.device(device).type
    assert out.tolist() == [0, 1, 0, 1]


def test_bad_arguments_raise():
    x = torch.randn(3)
    with pytest.raises(ValueError, match="lo and hi must have 1 entries"):
        torch.ops.lidarops.value_flags([], [torch.arange(3)], [0, 1], [2])
    with pytest.raises(ValueError, match=r"finite\[0\] must be floating"):
        torch.ops.lidarops.value_flags([torch.arange(3)], [], [], [])
    with pytest.raises(ValueError, match=r"ranged\[0\] must be an integer tensor"):
        torch.ops.lidarops.value_flags([], [x], [0], [1])
    with pytest.raises(ValueError, match=r"lo\[0\] = 2 > hi\[0\] = 1"):
        torch.ops.lidarops.value_flags([], [torch.arange(3)], [2], [1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs two devices to mix")
def test_mixed_devices_raise():
    with pytest.raises(ValueError, match=r"finite\[1\] is on cpu"):
        torch.ops.lidarops.value_flags([torch.randn(3, device="cuda"), torch.randn(3)], [], [], [])


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(device):
    x = torch.randn(10, 3, device=device)
    i = torch.arange(10, device=device)
    torch.library.opcheck(torch.ops.lidarops.value_flags.default, ([x, x.double()], [i], [0], [9]),
                          test_utils=("test_schema", "test_faketensor", "test_aot_dispatch_dynamic"))


@pytest.mark.parametrize("device", DEVICES)
def test_check_values_raises_first_failure_and_evaluates_messages_lazily(device):
    x = torch.randn(4, 3, device=device)
    bad = x.clone()
    bad[2, 1] = float("nan")
    calls = []

    def message():
        calls.append(1)
        return "lengths bad"

    check_values(finite=[(x, "x bad")], ranged=[(torch.arange(4, device=device), 0, 3, message)])
    assert calls == []
    with pytest.raises(ValueError, match="^x bad$"):
        check_values(finite=[(x, "never"), (bad, "x bad")], ranged=[(torch.arange(4, device=device), 0, 2, message)])
    with pytest.raises(ValueError, match="lengths bad"):
        check_values(ranged=[(torch.arange(4, device=device), 0, 2, message)],
                     extra=[(torch.tensor(True, device=device), "extra bad")])
    assert calls == [1]
    with pytest.raises(ValueError, match="extra bad"):
        check_values(extra=[(torch.tensor(True, device=device), "extra bad")])


@pytest.mark.parametrize("device", DEVICES)
def test_wrappers_report_values_through_value_flags(device):
    p = torch.randn(2, 50, 3, device=device)
    q = p.clone()
    q[1, 7, 2] = float("inf")
    with pytest.raises(ValueError, match=r"points contains NaN or infinite coordinates \(shape \(2, 50, 3\)"):
        lidarops.knn(p, q, 4)
    with pytest.raises(ValueError, match=r"query_lengths must lie in \[0, 50\], got \[50, 51\]"):
        lidarops.knn(p, p, 4, query_lengths=torch.tensor([50, 51], device=device))
    with pytest.raises(ValueError, match=r"lengths must lie in \[0, 50\], got \[-1, 3\]"):
        lidarops.fps(p, 4, lengths=torch.tensor([-1, 3], device=device))
    with pytest.raises(ValueError, match=r"start_idx must lie in \[0, lengths\)"):
        lidarops.fps(p, 4, lengths=torch.tensor([10, 3], device=device), start_idx=torch.tensor([0, 3], device=device))
    with pytest.raises(ValueError, match=r"idx must lie in \[-1, 50\), got values in \[-2, 5\]"):
        lidarops.gather(p, torch.tensor([[0, 5], [-2, 1]], device=device))
    with pytest.raises(ValueError, match=r"idx must lie in \[-1, 50\), got values in \[-1, 50\]"):
        lidarops.gather(p, torch.tensor([[0, 50], [-1, 1]], device=device))
    # valid edge values pass
    lidarops.gather(p, torch.tensor([[-1, 49], [0, 0]], device=device))
    lidarops.fps(p, 4, lengths=torch.tensor([0, 50], device=device))
