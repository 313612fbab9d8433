"""Pillar features onto the bird's-eye-view pseudo-image (``map_to_bev``): OpenPCDet's
``PointPillarScatter`` module, and :func:`scatter_to_bev`, the same scatter for pillars in the 2D
``(batch, y, x)`` layout of :mod:`lidarops.ops.pillars`.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

__all__ = ["PointPillarScatter", "scatter_to_bev"]


class PointPillarScatter(nn.Module):
    """Scatter of pillar features into the dense pseudo-image (OpenPCDet's ``PointPillarScatter``).

    Shape: ``forward(features (V, C), coords (V, 4) = (batch, z, y, x), batch_size)`` -> (B, C, ny, nx).
    Rows whose coords are negative (the padding of ``voxelize(..., padded=True)``) are left out without
    reading anything back to the host, so the scatter can run inside a CUDA graph.
    """

    #: Return the map in channels-last memory (a view of the scattered rows, no transposing copy), for
    #: networks whose convolutions run channels-last (``lidarops.models.cuda_graph.inference_copy`` sets it).
    channels_last = False

    def __init__(self, num_bev_features: int, grid_size):
        super().__init__()
        self.num_bev_features = int(num_bev_features)
        self.nx, self.ny, self.nz = (int(v) for v in grid_size)

    def forward(self, features: Tensor, coords: Tensor, batch_size: int) -> Tensor:
        c = coords.long()
        cells = batch_size * self.ny * self.nx
        flat = (c[:, 0] * self.ny + c[:, 2]) * self.nx + c[:, 3]
        # padding goes to one spare row (a full_like, not a Python scalar: nothing copied from the host)
        flat = torch.where((c >= 0).all(1), flat, torch.full_like(flat, cells))
        canvas = features.new_zeros(cells + 1, self.num_bev_features)
        canvas.index_copy_(0, flat, features)
        bev = canvas[:cells].view(batch_size, self.ny, self.nx, -1).permute(0, 3, 1, 2)
        return bev if self.channels_last else bev.contiguous()


def scatter_to_bev(pillar_features: Tensor, coords: Tensor, shape: Sequence[int], batch_size: int = 1) -> Tensor:
    """Dense pseudo-image (B, C, H, W) from pillar features (P, C) at int coords (P, 3) = (batch, y, x)."""
    H, W = int(shape[0]), int(shape[1])
    C = pillar_features.shape[1]
    out = pillar_features.new_zeros(batch_size, H, W, C)
    if coords.shape[0]:
        c = coords.long()
        out[c[:, 0], c[:, 1], c[:, 2]] = pillar_features
    return out.permute(0, 3, 1, 2).contiguous()
