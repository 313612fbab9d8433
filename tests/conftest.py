"""Shared test fixtures: devices, dtypes with their tolerances, and synthetic point clouds.

The cloud generators are plain functions (also used by ``benchmarks/``); every one is seeded,
returns a float64 CPU tensor ``(B, N, 3)`` and is cast by the caller with ``.to(device, dtype)``,
so a reference computed on the cast values sees exactly what the kernel sees.

Devices: ``cpu`` always; ``cuda`` when torch sees a GPU and lidarops was built with its CUDA
kernels. When torch sees a GPU but lidarops has no CUDA kernels the cuda cases are skipped with a
reason, unless ``LIDAROPS_TEST_REQUIRE_CUDA=1`` (then they run and fail loudly).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import pytest
import torch


def _lidarops_cuda_kernels() -> tuple[bool, str]:
    try:
        from lidarops import extension

        return extension.cuda_available(), extension.build_info().get("cuda_reason", "")
    except Exception as e:  # a broken build fails the op tests loudly; here we only pick devices
        return False, f"lidarops failed to load: {e}"


CUDA_VISIBLE = torch.cuda.is_available()
LIDAROPS_CUDA, _CUDA_REASON = _lidarops_cuda_kernels() if CUDA_VISIBLE else (False, "no GPU visible")
REQUIRE_CUDA = os.environ.get("LIDAROPS_TEST_REQUIRE_CUDA", "0") == "1"


def _device_params() -> list:
    params = [pytest.param("cpu", id="cpu")]
    if CUDA_VISIBLE:
        if LIDAROPS_CUDA or REQUIRE_CUDA:
            params.append(pytest.param("cuda", id="cuda"))
        else:
            params.append(pytest.param("cuda", id="cuda", marks=pytest.mark.skip(
                reason=f"torch sees a GPU but lidarops has no CUDA kernels ({_CUDA_REASON})")))
    return params


DEVICES = _device_params()
requires_cuda = pytest.mark.skipif(not (LIDAROPS_CUDA or (CUDA_VISIBLE and REQUIRE_CUDA)),
                                   reason="needs a GPU and lidarops built with CUDA kernels")


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


# ---- dtypes ----

FLOAT_DTYPES = [torch.float32, torch.float64, torch.float16, torch.bfloat16]
DTYPE_IDS = {torch.float32: "f32", torch.float64: "f64", torch.float16: "f16", torch.bfloat16: "bf16"}


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype the kernels compute (and return distances) in: float64 stays, the rest is float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def np_dtype(dtype: torch.dtype):
    return np.float64 if dtype == torch.float64 else np.float32


@dataclass(frozen=True)
class Tol:
    """Tolerances for one input dtype.

    dist2_rtol: relative error of a squared distance computed in the compute dtype against the exact
        (float64) value for the same input coordinates. Six rounded operations on non-negative terms
        (3 subtractions, 3 products, 2 sums, each relative error <= u) give <= ~5u; we allow 8u.
    grad_rtol, grad_atol: gradients of dist2 against a float64 autograd reference.
    """

    dist2_rtol: float
    grad_rtol: float
    grad_atol: float


_U32, _U64 = 2.0**-24, 2.0**-53
TOL = {
    torch.float64: Tol(8 * _U64, 1e-12, 1e-12),
    torch.float32: Tol(8 * _U32, 1e-5, 1e-5),
    # half inputs are computed in float32; their gradients are rounded back to the half dtype
    torch.float16: Tol(8 * _U32, 2e-3, 2e-3),
    torch.bfloat16: Tol(8 * _U32, 1.6e-2, 1.6e-2),
}


@pytest.fixture(params=FLOAT_DTYPES, ids=lambda d: DTYPE_IDS[d])
def dtype(request) -> torch.dtype:
    return request.param


# ---- synthetic clouds (float64, CPU, seeded) ----

def uniform_cloud(B: int, N: int, seed: int = 0, scale: float = 1.0) -> torch.Tensor:
    """Points uniform in the cube [-scale, scale]^3."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.uniform(-scale, scale, size=(B, N, 3)))


