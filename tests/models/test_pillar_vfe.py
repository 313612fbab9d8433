"""Tests of lidarops.models.pillar_vfe (PointPillars' pillar feature net) beyond what test_pointpillars covers."""
from __future__ import annotations

import torch

from lidarops.models.pillar_vfe import PFNLayer


def _pillars(num_pillars: int, slots: int = 32, seed: int = 0) -> torch.Tensor:
    """(V, N, 10) PFN inputs as PillarVFE makes them: a few points per pillar, the empty slots zero."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(1, 9, (num_pillars,), generator=g)
    filled = torch.arange(slots)[None] < counts[:, None]
    x = torch.zeros(num_pillars, slots, 10)
    scale = torch.tensor([20, 20, 0.5, 0.3, 0.1, 0.1, 0.1, 0.08, 0.08, 1.0])
    shift = torch.tensor([35, 0, -1, 0.3, 0, 0, 0, 0, 0, 0.5])
    x[filled] = torch.randn(int(filled.sum()), 10, generator=g) * scale + shift
    return x


def test_training_batchnorm_statistics_are_exact_on_cpu():
    # A training step normalises over every slot of every pillar (~3e5 rows for two frames). PyTorch's CPU
    # kernel for a flat (rows, C) batch lost float32 precision there (1e-2 off); OpenPCDet's (V, C, N)
    # layout keeps it (~1e-6). Reference: the same layer in float64.
    x = _pillars(10_000)
    for last in (True, False):
        torch.manual_seed(0)
        layer = PFNLayer(10, 64, use_norm=True, last_layer=last).train()
        ref = PFNLayer(10, 64, use_norm=True, last_layer=last).double().train()
        ref.load_state_dict(layer.state_dict())
        with torch.no_grad():
            got, want = layer(x), ref(x.double())
            err = (got.double() - want).abs().max().item()
        assert err < 1e-4, f"last_layer={last}: max |float32 - float64| = {err:.3g}"
        # the running statistics moved as BatchNorm1d's over (V, C, N) moves them
        torch.testing.assert_close(layer.norm.running_mean.double(), ref.norm.running_mean, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(layer.norm.running_var.double(), ref.norm.running_var, atol=1e-6, rtol=1e-5)
    # eval mode and the empty batch are unchanged
    layer.eval()
    assert layer(x[:0]).shape == (0, 32, 64)
