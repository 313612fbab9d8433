"""lidarops.compat.spconv: OpenPCDet-style backbones written against ``spconv.pytorch`` run unchanged.

The backbones below follow the structure of OpenPCDet's ``VoxelBackBone8x`` (SECOND) and of the
Sparse-PointPillars backbone (a strided sparse conv at the start of each block, submanifold convs
after it, transposed upsampling), written here against the spconv API. They are checked against a
dense emulation layer by layer (tests/helpers/sparse.py, emulate) and run forward/backward.
"""
from __future__ import annotations

from functools import partial

import pytest
import torch
from torch import nn

import lidarops.compat.spconv as spconv
from lidarops.sparse import SparseConvTensor
from lidarops.sparse import nn as spnn
from helpers.devices import DEVICES
from helpers.sparse import assert_same_sites_and_features, emulate, linear_order, random_sites


# ---- OpenPCDet-style networks, written against the spconv API ----

def post_act_block(in_channels, out_channels, kernel_size, indice_key=None, stride=1, padding=0, conv_type="subm",
                   norm_fn=None):
    if conv_type == "subm":
        conv = spconv.SubMConv3d(in_channels, out_channels, kernel_size, bias=False, indice_key=indice_key)
    elif conv_type == "spconv":
        conv = spconv.SparseConv3d(in_channels, out_channels, kernel_size, stride=stride, padding=padding,
                                   bias=False, indice_key=indice_key)
    elif conv_type == "inverseconv":
        conv = spconv.SparseInverseConv3d(in_channels, out_channels, kernel_size, indice_key=indice_key, bias=False)
    else:
        raise NotImplementedError
    return spconv.SparseSequential(conv, norm_fn(out_channels), nn.ReLU())


class VoxelBackBone8x(nn.Module):
    def __init__(self, input_channels, sparse_shape, with_decoder=False):
        super().__init__()
        norm_fn = partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)
        self.sparse_shape = sparse_shape
        self.conv_input = spconv.SparseSequential(
            spconv.SubMConv3d(input_channels, 16, 3, padding=1, bias=False, indice_key="subm1"),
            norm_fn(16), nn.ReLU())
        block = post_act_block
        self.conv1 = spconv.SparseSequential(block(16, 16, 3, norm_fn=norm_fn, padding=1, indice_key="subm1"))
        self.conv2 = spconv.SparseSequential(
            block(16, 32, 3, norm_fn=norm_fn, stride=2, padding=1, indice_key="spconv2", conv_type="spconv"),
            block(32, 32, 3, norm_fn=norm_fn, padding=1, indice_key="subm2"),
            block(32, 32, 3, norm_fn=norm_fn, padding=1, indice_key="subm2"))
        self.conv3 = spconv.SparseSequential(
            block(32, 64, 3, norm_fn=norm_fn, stride=2, padding=1, indice_key="spconv3", conv_type="spconv"),
            block(64, 64, 3, norm_fn=norm_fn, padding=1, indice_key="subm3"),
            block(64, 64, 3, norm_fn=norm_fn, padding=1, indice_key="subm3"))
        self.conv4 = spconv.SparseSequential(
            block(64, 64, 3, norm_fn=norm_fn, stride=2, padding=(0, 1, 1), indice_key="spconv4", conv_type="spconv"),
            block(64, 64, 3, norm_fn=norm_fn, padding=1, indice_key="subm4"),
            block(64, 64, 3, norm_fn=norm_fn, padding=1, indice_key="subm4"))
        self.conv_out = spconv.SparseSequential(
            spconv.SparseConv3d(64, 128, (3, 1, 1), stride=(2, 1, 1), padding=0, bias=False,
                                indice_key="spconv_down2"),
            norm_fn(128), nn.ReLU())
        self.with_decoder = with_decoder
        if with_decoder:  # a UNet-style way back (PartA2's UNetV2 uses inverse convs like this)
            self.inv4 = block(64, 64, 3, norm_fn=norm_fn, indice_key="spconv4", conv_type="inverseconv")
            self.inv3 = block(64, 32, 3, norm_fn=norm_fn, indice_key="spconv3", conv_type="inverseconv")

    def forward(self, voxel_features, voxel_coords, batch_size):
        x = spconv.SparseConvTensor(features=voxel_features, indices=voxel_coords.int(),
                                    spatial_shape=self.sparse_shape, batch_size=batch_size)
        x = self.conv_input(x)
        x_conv1 = self.conv1(x)
        x_conv2 = self.conv2(x_conv1)
        x_conv3 = self.conv3(x_conv2)
        x_conv4 = self.conv4(x_conv3)
        out = self.conv_out(x_conv4)
        spatial = out.dense()
        N, C, D, H, W = spatial.shape
        result = {"spatial_features": spatial.view(N, C * D, H, W), "x_conv4": x_conv4, "out": out}
        if self.with_decoder:
            up3 = self.inv4(x_conv4)
            up3 = up3.replace_feature(up3.features + x_conv3.features)
            result["up2"] = self.inv3(up3)
        return result


