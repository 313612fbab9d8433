"""The ops as PyTorch sees them: torch.library.opcheck on every registered op (schema, autograd
registration, fake kernel, AOT dispatch with dynamic shapes) and torch.compile(fullgraph=True).

Value checks are skipped while compiling, so every compiled result is compared with the eager one.
"""
from __future__ import annotations

import pytest
import torch

import lidarops
from helpers.clouds import lidar_cloud, noncontiguous, uniform_cloud
from helpers.compare import assert_equal_report
from lidarops import extension

extension.load()  # registers torch.ops.lidarops.* (importing lidarops alone is lazy)

OPCHECK_UTILS = ("test_schema", "test_autograd_registration", "test_faketensor", "test_aot_dispatch_dynamic")


def _lengths(values, device):
    return torch.tensor(values, dtype=torch.int64, device=device)


def fps_samples(device):
    p = lidar_cloud(2, 64, seed=1).to(device, torch.float32)
    yield "ragged", (p, _lengths([64, 17], device), _lengths([5, 16], device), 8, 0)
    yield "k>N-leaves", (p.double()[:, :6], _lengths([6, 3], device), _lengths([0, 2], device), 9, 2)
    yield "half-plain", (p.half(), _lengths([64, 64], device), _lengths([0, 0], device), 4, 1)
    yield "empty", (p[:, :0], _lengths([0, 0], device), _lengths([0, 0], device), 3, 0)


def _pair(device, dtype, M=16, N=40, grad=False, seed=0):
    q = uniform_cloud(2, M, seed=seed).to(device, dtype).requires_grad_(grad)
    p = uniform_cloud(2, N, seed=seed + 1).to(device, dtype).requires_grad_(grad)
    return q, p


def knn_samples(device):
    q, p = _pair(device, torch.float64, grad=True)
    yield "f64-grad-ragged", (q, p, _lengths([16, 5], device), _lengths([40, 3], device), 4, 0)
    yield "f64-grad-grid", (q, p, _lengths([16, 16], device), _lengths([40, 40], device), 6, 2)
    q, p = _pair(device, torch.float32, grad=True)
    yield "f32-grad-noncontig-brute", (noncontiguous(q.detach(), "transposed").requires_grad_(),
                                       p, _lengths([16, 16], device), _lengths([40, 0], device), 50, 1)
    q, p = _pair(device, torch.bfloat16)
    yield "bf16", (q, p, _lengths([16, 16], device), _lengths([40, 40], device), 3, 0)


def ball_query_samples(device):
    q, p = _pair(device, torch.float64, grad=True)
    yield "f64-grad-ragged", (q, p, _lengths([16, 5], device), _lengths([40, 3], device), 4, 0.9, 0)
    yield "f64-grad-grid", (q, p, _lengths([16, 16], device), _lengths([40, 40], device), 8, 0.7, 2)
    q, p = _pair(device, torch.float16, grad=True)
    yield "f16-grad-brute", (q, p, _lengths([16, 16], device), _lengths([40, 40], device), 5, 0.5, 1)


def gather_samples(device):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 9, 5, generator=g, dtype=torch.float64).to(device).requires_grad_()
    idx = torch.randint(-1, 9, (2, 7), generator=g).to(device)
    yield "f64-grad", (x, idx)
    yield "f32-grad-noncontig", (noncontiguous(x.detach().float(), "transposed").requires_grad_(), idx)
    yield "int64", (torch.randint(0, 100, (2, 9, 3), generator=g).to(device), idx)
    yield "empty-L", (x, idx[:, :0])


def gather_backward_samples(device):
    g = torch.Generator().manual_seed(1)
    idx = torch.randint(-1, 6, (2, 11), generator=g).to(device)
    yield "f64-grad", (torch.randn(2, 11, 4, generator=g, dtype=torch.float64).to(device).requires_grad_(), idx, 6)
    yield "f32", (torch.randn(2, 11, 4, generator=g).to(device), idx, 6)
    yield "bf16", (torch.randn(2, 11, 4, generator=g).to(device, torch.bfloat16), idx, 6)


