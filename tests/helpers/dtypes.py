"""The float dtypes of the op tests, their ids, and the tolerances each is held to."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

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
