"""The pillar feature net of PointPillars (``vfe``), OpenPCDet's ``PillarVFE``: for each point of a
pillar 10 features (x, y, z, intensity, offsets to the pillar's mean, offsets to the pillar centre), a
PointNet layer (Linear -> BatchNorm -> ReLU) and the max over the pillar's slots.

Like OpenPCDet, the VFE lets a pillar's empty slots (zero features) take part in BatchNorm's statistics
and in the max: that is what its checkpoints were trained with.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

__all__ = ["PillarVFE", "PFNLayer"]


class PFNLayer(nn.Module):
    """Linear -> BatchNorm1d -> ReLU on every slot of every pillar, then the max over the slots
    (concatenated back to each slot when this is not the last layer, as in OpenPCDet)."""

    def __init__(self, in_channels: int, out_channels: int, use_norm: bool = True, last_layer: bool = False):
        super().__init__()
        self.last_vfe = last_layer
        self.use_norm = use_norm
        if not last_layer:
            out_channels //= 2
        self.linear = nn.Linear(in_channels, out_channels, bias=not use_norm)
        if use_norm:
            self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, x: Tensor) -> Tensor:
        V, N, _ = x.shape
        if self.last_vfe and not self.training and self.use_norm and V * N:
            return self._folded_max(x)
        x = self.linear(x)
        if self.use_norm and V * N:  # statistics over every slot of every pillar, as BatchNorm1d over (V, C, N)
            if self.training and x.device.type == "cpu":
                # PyTorch's CPU kernel loses float32 precision on the statistics of a tall 2-D (rows, C)
                # batch: over the ~3e5 mostly empty slots of two frames the normalised features were off
                # by 5e-2 against float64, in OpenPCDet's (V, C, N) layout by 1e-6 (for about 1.7x this
                # layer's time). CUDA's kernels (Welford) keep the faster flat layout.
                x = self.norm(x.transpose(1, 2).contiguous()).transpose(1, 2)
            else:
                x = self.norm(x.reshape(V * N, -1)).view(V, N, -1)
        x = F.relu(x)
        x_max = x.amax(dim=1, keepdim=True) if N else x.new_zeros(V, 1, x.shape[2])
        if self.last_vfe:
            return x_max
        return torch.cat([x, x_max.expand(-1, N, -1)], dim=2)

    def _folded_max(self, x: Tensor) -> Tensor:
        """Inference of the last layer: BatchNorm's running statistics folded into the linear map, and
        the max over the slots before the ReLU (they commute): one GEMM and one reduction instead of
        four passes over every slot's features."""
        norm = self.norm
        scale = norm.weight * torch.rsqrt(norm.running_var + norm.eps)
        weight = self.linear.weight * scale[:, None]
        bias = norm.bias - norm.running_mean * scale
        return F.relu(F.linear(x, weight, bias).amax(dim=1, keepdim=True))


class PillarVFE(nn.Module):
    """OpenPCDet's ``PillarVFE``.

    Args:
        num_point_features (int): features per point (x, y, z, intensity: 4).
        voxel_size (Sequence[float]), point_cloud_range (Sequence[float]): the pillar grid.
        num_filters (Sequence[int]): PFN layer widths ([64]).
        with_distance (bool): add the point's distance to the sensor as a feature.
        use_absolute_xyz (bool): keep x, y, z among the features (else only the other point features).
        use_norm (bool): BatchNorm in the PFN layers.

    Shape:
        ``forward(voxels (V, N, C), num_points (V,), coords (V, 4) = (batch, z, y, x))`` ->
        ``(V, num_filters[-1])``.
    """

    def __init__(self, num_point_features: int, voxel_size, point_cloud_range, num_filters=(64,),
                 with_distance: bool = False, use_absolute_xyz: bool = True, use_norm: bool = True):
        super().__init__()
        self.use_absolute_xyz, self.with_distance = use_absolute_xyz, with_distance
        c_in = num_point_features + 6 if use_absolute_xyz else num_point_features + 3
        c_in += 1 if with_distance else 0
        self.num_point_features = num_point_features
        filters = [c_in] + [int(f) for f in num_filters]
        self.pfn_layers = nn.ModuleList(
            PFNLayer(filters[i], filters[i + 1], use_norm, last_layer=i == len(filters) - 2)
            for i in range(len(filters) - 1))
        self.out_channels = filters[-1]
        vs, pr = [float(v) for v in voxel_size], [float(v) for v in point_cloud_range]
        # buffers, not Python lists: no host-to-device copy per call (CUDA-graph capturable); not saved
        self.register_buffer("voxel_size", torch.tensor(vs), persistent=False)
        self.register_buffer("centre_offset", torch.tensor([vs[i] / 2 + pr[i] for i in range(3)]), persistent=False)

    def forward(self, voxels: Tensor, num_points: Tensor, coords: Tensor) -> Tensor:
        V, N, _ = voxels.shape
        xyz = voxels[:, :, :3]
        count = num_points.to(voxels.dtype).clamp_min(1).view(-1, 1, 1)
        f_cluster = xyz - xyz.sum(dim=1, keepdim=True) / count
        # pillar centres from (z, y, x) indices: columns 3, 2, 1 of coords are x, y, z (a flip, not a
        # list index: that would copy an index tensor from the host, which a CUDA graph capture refuses)
        centre = coords[:, 1:].flip(1).to(voxels.dtype) * self.voxel_size.to(voxels.dtype) \
            + self.centre_offset.to(voxels.dtype)
        f_center = xyz - centre[:, None, :]
        parts = [voxels if self.use_absolute_xyz else voxels[:, :, 3:], f_cluster, f_center]
        if self.with_distance:
            parts.append(torch.linalg.vector_norm(xyz, dim=2, keepdim=True))
        features = torch.cat(parts, dim=-1)
        slot = torch.arange(N, device=voxels.device)
        features = features * (slot[None, :] < num_points[:, None]).to(features.dtype)[..., None]
        for pfn in self.pfn_layers:
            features = pfn(features)
        return features.squeeze(1)