def lidar_cloud(B: int, N: int, seed: int = 0, extent: float = 200.0) -> torch.Tensor:
    """A LiDAR-like scan: ~55% ground returns on rings (a 40-beam sensor 1.73 m above a plane, 2048
    azimuth steps, ring radii 3 m .. ``extent``), ~30% in a dozen dense object clusters (cars,
    pedestrians, poles within 60 m), ~15% sparse far points (buildings, vegetation) anywhere in
    [-extent, extent]^2 x [-3, 20]. Point order is shuffled. Coordinates reach +-extent metres."""
    rng = np.random.default_rng(seed)
    out = np.empty((B, N, 3))
    for b in range(B):
        n_ground = int(N * 0.55)
        n_obj = int(N * 0.30)
        n_far = N - n_ground - n_obj
        beam = rng.integers(0, 40, n_ground)
        ring = 3.0 * (extent / 3.0) ** (beam / 39.0)
        r = ring * (1.0 + rng.normal(0.0, 0.002, n_ground))
        az = (rng.integers(0, 2048, n_ground) + rng.normal(0.0, 0.02, n_ground)) * (2 * math.pi / 2048)
        ground = np.stack([r * np.cos(az), r * np.sin(az), -1.73 + rng.normal(0.0, 0.02, n_ground)], 1)
        n_clusters = 12
        c_r = rng.uniform(4.0, 60.0, n_clusters)
        c_az = rng.uniform(0.0, 2 * math.pi, n_clusters)
        centres = np.stack([c_r * np.cos(c_az), c_r * np.sin(c_az), -1.73 + rng.uniform(0.3, 1.5, n_clusters)], 1)
        sigmas = rng.uniform(0.1, 1.2, size=(n_clusters, 3))
        which = rng.integers(0, n_clusters, n_obj)
        objects = centres[which] + rng.normal(size=(n_obj, 3)) * sigmas[which]
        far = np.stack([rng.uniform(-extent, extent, n_far), rng.uniform(-extent, extent, n_far),
                        rng.uniform(-3.0, 20.0, n_far)], 1)
        pts = np.concatenate([ground, objects, far])
        out[b] = pts[rng.permutation(N)]
    return torch.from_numpy(out)