class SparsePointPillarsBackbone(nn.Module):
    """PointPillars' RPN made sparse: per block a strided sparse conv, then submanifold convs; transposed
    upsampling of each block to the first block's grid; dense concatenation."""

    def __init__(self, in_channels=64, layer_nums=(3, 5, 5), layer_strides=(2, 2, 2), num_filters=(64, 128, 256),
                 upsample_strides=(1, 2, 4), num_upsample_filters=(128, 128, 128)):
        super().__init__()
        norm_fn = partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)
        self.blocks, self.deblocks = nn.ModuleList(), nn.ModuleList()
        c_in = in_channels
        for i, (n, s, f) in enumerate(zip(layer_nums, layer_strides, num_filters)):
            layers = [spconv.SparseConv2d(c_in, f, 3, stride=s, padding=1, bias=False, indice_key=f"down{i}"),
                      norm_fn(f), nn.ReLU()]
            for _ in range(n):
                layers += [spconv.SubMConv2d(f, f, 3, padding=1, bias=False, indice_key=f"subm{i}"), norm_fn(f),
                           nn.ReLU()]
            self.blocks.append(spconv.SparseSequential(*layers))
            u, uf = upsample_strides[i], num_upsample_filters[i]
            self.deblocks.append(spconv.SparseSequential(
                spconv.SparseConvTranspose2d(f, uf, u, stride=u, bias=False, indice_key=f"up{i}"), norm_fn(uf),
                nn.ReLU(), spconv.ToDense()))
            c_in = f

    def forward(self, x):
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        return torch.cat(ups, dim=1)


def _voxels(batch, shape, per_sample, channels, seed, device, dtype=torch.float64):
    idx = random_sites(batch, shape, per_sample, seed, empty_middle=False)
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn(idx.shape[0], channels, generator=g, dtype=torch.float64)
    return feats.to(device=device, dtype=dtype), idx.to(device)


def _randomize_bn(net, seed=0):
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm1d):
            m.running_mean.copy_(torch.randn(m.num_features, generator=g) * 0.1)
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.bias.data.copy_(torch.randn(m.num_features, generator=g) * 0.1)


def test_voxel_backbone_8x_matches_dense_emulation(device):
    shape = [41, 24, 24]
    net = VoxelBackBone8x(4, shape, with_decoder=True).double().to(device).eval()
    _randomize_bn(net)
    feats, coords = _voxels(2, shape, 700, 4, seed=0, device=device)
    out = net(feats, coords, 2)
    x = SparseConvTensor(feats, coords, shape, 2)
    reg = {}
    r = emulate(net.conv_input, x, reg)
    r1 = emulate(net.conv1, r, reg)
    r2 = emulate(net.conv2, r1, reg)
    r3 = emulate(net.conv3, r2, reg)
    r4 = emulate(net.conv4, r3, reg)
    ro = emulate(net.conv_out, r4, reg)
    assert out["spatial_features"].shape == (2, 128 * 2, 3, 3)
    torch.testing.assert_close(out["out"].dense(), ro.dense(), rtol=1e-9, atol=1e-9)
    # the decoder goes back to the sites of conv2's output
    up2 = out["up2"]
    r_up3 = emulate(net.inv4, r4, reg)
    # add the skip in the emulation (same sites as r3, order of the reference output)
    ref3 = {tuple(v): i for i, v in enumerate(r3.indices.tolist())}
    perm = torch.tensor([ref3[tuple(v)] for v in r_up3.indices.tolist()], dtype=torch.long)
    r_up3 = r_up3.replace_feature(r_up3.features + r3.features[perm.to(r3.features.device)])
    r_up2 = emulate(net.inv3, r_up3, reg)
    assert torch.equal(up2.indices, out["x_conv4"].indice_dict["spconv3"].indices)
    order = linear_order(r_up2.indices, r_up2.spatial_shape)
    assert_same_sites_and_features(up2.indices, up2.features, r_up2.indices[order], r_up2.features[order],
                                   up2.spatial_shape, 1e-9, "inverse-conv decoder")


