"""Small models of the model, SSCATeR and stream tests: a reduced BEV backbone with BatchNorm statistics far
from the identity."""
from __future__ import annotations

import torch

from lidarops.models.bev_backbone import BaseBEVBackbone


def randomize_bn(module: torch.nn.Module, seed: int, negative_bias: float = 0.0) -> None:
    """Running statistics and affine parameters far from the identity; a negative bias makes many
    pre-activations negative (ReLU zeros)."""
    g = torch.Generator().manual_seed(seed)
    for m in module.modules():
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
            n = m.num_features
            m.running_mean.copy_(torch.rand(n, generator=g) - 0.5)
            m.running_var.copy_(torch.rand(n, generator=g) * 1.5 + 0.5)
            m.weight.data.copy_(torch.rand(n, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(n, generator=g) * 0.6 - 0.3 - negative_bias)


def small_backbone(cin=8, seed=0, negative_bias=0.0, dtype=torch.float64):
    """A three-block :class:`BaseBEVBackbone` (1/2/2 layers, 8/12/16 filters), randomized BatchNorm, eval mode."""
    torch.manual_seed(seed)
    bb = BaseBEVBackbone(cin, (1, 2, 2), (2, 2, 2), (8, 12, 16), (1, 2, 4), (6, 6, 6))
    randomize_bn(bb, seed, negative_bias)
    return bb.eval().to(dtype)


#: A small PointPillars config (one class, an 8 x 8 grid of 1 m pillars, 8 filters): model tests build it in
#: milliseconds.
TINY = dict(
    class_names=["Car"],
    point_cloud_range=[0.0, -4.0, -3.0, 8.0, 4.0, 1.0],
    voxel_size=[1.0, 1.0, 4.0],
    vfe_num_filters=[8],
    layer_nums=[1, 1, 1], layer_strides=[2, 2, 2], num_filters=[8, 8, 8],
    upsample_strides=[1, 2, 4], num_upsample_filters=[4, 4, 4],
    anchor_generator_config=[{"class_name": "Car", "anchor_sizes": [[2.0, 1.0, 1.5]], "anchor_rotations": [0, 1.57],
                              "anchor_bottom_heights": [-1.78], "align_center": True, "feature_map_stride": 2,
                              "matched_threshold": 0.6, "unmatched_threshold": 0.45}],
)


def greedy_reference(scores: torch.Tensor, mask=None) -> torch.Tensor:
    """The sequential greedy of distinct picks: the finite (row, point) pairs by decreasing score (ties: lower
    row, then lower point), skipping used rows and points; a row left over keeps its best point (the lowest
    among ties). ``mask (B, N)`` leaves points out."""
    B, m, N = scores.shape
    out = torch.full((B, m), -1, dtype=torch.int64)
    for b in range(B):
        sb = scores[b].detach().tolist()
        ok = [j for j in range(N) if mask is None or bool(mask[b, j])]
        pairs = sorted(((sb[i][j], i, j) for i in range(m) for j in ok if sb[i][j] > float("-inf")),
                       key=lambda t: -t[0])
        rows, cols = set(), set()
        for _, i, j in pairs:
            if i not in rows and j not in cols:
                out[b, i] = j
                rows.add(i)
                cols.add(j)
        for i in range(m):
            if out[b, i] < 0:
                out[b, i] = max(ok, key=lambda j: (sb[i][j], -j))
    return out

