"""A kernel map checks a frame's sites once: sites a layer made, or sites already checked at their current
version, are not checked again (the check is a host synchronisation on CUDA), and an in-place change brings
the check back. Under ``lidarops.validation(False)`` bad rows are skipped, never read out of bounds."""
from __future__ import annotations

import math

import pytest
import torch

from lidarops.ops.validation import validation
from lidarops.sparse import SparseConvTensor
from lidarops.sparse import functional as Fs
from lidarops.sparse.tensor import sites_checked
from helpers.devices import requires_cuda
from helpers.sparse import assert_same_sites_and_features, linear_order, random_tensor, random_weight

SHAPE = (9, 11)
ops = torch.ops.lidarops


def test_a_layers_output_sites_are_known_valid_and_its_input_sites_once_checked(device):
    x = random_tensor(2, SHAPE, 25, 3, seed=1, device=device)
    assert not sites_checked(x.indices, x.batch_size, x.spatial_shape)
    y = Fs.conv(x, random_weight(4, (3, 3), 3, device=device), kind="conv", stride=2, padding=1)
    assert sites_checked(x.indices, x.batch_size, x.spatial_shape)  # checked by the map's construction
    assert sites_checked(y.indices, y.batch_size, y.spatial_shape)  # made by the layer
    assert not sites_checked(y.indices, y.batch_size, [s + 1 for s in y.spatial_shape])  # another grid: not known
    w2 = random_weight(5, (3, 3), 4, seed=1, device=device)
    z = Fs.conv(y, w2, kind="subm")  # on sites it does not check again: still the dense reference's answer
    ref_i, ref_f = Fs._conv_reference(y, w2, None, "subm")
    assert_same_sites_and_features(z.indices, z.features, ref_i, ref_f, z.spatial_shape, 1e-10, "subm on made sites")


@pytest.mark.parametrize("kind", ["subm", "conv"])
def test_an_in_place_change_of_checked_sites_is_checked_again(device, kind):
    x = random_tensor(1, SHAPE, 20, 3, seed=2, device=device)
    w = random_weight(4, (3, 3), 3, device=device)
    Fs.conv(x, w, kind=kind, stride=2, padding=1)  # checks x's sites
    x.indices[3, 1] = SHAPE[0] + 4  # outside the grid, after the check
    with pytest.raises(ValueError, match=r"indices lie outside|outside"):
        Fs.conv(SparseConvTensor(x.features, x.indices, list(SHAPE), 1), w, kind=kind, stride=2, padding=1)


def test_made_sites_changed_in_place_are_checked(device):
    x = random_tensor(1, SHAPE, 20, 3, seed=3, device=device)
    y = Fs.conv(x, random_weight(4, (3, 3), 3, device=device), kind="conv", stride=2, padding=1)
    y.indices[0] = y.indices[1]  # a duplicate site in the layer's own output
    with pytest.raises(ValueError, match="duplicate|more than once"):
        Fs.conv(y, random_weight(4, (3, 3), 4, device=device), kind="subm")


def test_a_duplicate_site_in_a_new_frame_is_caught_by_a_strided_layer(device):
    x = random_tensor(1, SHAPE, 20, 3, seed=4, device=device)
    idx = x.indices.clone()
    idx[5] = idx[2]
    with pytest.raises(ValueError, match="duplicate|more than once"):
        Fs.conv(SparseConvTensor(x.features, idx, list(SHAPE), 1), random_weight(4, (3, 3), 3, device=device),
                kind="conv", stride=2, padding=1)


@pytest.mark.parametrize("kind", ["conv", "transposed", "subm"])
def test_validation_off_skips_rows_outside_the_grid(device, kind):
    x = random_tensor(1, SHAPE, 20, 3, seed=5, device=device)
    w = random_weight(4, (3, 3), 3, device=device)
    kw = {} if kind == "subm" else {"stride": 2, "padding": 1}
    good = Fs.conv(x, w, kind=kind, **kw)
    bad_rows = torch.tensor([[0, SHAPE[0] + 3, 1], [1, 2, 2], [0, -1, 4]], dtype=torch.int32, device=device)
    idx = torch.cat([x.indices, bad_rows])
    feats = torch.cat([x.features, torch.randn(3, 3, dtype=x.features.dtype, device=device)])
    bad = SparseConvTensor(feats, idx, list(SHAPE), 1)
    with pytest.raises(ValueError, match="outside"):
        Fs.conv(bad, w, kind=kind, **kw)
    with validation(False):
        y = Fs.conv(bad, w, kind=kind, **kw)
    if kind == "subm":  # the output keeps the input's rows; the bad rows read no neighbour and none reads them
        torch.testing.assert_close(y.features[:-3], good.features, rtol=0, atol=1e-12)
    else:
        assert torch.equal(y.indices.cpu(), good.indices.cpu())
        torch.testing.assert_close(y.features, good.features, rtol=0, atol=1e-12)