def lattice_cloud(B: int, N: int, seed: int = 0, side: int = 5) -> torch.Tensor:
    """Points on the integer lattice {0..side-1}^3: exact distance ties everywhere, many duplicates."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.integers(0, side, size=(B, N, 3)).astype(np.float64))


def duplicate_cloud(B: int, N: int, seed: int = 0, unique: int | None = None, scale: float = 1.0) -> torch.Tensor:
    """N points drawn with repetition from ``unique`` (default N // 4) distinct uniform points."""
    rng = np.random.default_rng(seed)
    u = max(1, N // 4 if unique is None else unique)
    base = rng.uniform(-scale, scale, size=(B, u, 3))
    pick = rng.integers(0, u, size=(B, N))
    return torch.from_numpy(np.take_along_axis(base, pick[..., None], axis=1))


def identical_cloud(B: int, N: int, value: tuple[float, float, float] = (1.5, -2.0, 0.25)) -> torch.Tensor:
    """N copies of one point: every distance ties."""
    return torch.tensor(value, dtype=torch.float64).expand(B, N, 3).clone()


CLOUD_KINDS = ("uniform", "lidar", "lattice", "duplicates")


def make_cloud(kind: str, B: int, N: int, seed: int = 0) -> torch.Tensor:
    if kind == "uniform":
        return uniform_cloud(B, N, seed)
    if kind == "lidar":
        return lidar_cloud(B, N, seed)
    if kind == "lattice":
        return lattice_cloud(B, N, seed)
    if kind == "duplicates":
        return duplicate_cloud(B, N, seed)
    if kind == "identical":
        return identical_cloud(B, N)
    raise ValueError(f"unknown cloud kind {kind!r}")


def ragged_lengths(B: int, N: int, seed: int = 0) -> torch.Tensor:
    """(B,) int64 lengths in [0, N]: the first row is full, the second (if any) empty, the rest random."""
    rng = np.random.default_rng(seed + 1000)
    lengths = rng.integers(0, N + 1, size=B)
    if B > 0:
        lengths[0] = N
    if B > 1:
        lengths[1] = 0
    return torch.from_numpy(lengths.astype(np.int64))


def noncontiguous(x: torch.Tensor, how: str) -> torch.Tensor:
    """The same values as ``x`` (B, N, C) in a non-contiguous layout."""
    if how == "transposed":  # stored (B, C, N)
        y = x.transpose(1, 2).contiguous().transpose(1, 2)
    elif how == "strided":  # every other row of a twice-as-long buffer
        buf = torch.zeros((x.shape[0], 2 * x.shape[1], x.shape[2]), dtype=x.dtype, device=x.device)
        buf[:, ::2] = x
        y = buf[:, ::2]
    elif how == "channels":  # a (B, N, 3) slice of a wider (B, N, 5) buffer
        buf = torch.zeros((*x.shape[:2], x.shape[2] + 2), dtype=x.dtype, device=x.device)
        buf[..., 1:-1] = x
        y = buf[..., 1:-1]
    else:
        raise ValueError(how)
    assert torch.equal(y, x) and (x.numel() == 0 or not y.is_contiguous())
    return y


# ---- comparison helpers that say where things differ ----

def assert_equal_report(actual: torch.Tensor, expected: torch.Tensor, what: str) -> None:
    """Exact equality (NaN never expected; +inf == +inf), with the first mismatches in the message."""
    actual, expected = actual.detach().cpu(), expected.detach().cpu()
    assert actual.shape == expected.shape, f"{what}: shape {tuple(actual.shape)} != {tuple(expected.shape)}"
    assert actual.dtype == expected.dtype, f"{what}: dtype {actual.dtype} != {expected.dtype}"
    bad = actual != expected
    if bad.any():
        where = bad.nonzero()[:5].tolist()
        detail = "; ".join(f"at {tuple(w)}: got {actual[tuple(w)].item()} expected {expected[tuple(w)].item()}"
                           for w in where)
        raise AssertionError(f"{what}: {int(bad.sum())} of {bad.numel()} entries differ; {detail}")


def assert_close_report(actual: torch.Tensor, expected: torch.Tensor, rtol: float, atol: float, what: str) -> None:
    """|actual - expected| <= atol + rtol |expected| in float64, infinities equal; reports the max difference."""
    a, e = actual.detach().cpu().double(), expected.detach().cpu().double()
    assert a.shape == e.shape, f"{what}: shape {tuple(a.shape)} != {tuple(e.shape)}"
    inf_a, inf_e = torch.isinf(a), torch.isinf(e)
    assert torch.equal(inf_a, inf_e) and torch.equal(a[inf_a], e[inf_e]), f"{what}: infinities differ"
    fin = ~inf_e
    if not fin.any():
        return
    diff = torch.where(fin, (a - e).abs(), torch.zeros_like(a))
    excess = diff - (atol + rtol * torch.where(fin, e.abs(), torch.zeros_like(e)))
    if (excess > 0).any() or torch.isnan(a).any():
        w = tuple(torch.nonzero(excess == excess.max())[0].tolist())
        raise AssertionError(f"{what}: max difference {diff.max().item():.3e} (rtol {rtol:.1e}, atol {atol:.1e}); "
                             f"worst at {w}: got {a[w].item()!r} expected {e[w].item()!r}")


@pytest.fixture
def one_thread():
    """Run the test with one intra-op thread (restored after): for tests of tiny tensors, where
    OpenMP wake-ups on a shared machine cost more than the work."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