def test_voxel_backbone_8x_trains(device):
    shape = [41, 40, 40]
    net = VoxelBackBone8x(4, shape).to(device).train()
    feats, coords = _voxels(2, shape, 1500, 4, seed=1, device=device, dtype=torch.float32)
    out = net(feats, coords, 2)["spatial_features"]
    assert out.shape == (2, 128 * 2, 5, 5)
    out.square().mean().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.conv_input[0].weight.grad.abs().sum() > 0


def test_sparse_pointpillars_backbone(device):
    shape = [32, 32]
    net = SparsePointPillarsBackbone(in_channels=16, num_filters=(16, 32, 64), num_upsample_filters=(32, 32, 32))
    net = net.double().to(device).eval()
    _randomize_bn(net, 1)
    feats, coords = _voxels(2, shape, 150, 16, seed=2, device=device)
    x = spconv.SparseConvTensor(feats, coords, shape, 2)
    out = net(x)
    assert out.shape == (2, 96, 16, 16)
    ups, r = [], x
    for block, deblock in zip(net.blocks, net.deblocks):
        r = emulate(block, r)
        ups.append(emulate(deblock, r))
    torch.testing.assert_close(out, torch.cat(ups, 1), rtol=1e-9, atol=1e-9)
    net.train()
    out = net(x)
    out.mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_full_size_sparse_pointpillars_runs_forward_backward():
    shape = [64, 64]
    net = SparsePointPillarsBackbone().train()
    feats, coords = _voxels(1, shape, 300, 64, seed=3, device="cpu", dtype=torch.float32)
    out = net(spconv.SparseConvTensor(feats, coords, shape, 1))
    assert out.shape == (1, 384, 32, 32)
    out.mean().backward()
    assert net.blocks[2][0].weight.grad.shape == (256, 3, 3, 128)


# ---- the kernel-size-1 trap: spconv 2.3.8 computes features @ weight.view(Cin, Cout) ----

@pytest.mark.parametrize("cls,kw", [(spconv.SubMConv3d, {}), (spconv.SparseConv3d, {}),
                                    (spconv.SparseConvTranspose3d, {}), (spconv.SubMConv3d, {"indice_key": "k"})])
def test_kernel_size_one_reproduces_spconv(device, cls, kw):
    feats, coords = _voxels(2, [5, 6, 7], 12, 4, seed=4, device=device)
    x = spconv.SparseConvTensor(feats, coords, [5, 6, 7], 2)
    m = cls(4, 6, 1, bias=True, **kw).double().to(device)
    assert m.weight.shape == (6, 1, 1, 1, 4)
    y = m(x)
    assert y.indices is x.indices and y.spatial_shape == [5, 6, 7]
    torch.testing.assert_close(y.features, x.features @ m.weight.reshape(4, 6) + m.bias)
    assert "k" not in y.indice_dict  # spconv registers no kernel map for this shortcut
    # lidarops.sparse's own module keeps the documented [Cout, 1, 1, 1, Cin] layout
    own = spnn.SubMConv3d(4, 6, 1).double().to(device)
    own.load_state_dict(m.state_dict())
    torch.testing.assert_close(own(x).features, x.features @ m.weight.reshape(6, 4).t() + m.bias)
    assert not torch.allclose(own(x).features, y.features)