def test_out_indices_op_without_validation_skips_bad_rows(device):
    x = random_tensor(2, SHAPE, 20, 3, seed=6, device=device)
    args = (2, list(SHAPE), [5, 6], [3, 3], [2, 2], [1, 1], [1, 1], False, 0)
    good = ops.sparse_conv_out_indices(x.indices, *args)
    bad = torch.cat([x.indices, torch.tensor([[2, 0, 0], [0, 0, SHAPE[1]], [-1, 3, 3]], dtype=torch.int32,
                                             device=device)])
    with pytest.raises(ValueError, match="outside"):
        ops.sparse_conv_out_indices(bad, *args)
    assert torch.equal(ops.sparse_conv_out_indices(bad, *args, False).cpu(), good.cpu())


@pytest.mark.parametrize("kind, ksize, kw", [("subm", (3, 3), {}), ("conv", (3, 3), {"stride": 2, "padding": 1}),
                                             ("transposed", (2, 2), {"stride": 2})])
def test_a_failed_check_registers_no_map_and_marks_nothing(device, kind, ksize, kw):
    """A failed check of a new frame's sites (the flags kept in the table's fill on CUDA) raises the named error,
    and neither the sites nor the input's indice_dict keep anything from the failed call (the same bad tensor
    raises again); a good frame is marked checked and its layer is the reference's."""
    x = random_tensor(1, SHAPE, 20, 3, seed=7, device=device)
    w = random_weight(4, ksize, 3, device=device)
    kw = dict(kw, indice_key="k")
    idx = x.indices.clone()
    idx[6] = idx[4]  # a duplicate
    bad = SparseConvTensor(x.features, idx, list(SHAPE), 1)
    for _ in range(2):
        with pytest.raises(ValueError, match=r"rows 4 and 6 both hold"):
            Fs.conv(bad, w, kind=kind, **kw)
        assert not sites_checked(bad.indices, 1, SHAPE) and "k" not in bad.indice_dict
    idx[6, 1] = SHAPE[0]  # outside instead
    bad = SparseConvTensor(x.features, idx, list(SHAPE), 1)
    with pytest.raises(ValueError, match=r"indices row 6 .* lies outside"):
        Fs.conv(bad, w, kind=kind, **kw)
    y = Fs.conv(x, w, kind=kind, **kw)
    assert sites_checked(x.indices, 1, SHAPE) and "k" in y.indice_dict and "k" not in x.indice_dict
    ref_i, ref_f = Fs._conv_reference(x, w, None, kind, **{k: v for k, v in kw.items() if k != "indice_key"})
    order = linear_order(ref_i, SHAPE if kind == "subm" else y.spatial_shape)
    assert_same_sites_and_features(y.indices, y.features, ref_i[order.to(ref_i.device)],
                                   ref_f[order.to(ref_f.device)], y.spatial_shape, 1e-10, f"{kind} after")