SAMPLES = {
    "fps": fps_samples,
    "knn": knn_samples,
    "ball_query": ball_query_samples,
    "gather": gather_samples,
    "gather_backward": gather_backward_samples,
}


@pytest.mark.parametrize("op", list(SAMPLES))
def test_opcheck(device, op):
    """Schema, autograd registration, fake kernel and AOT dispatch (dynamic shapes) of every op."""
    for name, args in SAMPLES[op](device):
        # the AOT-dispatch check compiles; once per op (on its first sample) keeps the suite fast
        utils = OPCHECK_UTILS if name == next(iter(SAMPLES[op](device)))[0] else OPCHECK_UTILS[:3]
        result = torch.library.opcheck(getattr(torch.ops.lidarops, op).default, args, test_utils=utils,
                                       raise_exception=False)
        bad = {k: v for k, v in result.items() if v != "SUCCESS"}
        assert not bad, f"opcheck {op} sample {name!r}: {bad}"


def _pipeline(points, query, feats):
    """A PointNet++ set-abstraction-like step through every op."""
    centres_idx = lidarops.fps(points, 32)
    centres = lidarops.gather(points, centres_idx)
    d_knn, i_knn = lidarops.knn(centres, points, 8)
    d_ball, i_ball = lidarops.ball_query(query, points, 0.5, 6, method="grid")
    grouped = lidarops.gather(feats, i_knn)  # (B, 32, 8, C)
    return centres_idx, centres, d_knn, i_knn, d_ball, i_ball, grouped


def test_compile_fullgraph_matches_eager(device):
    """The default backend (Inductor), no graph break allowed."""
    points = lidar_cloud(2, 500, seed=3).to(device, torch.float32) * 0.02
    query = points[:, :50] + 0.01
    feats = torch.randn(2, 500, 16, device=device)
    torch._dynamo.reset()
    compiled = torch.compile(_pipeline, fullgraph=True)
    for i, (a, b) in enumerate(zip(compiled(points, query, feats), _pipeline(points, query, feats))):
        assert_equal_report(a, b, f"compiled output {i}")


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_compile_dynamic_shapes_and_backward(device):
    """dynamic=True: one graph serves several sizes; gradients through the compiled ops equal eager.
    The aot_eager backend traces the fake kernels and the autograd formulas exactly as Inductor
    does, without its (slow, on 2 CPU cores) code generation."""

    def loss_fn(query, points, feats):
        dist, idx = lidarops.knn(query, points, 4)
        bd, bi = lidarops.ball_query(query, points, 0.6, 4)
        g = lidarops.gather(feats, idx)
        valid = bi >= 0
        return (torch.where(valid, bd, torch.zeros_like(bd)).sum() + dist.sum() + (g * g).sum(), idx)

    torch._dynamo.reset()
    compiled = torch.compile(loss_fn, fullgraph=True, dynamic=True, backend="aot_eager")
    for M, N in ((20, 100), (33, 170), (7, 64)):
        q0 = uniform_cloud(2, M, seed=M).to(device, torch.float64)
        p0 = uniform_cloud(2, N, seed=N).to(device, torch.float64)
        f0 = torch.randn(2, N, 3, dtype=torch.float64, device=device)
        grads = []
        for fn in (loss_fn, compiled):
            q, p, f = (t.clone().requires_grad_() for t in (q0, p0, f0))
            loss, idx = fn(q, p, f)
            loss.backward()
            grads.append((loss.detach(), idx, q.grad, p.grad, f.grad))
        for i, (a, b) in enumerate(zip(*grads)):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=lambda m: f"M={M} N={N} item {i}: {m}")


def test_compile_skips_value_checks_but_shape_checks_remain(device):
    """While compiling, checks that read tensor values are skipped (no host sync); shape errors are
    still raised at trace time."""
    p = uniform_cloud(2, 30, seed=0).to(device, torch.float32)

    @torch.compile(fullgraph=True)
    def bad_rank(x):
        return lidarops.knn(x[0], x, 3)

    torch._dynamo.reset()
    with pytest.raises(Exception, match="query must be"):
        bad_rank(p)