def test_kernel_size_one_with_stride_takes_the_regular_path(device):
    feats, coords = _voxels(1, [6, 6, 6], 30, 4, seed=5, device=device)
    x = spconv.SparseConvTensor(feats, coords, [6, 6, 6], 1)
    m = spconv.SparseConv3d(4, 3, 1, stride=2, bias=False, indice_key="s").double().to(device)
    assert not m.conv1x1
    y = m(x)
    ref = emulate(m, x)
    order = linear_order(ref.indices, ref.spatial_shape)
    assert_same_sites_and_features(y.indices, y.features, ref.indices[order], ref.features[order], y.spatial_shape,
                                   1e-10, "k=1 stride 2")
    assert "s" in y.indice_dict


# ---- API surface and state_dicts ----

def test_spconv_names_and_signatures():
    for name in ("SparseConvTensor", "SubMConv2d", "SubMConv3d", "SparseConv2d", "SparseConv3d",
                 "SparseConvTranspose2d", "SparseConvTranspose3d", "SparseInverseConv2d", "SparseInverseConv3d",
                 "SparseSequential", "SparseMaxPool2d", "SparseMaxPool3d", "ToDense", "SparseModule", "ConvAlgo"):
        assert hasattr(spconv, name), name
    conv = spconv.SubMConv3d(4, 8, 3, 1, 0, 1, 1, False, "k", spconv.ConvAlgo.MaskImplicitGemm, name="c")
    assert isinstance(conv, spconv.conv.SparseConvolution)  # OpenPCDet's find_all_spconv_keys
    assert conv.indice_key == "k" and conv.bias is None and conv.subm
    inv = spconv.SparseInverseConv3d(8, 4, 3, "k", bias=False, algo=None)
    assert inv.inverse and inv.indice_key == "k"
    pool = spconv.SparseMaxPool3d(2, 2, indice_key="p", algo=spconv.ConvAlgo.Native)
    assert pool.stride == (2, 2, 2)
    with pytest.raises(ValueError, match="groups=1 only"):
        spconv.SparseConv3d(4, 8, 3, groups=2)


def test_state_dict_compatible_with_lidarops_modules():
    shape = [41, 24, 24]
    a = VoxelBackBone8x(4, shape).eval()
    _randomize_bn(a, 3)
    sd = a.state_dict()
    assert sd["conv2.0.0.weight"].shape == (32, 3, 3, 3, 16)  # spconv 2.x layout [Cout, *k, Cin]
    assert sd["conv_out.0.weight"].shape == (128, 3, 1, 1, 64)
    b = VoxelBackBone8x(4, shape).eval()
    b.load_state_dict(sd)
    # the same structure built from lidarops.sparse.nn modules takes the same state_dict
    c = VoxelBackBone8x(4, shape).eval()
    for name, m in list(c.named_modules()):
        for child_name, child in list(m.named_children()):
            if isinstance(child, spconv.SparseConvolution):
                k = child.kind
                new = spnn.SparseConvolution(3, child.in_channels, child.out_channels, child.kernel_size,
                                             child.stride, child.padding, child.dilation, child.bias is not None,
                                             k, indice_key=child.indice_key)
                setattr(m, child_name, new)
    c.load_state_dict(sd)
    feats, coords = _voxels(2, shape, 500, 4, seed=6, device="cpu", dtype=torch.float32)
    ya, yb, yc = (n(feats, coords, 2)["spatial_features"] for n in (a, b, c))
    assert torch.equal(ya, yb)
    torch.testing.assert_close(ya, yc, rtol=0, atol=0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("D", [2, 3])
def test_max_pool_starts_at_zero_like_spconv(device, D):
    """spconv 2.3.8's max pool starts the running max at zero: signed features are clamped below at 0."""
    from lidarops.sparse.functional import _max_pool_reference
    shape = [12, 10] if D == 2 else [6, 8, 7]
    sites = random_sites(2, shape, 40, seed=D).to(device)
    feats = torch.randn(sites.shape[0], 5, dtype=torch.float64, device=device) - 0.5  # many all-negative windows
    x = SparseConvTensor(feats, sites, shape, 2)
    y = (spconv.SparseMaxPool2d if D == 2 else spconv.SparseMaxPool3d)(2, 2)(x)
    ref_sites, ref_feats = _max_pool_reference(x, 2, 2)
    assert (ref_feats < 0).any(), "the test needs windows whose max is negative"
    assert_same_sites_and_features(y.indices, y.features, ref_sites, ref_feats.clamp_min(0), y.spatial_shape, 0.0,
                                   f"compat max pool {D}D")
