"""SSCATeR against independent facts, not against itself: the per-layer change counts of hand-made
streams counted by hand from the geometry (3x3 windows, stride 2, transposed children), the same
counts against a dense reference on random integer streams (exact in float64, so "value did not
change" is exact), and pillars whose features change in only some channels.

Definitions under test (lidarops/sscater/delta.py, ``LayerStats`` and ``_layer_step``), per layer and
step:

- ``active``: the layer's output sites in the sparse network (pillars with points; a strided layer's
  outputs with an active input under their 3x3 window; a submanifold layer keeps its block's sites; a
  transposed layer's sites are the children of its active inputs);
- ``changed``: sites whose post-ReLU output changed in at least one channel, plus sites whose active
  status changed (a site re-evaluated to the value it had is NOT changed);
- ``touched``: sites re-evaluated: active output sites under the kernel of an input site whose value
  changed, plus sites whose active status changed.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.models.sscater_pointpillars import PillarFeatureNet
from lidarops.sscater.delta import DeltaBackbone
from lidarops.stream import PillarGrid
from helpers.models import small_backbone


# tiny tensors: on a shared 2-core machine OpenMP wake-ups cost more than the work
pytestmark = pytest.mark.usefixtures("one_thread")


def _integer_backbone(cin, layer_nums, filters, ups, up_filters, seed=None, shifts=None):
    """A float64 backbone with exact arithmetic: integer weights (all ones, or random in {-1, 0, 1, 2}
    with ``seed``), BatchNorm folded to scale 1 and an integer shift (var = 1, mean = 0, eps = 1e-300: 1 + eps rounds to
    1, so the scale is exactly 1; torch refuses eps = 0 in some versions), so
    every sum is an exact integer and recycled sums equal fresh ones bit for bit."""
    bb = BaseBEVBackbone(cin, layer_nums, (2,) * len(layer_nums), filters, ups, up_filters).double()
    g = torch.Generator().manual_seed(seed or 0)
    convs = [m for m in bb.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    norms = [m for m in bb.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    with torch.no_grad():
        for conv in convs:
            if seed is None:
                conv.weight.fill_(1.0)
            else:
                conv.weight.copy_(torch.randint(-1, 3, conv.weight.shape, generator=g).double())
        for i, n in enumerate(norms):
            n.eps = 1e-300
            n.running_mean.zero_()
            n.running_var.fill_(1.0)
            n.weight.fill_(1.0)
            if shifts is not None:
                n.bias.fill_(float(shifts[i]))
            elif seed is not None:
                n.bias.copy_(torch.randint(-3, 2, (n.num_features,), generator=g).double())
            else:
                n.bias.zero_()
    return bb.eval()


def _dense_reference(bb: BaseBEVBackbone, H: int, W: int, pillars: dict):
    """The sparse network's layers with dense ops: per layer (active map, post-ReLU values (C, h, w),
    input values), in DeltaBackbone's order (every block's layers, then the upsampling layers)."""
    C = bb.in_channels
    x = torch.zeros(1, C, H, W, dtype=torch.float64)
    act = torch.zeros(1, 1, H, W, dtype=torch.float64)
    for (y, xx), f in pillars.items():
        x[0, :, y, xx] = torch.as_tensor(f, dtype=torch.float64)
        act[0, 0, y, xx] = 1.0
    layers, block_out = [], []
    for block in bb.blocks:
        mods = [m for m in block if isinstance(m, (torch.nn.Conv2d, torch.nn.BatchNorm2d))]
        for i in range(0, len(mods), 2):
            conv, norm = mods[i], mods[i + 1]
            s = conv.stride[0]
            y = F.conv2d(x, conv.weight, None, s, 1)
            if s > 1:  # a strided layer's sites: an active input under the 3x3 window
                act = (F.conv2d(act, torch.ones(1, 1, 3, 3, dtype=torch.float64), None, s, 1) > 0).double()
            scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
            shift = norm.bias - norm.running_mean * scale
            v = torch.relu(y * scale[:, None, None] + shift[:, None, None]) * act
            layers.append((act[0, 0] > 0, v[0], x[0]))
            x = v
        block_out.append((x, act))
    for (x, act), deblock in zip(block_out, bb.deblocks):
        up, norm = deblock[0], deblock[1]
        u = up.stride[0]
        y = F.conv_transpose2d(x, up.weight, None, u)
        a = F.interpolate(act, scale_factor=u, mode="nearest")  # the children of active inputs
        scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
        shift = norm.bias - norm.running_mean * scale
        v = torch.relu(y * scale[:, None, None] + shift[:, None, None]) * a
        layers.append((a[0, 0] > 0, v[0], x[0]))
    out = torch.cat([v for (_, v, _) in layers[-len(bb.deblocks):]], 0)[None]
    return layers, out


def _reach(kind: str, stride: int, changed_in: torch.Tensor, out_shape) -> torch.Tensor:
    """Output sites whose kernel window holds a changed input site (bool (h, w))."""
    m = changed_in.double()[None, None]
    if kind == "up":
        r = F.interpolate(m, scale_factor=stride, mode="nearest")
    else:
        r = F.conv2d(m, torch.ones(1, 1, 3, 3, dtype=torch.float64), None, stride, 1)
    assert tuple(r.shape[2:]) == tuple(out_shape)
    return r[0, 0] > 0


def _expected_counts(db: DeltaBackbone, before, after, in_before: dict, in_after: dict, H: int, W: int):
    """(active, changed, touched) per layer from two dense evaluations, by the definitions above."""
    kinds = [(lay.kind, lay.stride) for lay in db.layers + db.up_layers]
    # the pillar map's changed sites: features differ in some channel (an emptied pillar's features
    # become zero: it changes when they were not)
    C = db.in_channels
    pin = torch.zeros(H, W, dtype=torch.bool)
    for key in set(in_before) | set(in_after):
        a = torch.as_tensor(in_before.get(key, [0.0] * C), dtype=torch.float64)
        b = torch.as_tensor(in_after.get(key, [0.0] * C), dtype=torch.float64)
        pin[key] = bool((a != b).any())
    out = []
    n_blocks = len(db.up_layers)
    for i, ((a0, v0, _), (a1, v1, x1), (kind, s)) in enumerate(zip(before, after, kinds)):
        if i == 0:
            changed_in = pin
        elif kind == "up":  # the block's last layer feeds the upsampling layer of that block
            block = db.up_layers[i - len(db.layers)].block
            j = db.block_last[block]
            changed_in = (before[j][1] != after[j][1]).any(0)
        else:
            changed_in = (before[i - 1][1] != after[i - 1][1]).any(0)
        status = a0 != a1
        changed = (v0 != v1).any(0) | status
        touched = (_reach(kind, s, changed_in, a1.shape) & a1) | status
        out.append((int(a1.sum()), int(changed.sum()), int(touched.sum())))
    assert len(out) == len(db.layers) + n_blocks
    return out


def _update(db: DeltaBackbone, before: dict, after: dict):
    """Feed the pillars that differ between two maps (emptied ones with removed=True)."""
    C = db.in_channels
    keys = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    sites = torch.tensor(keys, dtype=torch.int32).reshape(-1, 2)
    feats = torch.tensor([after.get(k, [0.0] * C) for k in keys], dtype=torch.float64).reshape(-1, C)
    removed = torch.tensor([k not in after for k in keys], dtype=torch.bool)
    return db.update(sites, feats, removed)


def _counts(db: DeltaBackbone):
    return [(s.active, s.changed, s.touched) for s in db.stats]


# ---- hand-counted steps on a one-block network -------------------------------------------------

def test_hand_counted_change_maps_one_block():
    """8 x 8 pillars, one channel everywhere, weights all ones; layers: down0 (3x3, stride 2, padding 1:
    8 x 8 -> 4 x 4), subm1 (3x3 on 4 x 4), up0 (2x2 transposed, stride 2: 4 x 4 -> 8 x 8). BatchNorm
    folds to scale 1, shift -1 (down0), 0 (subm1), 0 (up0).

    Geometry: down0's output (oy, ox) sees input rows 2 oy - 1 .. 2 oy + 1 (and columns alike), so an
    input at an even row (column) is under one output row (column), an odd one under two.
    A = (2, 2) -> down0 (1, 1) only; B = (5, 5) -> down0 (2, 2), (2, 3), (3, 2), (3, 3);
    C = (2, 6) -> down0 (1, 3) only. Each active down0 / subm1 site has 4 active up0 children.

    Start: A = 1, B = 3. down0: (1, 1) = relu(1 - 1) = 0, B's four = relu(3 - 1) = 2 (5 active).
    subm1 = the sum of down0 over the 3x3 neighbourhood: (1, 1) = 0 + 2 = 2, B's four = 4 x 2 = 8.
    """
    H = W = 8
    bb = _integer_backbone(1, (1,), (1,), (2,), (1,), shifts=[-1, 0, 0])
    db = DeltaBackbone(bb, (H, W), torch.float64)
    state = {(2, 2): [1.0], (5, 5): [3.0]}
    sites = torch.tensor(sorted(state), dtype=torch.int32)
    db.refresh(sites, torch.tensor([state[k] for k in sorted(state)], dtype=torch.float64))
    steps = [
        # 1. A: 1 -> 0 (still a pillar). down0 (1, 1) is re-evaluated: relu(0 - 1) = 0 as before, so
        #    touched 1, changed 0, and nothing goes further.
        ({(2, 2): [0.0], (5, 5): [3.0]}, [(5, 0, 1), (5, 0, 0), (20, 0, 0)]),
        # 2. A empties (its features were already 0: no value delta, only a status change). down0
        #    (1, 1) loses its only input: inactive (status: changed 1 although its value 0 stays 0).
        #    subm1 (1, 1) goes inactive with it (value 2 -> 0): 1, 1; no other subm1 site is reached
        #    (down0 passed on no value change). up0: the 4 children of (1, 1) go inactive.
        ({(5, 5): [3.0]}, [(4, 1, 1), (4, 1, 1), (16, 4, 4)]),
        # 3. C = 1 appears. down0 (1, 3) becomes active, value relu(1 - 1) = 0: status only (1, 1).
        #    subm1 (1, 3) becomes active with its block, value 0 + 2 + 2 = 4 (down0 (1, 3), (2, 2),
        #    (2, 3)); no value change came from down0, so nothing else is touched. up0: its 4 children.
        ({(2, 6): [1.0], (5, 5): [3.0]}, [(5, 1, 1), (5, 1, 1), (20, 4, 4)]),
        # 4. B: 3 -> 4. down0: B's four re-evaluated, 2 -> 3 each. subm1: every active site is within
        #    one site of them ((1, 3) sees (2, 2) and (2, 3)): 5 touched, 5 changed ((1, 3): 4 -> 6;
        #    the others 8 -> 12). up0: 5 x 4 children.
        ({(2, 6): [1.0], (5, 5): [4.0]}, [(5, 4, 4), (5, 5, 5), (20, 20, 20)]),
        # 5. B: 4 -> 3 and C: 1 -> 3 together. down0: (1, 3) 0 -> 2 (+2) and B's four 3 -> 2 (-1
        #    each): 5 touched, 5 changed. subm1: all 5 re-evaluated, but (1, 3) sums (1, 3), (2, 2),
        #    (2, 3): +2 - 1 - 1 = 0, so it keeps its value 6: changed 4, touched 5.
        #    up0: the children of the 4 changed sites: 16.
        ({(2, 6): [3.0], (5, 5): [3.0]}, [(5, 5, 5), (5, 4, 5), (20, 16, 16)]),
        # 6. nothing changes: nothing is re-evaluated.
        ({(2, 6): [3.0], (5, 5): [3.0]}, [(5, 0, 0), (5, 0, 0), (20, 0, 0)]),
        # 7. everything empties: every site changes status (C's and B's down0 values 2 -> 0).
        ({}, [(0, 5, 5), (0, 5, 5), (0, 20, 20)]),
    ]
    for i, (new, expected) in enumerate(steps, 1):
        before_layers, _ = _dense_reference(bb, H, W, state)
        out = _update(db, state, new)
        after_layers, ref = _dense_reference(bb, H, W, new)
        assert _counts(db) == expected, f"step {i}: (active, changed, touched) per layer"
        # the hand counts and the dense reference's counts agree (a check of the reference itself)
        assert _expected_counts(db, before_layers, after_layers, state, new, H, W) == expected, f"step {i}"
        assert torch.equal(out, ref.to(memory_format=torch.channels_last)), f"step {i}: output"
        state = new
    assert not out.any()  # an empty grid: no active site anywhere, an all-zero map


def test_change_counts_match_the_dense_reference_on_random_integer_streams():
    """Three blocks, 3 channels, random integer weights and shifts (exact float64 sums: a value that
    did not change compares equal). Each step adds, empties and edits pillars, often in one channel
    only, re-writes some with their own values, and some steps change nothing."""
    H, W, C = 16, 16, 3
    bb = _integer_backbone(C, (1, 1, 1), (3, 4, 5), (1, 2, 4), (2, 2, 2), seed=5)
    db = DeltaBackbone(bb, (H, W), torch.float64)
    rng = np.random.default_rng(0)
    state = {}
    for _ in range(40):
        k = (int(rng.integers(H)), int(rng.integers(W)))
        state[k] = [float(v) for v in rng.integers(0, 4, C)]
    keys = sorted(state)
    db.refresh(torch.tensor(keys, dtype=torch.int32), torch.tensor([state[k] for k in keys], dtype=torch.float64))
    totals = np.zeros(3, dtype=np.int64)
    unchanged_but_touched = 0
    for step in range(30):
        new = {k: list(v) for k, v in state.items()}
        if step % 7 != 6:  # every 7th step changes nothing
            for _ in range(int(rng.integers(1, 6))):
                k = (int(rng.integers(H)), int(rng.integers(W)))
                r = rng.random()
                if k in new and r < 0.3:
                    del new[k]
                elif k in new and r < 0.8:
                    new[k][int(rng.integers(C))] = float(rng.integers(0, 4))  # one channel (maybe the same value)
                else:
                    new[k] = [float(v) for v in rng.integers(0, 4, C)]
        before, _ = _dense_reference(bb, H, W, state)
        out = _update(db, state, new)
        after, ref = _dense_reference(bb, H, W, new)
        exp = _expected_counts(db, before, after, state, new, H, W)
        assert _counts(db) == exp, f"step {step}: (active, changed, touched) per layer"
        assert torch.equal(out, ref.to(memory_format=torch.channels_last)), f"step {step}: output"
        totals += np.array([sum(c[i] for c in exp) for i in range(3)])
        unchanged_but_touched += sum(t - c for _, c, t in exp if t > c)
        state = new
    # the stream exercised what the counts distinguish: re-evaluated sites whose value stayed
    assert unchanged_but_touched > 0 and totals[1] > 0 and totals[2] > totals[1]


# ---- changes in only some channels ------------------------------------------------------------

def test_a_change_in_one_channel_of_a_pillar_is_passed_on():
    """A pillar whose new features differ from the old ones in channel 1 only: the pillar map's delta
    is zero in channel 0, yet the pillar changed. Channel 0 of down0 reads only input channel 0, so
    its output channel 0 does not change while channel 1 does: partial at the next layer too."""
    H = W = 8
    bb = _integer_backbone(2, (1,), (2,), (2,), (1,), shifts=[0, 0, 0])
    with torch.no_grad():  # down0: output channel c reads input channel c only
        w = bb.blocks[0][1].weight
        w.zero_()
        w[0, 0] = 1.0
        w[1, 1] = 1.0
    db = DeltaBackbone(bb, (H, W), torch.float64)
    state = {(3, 3): [2.0, 1.0], (4, 4): [1.0, 1.0]}
    keys = sorted(state)
    db.refresh(torch.tensor(keys, dtype=torch.int32), torch.tensor([state[k] for k in keys], dtype=torch.float64))
    new = {(3, 3): [2.0, 5.0], (4, 4): [1.0, 1.0]}
    before, _ = _dense_reference(bb, H, W, state)
    out = _update(db, state, new)
    after, ref = _dense_reference(bb, H, W, new)
    assert torch.equal(out, ref.to(memory_format=torch.channels_last))
    # (3, 3) is at an odd row and column: under 4 down0 outputs ((1, 1), (1, 2), (2, 1), (2, 2)), all
    # active; their channel 0 is unchanged, channel 1 grows by 4
    d0 = after[0][1] - before[0][1]
    assert torch.equal(d0[0], torch.zeros_like(d0[0])) and int((d0[1] != 0).sum()) == 4
    assert _counts(db)[0] == (int(after[0][0].sum()), 4, 4)
    assert _counts(db) == _expected_counts(db, before, after, state, new, H, W)


def _points_model(dtype=torch.float64):
    """PFN with two hand-set channels (BatchNorm folded to the identity): channel 0 = intensity,
    channel 1 = x - x_centre of the pillar; the max over a pillar's points of their ReLU."""
    pfn = PillarFeatureNet(9, 2)
    with torch.no_grad():
        pfn.linear.weight.zero_()
        pfn.linear.weight[0, 3] = 1.0  # intensity
        pfn.linear.weight[1, 7] = 1.0  # x offset to the pillar centre
        pfn.norm.eps = 1e-300  # 1 + eps rounds to 1 (torch refuses eps = 0 in some versions)
        pfn.norm.running_mean.zero_()
        pfn.norm.running_var.fill_(1.0)
        pfn.norm.weight.fill_(1.0)
        pfn.norm.bias.zero_()
    return pfn.eval().to(dtype), small_backbone(cin=2, seed=4, negative_bias=0.2).to(dtype)


