"""What the OpenPCDet faces share: numpy in -> numpy out (``common_utils.check_numpy_to_torch``) and the
shape checks in OpenPCDet's argument names."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from lidarops.ops.validation import check_tensor, describe


def to_torch(x, name: str) -> tuple[Tensor, bool]:
    """``(tensor, was_numpy)``; OpenPCDet's CPU ops take numpy arrays as well as tensors."""
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x), True
    check_tensor(x, name)
    return x, False


def check_boxes(t: Tensor, name: str, batched: bool = False) -> None:
    shape = "(B, T, 7)" if batched else "(N, 7)"
    check_tensor(t, name)  # a list or None would otherwise fail on .dim() with an AttributeError
    if t.dim() != (3 if batched else 2) or t.shape[-1] != 7 or not t.is_floating_point():
        raise ValueError(f"{name} must be a floating {shape} tensor [x, y, z, dx, dy, dz, heading], got {describe(t)}")


def check_points(t: Tensor, name: str, batched: bool = False) -> None:
    shape = "(B, M, 3)" if batched else "(num_points, 3)"
    check_tensor(t, name)
    if t.dim() != (3 if batched else 2) or t.shape[-1] != 3 or not t.is_floating_point():
        raise ValueError(f"{name} must be a floating {shape} tensor, got {describe(t)}")

