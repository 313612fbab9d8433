"""lidarops.models.bev_backbone: the dense / sparse BaseBEVBackbone, and SSCATeR's PillarFeatureNet and
scatter_to_bev, against float64 references written here with plain torch ops (the sparse mode against dense
convolutions masked to the sparse network's sites)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from helpers.devices import DEVICES
from helpers.models import randomize_bn, small_backbone
from lidarops.models.bev_backbone import BaseBEVBackbone, backbone_layers
from lidarops.models.map_to_bev import scatter_to_bev
from lidarops.models.sscater_pointpillars import PillarFeatureNet
from lidarops.sparse import SparseConvTensor


def random_pillars(H, W, P, C, seed, dtype=torch.float64, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    keys = torch.randperm(H * W, generator=g)[:P]
    coords = torch.stack([torch.zeros_like(keys), keys // W, keys % W], 1).int()
    feats = torch.rand(P, C, generator=g, dtype=torch.float64).to(dtype)
    return SparseConvTensor(feats.to(device), coords.to(device), [H, W], 1)


def sparse_reference(bb: BaseBEVBackbone, x: SparseConvTensor) -> torch.Tensor:
    """The sparse network's semantics with dense ops: every layer's output masked to its active sites."""
    def bn_relu(y, norm):
        s = norm.weight / torch.sqrt(norm.running_var + norm.eps)
        return torch.relu(y * s[None, :, None, None] + (norm.bias - norm.running_mean * s)[None, :, None, None])

    dense = x.dense(channels_first=True)
    mask = (dense.abs().sum(1, keepdim=True) >= 0).to(dense.dtype) * 0
    c = x.indices.long()
    mask[c[:, 0], 0, c[:, 1], c[:, 2]] = 1.0
    h, outs = dense, []
    for block, deblock in zip(bb.blocks, bb.deblocks):
        mods = [m for m in block if not isinstance(m, (torch.nn.ZeroPad2d, torch.nn.ReLU))]
        for i in range(0, len(mods), 2):
            conv, norm = mods[i], mods[i + 1]
            s = conv.stride[0]
            h = F.conv2d(h, conv.weight, None, s, 1)
            if s > 1:
                mask = (F.conv2d(mask, torch.ones(1, 1, 3, 3, dtype=mask.dtype), None, s, 1) > 0).to(mask.dtype)
            h = bn_relu(h, norm) * mask
        up, norm = deblock[0], deblock[1]
        u = up.stride[0]
        outs.append(bn_relu(F.conv_transpose2d(h, up.weight, None, u), norm)
                    * F.interpolate(mask, scale_factor=u, mode="nearest"))
    return torch.cat(outs, 1)


@pytest.mark.parametrize("shape,P", [((40, 48), 150), ((24, 40), 60), ((16, 16), 1), ((16, 24), 0)])
def test_sparse_mode_matches_masked_dense_reference(shape, P):
    bb = small_backbone(seed=P)
    x = random_pillars(*shape, P, 8, seed=P)
    with torch.no_grad():
        got = bb(x, mode="sparse")
        ref = sparse_reference(bb, x)
    assert got.shape == ref.shape == (1, 18, *bb.output_shape(shape))
    assert (got - ref).abs().max() <= 1e-12 * ref.abs().max().clamp_min(1)


@pytest.mark.parametrize("device", DEVICES)
def test_sparse_mode_on_device_and_float32(device):
    bb = small_backbone(seed=3)
    x = random_pillars(40, 48, 200, 8, seed=3)
    with torch.no_grad():
        ref = sparse_reference(bb, x)
        got = bb.float().to(device)(SparseConvTensor(x.features.float().to(device), x.indices.to(device), [40, 48], 1),
                                    mode="sparse")
    assert (got.double().cpu() - ref).abs().max() <= 1e-5 * ref.abs().max()


def test_dense_mode_is_the_dense_network_and_one_state_dict_serves_both():
    bb = small_backbone(seed=1)
    sd = bb.state_dict()
    assert "blocks.0.1.weight" in sd and "deblocks.2.0.weight" in sd  # OpenPCDet's BaseBEVBackbone names
    x = random_pillars(32, 40, 300, 8, seed=1)
    dense_in = x.dense()
    with torch.no_grad():
        h, outs = dense_in, []
        for block, deblock in zip(bb.blocks, bb.deblocks):
            h = block(h)
            outs.append(deblock(h))
        ref = torch.cat(outs, 1)
        assert torch.equal(bb(dense_in, mode="dense"), ref)
        assert torch.equal(bb(x, mode="dense"), ref)  # a SparseConvTensor is densified
        other = BaseBEVBackbone(8, (1, 2, 2), (2, 2, 2), (8, 12, 16), (1, 2, 4), (6, 6, 6), mode="sparse")
        other.load_state_dict(sd)
        other = other.eval().double()
        assert torch.equal(other(x), bb(x, mode="sparse"))


def test_default_backbone_shapes_drone_grid():
    bb = BaseBEVBackbone().eval()
    assert bb.output_shape((512, 512)) == (256, 256) and bb.output_shape((496, 432)) == (248, 216)
    layers = backbone_layers(bb)
    assert [l.kind for l in layers].count("subm") == 13 and [l.kind for l in layers].count("down") == 3
    assert [l.stride for l in layers if l.kind == "up"] == [1, 2, 4]
    x = random_pillars(64, 64, 50, 64, seed=0, dtype=torch.float32)
    with torch.no_grad():
        assert bb(x, mode="sparse").shape == (1, 384, 32, 32)


def _pfn_reference(pfn, features, num_points):
    out = []
    s = pfn.norm.weight / torch.sqrt(pfn.norm.running_var + pfn.norm.eps)
    b = pfn.norm.bias - pfn.norm.running_mean * s
    for p in range(features.shape[0]):
        n = int(num_points[p])
        h = torch.relu(features[p, :n] @ pfn.linear.weight.t() * s + b)
        out.append(h.max(0).values if n else torch.zeros(pfn.out_channels, dtype=features.dtype))
    return torch.stack(out)


@pytest.mark.parametrize("device", DEVICES)
def test_pillar_feature_net_masks_padding(device):
    torch.manual_seed(0)
    pfn = PillarFeatureNet(9, 16)
    randomize_bn(pfn, 0, negative_bias=0.3)
    pfn = pfn.eval().double()
    P, N = 30, 12
    num = torch.randint(1, N + 1, (P,))
    feats = torch.randn(P, N, 9, dtype=torch.float64)
    ref = _pfn_reference(pfn, feats, num)
    garbage = feats.clone()
    garbage[torch.arange(N)[None, :] >= num[:, None]] = 1e3  # padding must not matter
    with torch.no_grad():
        got = pfn.to(device)(SimpleNamespace(features=garbage.to(device), num_points=num.to(device)))
    assert (got.cpu() - ref).abs().max() <= 1e-12 * ref.abs().max()
    # rows are independent in eval mode (what lets SSCATeR recompute only the changed pillars)
    with torch.no_grad():
        part = pfn(SimpleNamespace(features=garbage[5:9].to(device), num_points=num[5:9].to(device)))
    assert (part - got[5:9]).abs().max() <= 1e-13 * got.abs().max()  # equal up to the GEMM's blocking


def test_pillar_feature_net_training_statistics_come_from_real_points():
    torch.manual_seed(1)
    pfn = PillarFeatureNet(9, 8).double().train()
    num = torch.tensor([3, 1, 5])
    feats = torch.randn(3, 5, 9, dtype=torch.float64)
    pfn(SimpleNamespace(features=feats, num_points=num))
    real = torch.cat([feats[p, :int(num[p])] for p in range(3)]) @ pfn.linear.weight.t()
    expected = 0.99 * torch.zeros(8, dtype=torch.float64) + 0.01 * real.mean(0)
    assert torch.allclose(pfn.norm.running_mean, expected, atol=1e-12)


def test_scatter_to_bev_and_bad_inputs():
    x = random_pillars(10, 12, 7, 4, seed=2)
    assert torch.equal(scatter_to_bev(x.features, x.indices, (10, 12)), x.dense())
    pfn = PillarFeatureNet(9, 8)
    with pytest.raises(ValueError, match=r"pillars.features must be \(P, N, 9\)"):
        pfn(SimpleNamespace(features=torch.zeros(3, 4, 7), num_points=torch.ones(3)))
    with pytest.raises(ValueError, match="pillars.num_points must be"):
        pfn(SimpleNamespace(features=torch.zeros(3, 4, 9), num_points=torch.ones(2)))
    bb = BaseBEVBackbone(8, (1, 1, 1), (2, 2, 2), (4, 4, 4), (1, 2, 4), (2, 2, 2))
    with pytest.raises(ValueError, match="mode must be 'dense' or 'sparse'"):
        bb(x, mode="sprase")
    with pytest.raises(ValueError, match=r"x must be \(B, 8, H, W\)"):
        bb(torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match="takes a 2D SparseConvTensor"):
        bb(torch.zeros(1, 8, 8, 8), mode="sparse")
    with pytest.raises(ValueError, match="upsampled maps of different sizes"):
        bb(random_pillars(37, 29, 5, 8, seed=0), mode="sparse")
    with pytest.raises(ValueError, match="must have the same length"):
        BaseBEVBackbone(8, (1, 1), (2, 2, 2))