def test_a_point_that_changes_some_pfn_channels_only():
    """SSCATeRPointPillars: a second point enters a pillar with a lower intensity (channel 0 keeps
    the first point's maximum exactly) and a positive offset to the centre (channel 1 goes from 0 to
    0.3): the pillar changed in one channel only. It must be passed on, and the output must equal the
    full recomputation; then the first point leaves (both channels change) and the second leaves."""
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    grid = PillarGrid((-8.0, -8.0, -2.0, 8.0, 8.0, 2.0), (1.0, 1.0))  # 16 x 16; pillar (10, 10): x, y in [2, 3)
    pfn, bb = _points_model()
    model = SSCATeRPointPillars(pfn, bb, grid, window=0.1, max_points_per_pillar=8, max_pillars=256,
                                refresh_every=0, dtype=torch.float64)
    other = [[-5.5, -3.5, 0.0, 0.7], [6.5, 0.5, 0.0, 0.4]]  # two pillars that stay, far away
    slices = [
        (torch.tensor([[2.2, 2.5, 0.0, 0.9]] + other), [0.001, 0.001, 0.001]),
        (torch.tensor([[2.8, 2.5, 0.0, 0.3]]), [0.011]),
        (torch.tensor(other), [0.095, 0.095]),  # keeps the far pillars; the window ends at 0.095
        (torch.zeros(0, 4), []),  # now = 0.105: the first point (t = 0.001) left; the 2nd stays
        (torch.zeros(0, 4), []),  # now = 0.115: the second left: the pillar empties
    ]
    nows = [0.001, 0.011, 0.095, 0.105, 0.115]
    pushed, pushed_t = [], []
    prev = None
    for i, ((p, t), now) in enumerate(zip(slices, nows)):
        out = model.step(p.float(), torch.tensor(t, dtype=torch.float64), now=now).clone()
        pushed.append(p.float())
        pushed_t.append(torch.tensor(t, dtype=torch.float64))
        allp, allt = torch.cat(pushed), torch.cat(pushed_t)
        ref = model.recompute(allp[allt > model.stats.t - model.window])
        assert (out - ref).abs().max() <= 1e-12 * ref.abs().max(), f"slice {i}"
        if i < 2:  # the pillar's PFN features: (0.9, 0) after the first point, (0.9, 0.3) after the second
            with torch.no_grad():
                f = model.pfn(model.stream.pillars(torch.tensor([[0, 10, 10]], dtype=torch.int32)))
            assert f[0, 0].item() == pytest.approx(0.9, abs=1e-6)
            assert f[0, 1].item() == (0.0 if i == 0 else pytest.approx(0.3, abs=1e-6))
        if i == 1:
            assert model.stats.pillars_changed == 1 and not model.stats.refreshed
            assert model.stats.layers[0].changed > 0 and not torch.equal(out, prev)
        prev = out
    assert model.stats.pillars_changed == 1 and model.stream.num_active == 2