def test_a_new_frames_check_read_after_the_convolution_is_queued_gives_the_checked_result(device):
    """conv reads a new frame's check after queuing the convolution (CUDA): the map and the output are those of
    the map built with the check read at once, and the sites are marked checked only once the check is read."""
    x = random_tensor(2, SHAPE, 30, 3, seed=8, device=device)
    w = random_weight(4, (3, 3), 3, device=device)
    for kind, kw in (("subm", {}), ("conv", {"stride": 2, "padding": 1})):
        fresh = SparseConvTensor(x.features, x.indices.clone(), list(SHAPE), 2)
        km, pending = Fs._build_kernel_map(fresh, kind, (3, 3), kw.get("stride", 1), kw.get("padding", 0), 1, 0,
                                           None, "auto", defer=True)
        assert (pending is not None) == fresh.indices.is_cuda  # the CPU checks at once
        assert sites_checked(fresh.indices, 2, SHAPE) == (pending is None)
        if pending is not None:
            Fs._settle(pending)
        assert sites_checked(fresh.indices, 2, SHAPE)
        ref = Fs.build_kernel_map(SparseConvTensor(x.features, x.indices.clone(), list(SHAPE), 2), kind, 3, **kw)
        assert torch.equal(km.neighbors.cpu(), ref.neighbors.cpu()) and torch.equal(km.out_indices.cpu(),
                                                                                     ref.out_indices.cpu())
        y = Fs.conv(SparseConvTensor(x.features, x.indices.clone(), list(SHAPE), 2), w, kind=kind, **kw)
        ref_i, ref_f = Fs._conv_reference(x, w, None, kind, **kw)
        order = linear_order(ref_i, y.spatial_shape)
        assert_same_sites_and_features(y.indices, y.features, ref_i[order.to(ref_i.device)],
                                       ref_f[order.to(ref_f.device)], y.spatial_shape, 1e-10, kind)


def test_deferred_checks_never_read_do_not_disturb_later_ones(device):
    """A deferred check whose caller raised before reading it (its ticket never redeemed) is dropped when its slot
    comes round again: more such checks than the ring holds, then good and bad frames are still checked."""
    if device != "cuda":
        pytest.skip("the CPU reads its checks at once")
    x = random_tensor(1, SHAPE, 20, 3, seed=9, device=device)
    args = (1, list(SHAPE), [3, 3], [1, 1], [1, 1], [1, 1], False, 0)
    tickets = [ops.sparse_kernel_map_deferred(x.indices.clone(), x.indices, *args)[1] for _ in range(70)]
    assert tickets == list(range(tickets[0], tickets[0] + 70))
    with pytest.raises(ValueError, match="is unknown or its slot was reused"):
        ops.sparse_site_check(x.indices, tickets[0], 1, list(SHAPE))  # its slot was reused
    ops.sparse_site_check(x.indices, tickets[-1], 1, list(SHAPE))
    w = random_weight(4, (3, 3), 3, device=device)
    idx = x.indices.clone()
    idx[3] = idx[1]
    with pytest.raises(ValueError, match=r"rows 1 and 3 both hold"):
        Fs.conv(SparseConvTensor(x.features, idx, list(SHAPE), 1), w, kind="subm")
    y = Fs.conv(SparseConvTensor(x.features, x.indices.clone(), list(SHAPE), 1), w, kind="subm")
    ref_i, ref_f = Fs._conv_reference(x, w, None, "subm")
    order = linear_order(ref_i, SHAPE)
    assert_same_sites_and_features(y.indices, y.features, ref_i[order.to(ref_i.device)],
                                   ref_f[order.to(ref_f.device)], y.spatial_shape, 1e-10, "subm after")


@pytest.mark.parametrize("landed", [True, False])
def test_a_layer_reads_its_check_in_the_slot_or_through_the_op(device, monkeypatch, landed):
    """A layer reads a passed check in its slot; a slot not yet written (here: every slot shows no ticket) sends
    it through ``sparse_site_check``, which waits for the word: the same results and errors either way."""
    if device != "cuda":
        pytest.skip("the CPU reads its checks at once")
    calls = []

    def deferred(*a):  # the map's kernels done before the layer reads its slot, so that the count is exact
        out = ops.sparse_kernel_map_deferred(*a)
        torch.cuda.synchronize()
        return out

    class Spy:  # torch.ops namespaces refuse attribute patches: swap the namespace the module reads
        def __getattr__(self, name):
            if name == "sparse_site_check":
                return lambda *a: (calls.append(a[1]), ops.sparse_site_check(*a))[1]
            return deferred if name == "sparse_kernel_map_deferred" else getattr(ops, name)

    monkeypatch.setattr(Fs.torch.ops, "lidarops", Spy(), raising=False)
    if not landed:
        slots = ops.sparse_site_check_slots(torch.zeros(1, device=device)).numpy()
        monkeypatch.setattr(Fs, "_check_slots", slots * 0 - 1)  # no slot holds a ticket's word
    x = random_tensor(1, SHAPE, 20, 3, seed=10, device=device)
    w = random_weight(4, (3, 3), 3, device=device)
    torch.cuda.synchronize()
    y = Fs.conv(SparseConvTensor(x.features, x.indices.clone(), list(SHAPE), 1), w, kind="subm")
    assert sites_checked(y.indices, 1, SHAPE)
    ref_i, ref_f = Fs._conv_reference(x, w, None, "subm")
    order = linear_order(ref_i, SHAPE)
    assert_same_sites_and_features(y.indices, y.features, ref_i[order.to(ref_i.device)],
                                   ref_f[order.to(ref_f.device)], y.spatial_shape, 1e-10, "subm")
    idx = x.indices.clone()
    idx[4] = idx[2]
    with pytest.raises(ValueError, match=r"rows 2 and 4 both hold"):
        Fs.conv(SparseConvTensor(x.features, idx, list(SHAPE), 1), w, kind="subm")
    assert not sites_checked(idx, 1, SHAPE)
    # the passed frame went through the op only when its slot showed nothing; the failed one always does
    assert len(calls) == (1 if landed else 2), calls


@pytest.mark.parametrize("D, kernel, stride, out_extra", [
    (2, [2, 2], [2, 2], [0, 0]), (2, [1, 1], [1, 1], [0, 0]), (2, [3, 2], [3, 2], [1, 0]), (3, [2, 2, 2], [2, 2, 2], [0, 1, 0]),
    (2, [3, 3], [2, 2], [0, 0]), (2, [2, 2], [2, 2], [-1, 0])])  # the last two: not disjoint blocks (overlap, cut)
def test_transposed_out_indices_of_checked_sites_are_the_counted_ones(device, D, kernel, stride, out_extra):
    """``checked=True`` (sites vouched for) gives the same sorted output sites as counting them, for every
    geometry: a transposed convolution whose kernel is its stride knows its N K outputs (no read on CUDA), the
    others count as before; ragged batches and no sites at all."""
    shape = (5, 6, 4)[:D]
    for seed, (batch, n) in enumerate([(3, 30), (2, 1), (1, 0), (2, 40)]):
        x = random_tensor(batch, shape, n, 2, seed=seed, device=device)
        out_shape = [s * st + e for s, st, e in zip(shape, stride, out_extra)]
        args = (batch, list(shape), out_shape, kernel, stride, [0] * D, [1] * D, True, 0, False)
        counted = ops.sparse_conv_out_indices(x.indices, *args)
        assert torch.equal(ops.sparse_conv_out_indices(x.indices, *args, True).cpu(), counted.cpu())
        if out_extra[0] >= 0 and kernel == stride:  # each input site's block of K outputs, all inside the grid
            assert counted.shape[0] == x.indices.shape[0] * math.prod(kernel)


@requires_cuda
def test_a_transposed_layer_whose_kernel_is_its_stride_reads_nothing_back_on_checked_sites():
    """On sites a layer made (or checked before), an upsampling layer whose kernel is its stride builds its map
    without waiting for the device, and gives the dense reference's answer; one whose blocks overlap reads its
    output count (what the sync detector must catch)."""
    device = "cuda"
    x = random_tensor(2, SHAPE, 40, 3, seed=11, device=device)
    w = random_weight(4, (3, 3), 3, device=device)
    with torch.no_grad():
        y = Fs.conv(x, w, kind="conv", stride=2, padding=1)  # made sites
        for ksize, stride, reads in (((2, 2), 2, False), ((1, 1), 1, False), ((3, 3), 2, True)):
            w_up = random_weight(5, ksize, 4, seed=3, device=device)
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("error")
            try:
                if reads:
                    with pytest.raises(RuntimeError, match="synchroniz"):
                        Fs.conv(y, w_up, kind="transposed", stride=stride)
                    continue
                z = Fs.conv(y, w_up, kind="transposed", stride=stride)
            finally:
                torch.cuda.set_sync_debug_mode("default")
            ref_i, ref_f = Fs._conv_reference(y, w_up, None, "transposed", stride=stride)
            order = linear_order(ref_i, z.spatial_shape)
            assert_same_sites_and_features(z.indices, z.features, ref_i[order.to(ref_i.device)],
                                           ref_f[order.to(ref_f.device)], z.spatial_shape, 1e-5, f"{ksize} up")
