"""Fuzz properties of this change's entry points: the CPU's channel-sparse delta scatter
(``sscater_scatter_(..., channel_sparse=)``) against its float64 reference on random layers, deltas with any share
of exact zeros, padding rows, inactive outputs and counts, with bad ``channel_sparse`` values named; and the
whole-view KITTI evaluation (``whole_view_annos``, ``KittiEvaluator(camera=False)``) on random drone boxes; and the
recycling backbone's ``channel_sparse`` and dense refresh (``DeltaBackbone``) against the full recomputation on random
pillar maps, with bad ``channel_sparse`` values named."""
from __future__ import annotations

import numpy as np
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.data.formats.kitti import KittiCalib, boxes_to_kitti_labels, camera_to_lidar_boxes
from lidarops.eval import kitti
from helpers.models import small_backbone
from lidarops.sparse import SparseConvTensor
from lidarops.sscater import delta as delta_module
from lidarops.sscater import ops as sops
from .fuzzing import assert_clear_error, assert_close, assert_no_error, fuzz, outcome


@fuzz
@given(data=st.data())
def test_channel_sparse_scatter_matches_reference(data):
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), "seed"))
    k, s, p, transposed = data.draw(st.sampled_from([(3, 1, 1, False), (3, 2, 1, False), (1, 1, 0, False),
                                                     (2, 2, 0, True)]), "layer")
    H, W = data.draw(st.integers(1, 9), "H"), data.draw(st.integers(1, 9), "W")
    cin, cout = data.draw(st.integers(1, 40), "cin"), data.draw(st.integers(1, 70), "cout")
    n = data.draw(st.integers(0, 30), "rows")
    sites = torch.stack([torch.randint(-1, H, (n,), generator=g), torch.randint(-1, W, (n,), generator=g)], 1).int()
    sites[(sites < 0).any(1)] = -1  # padding rows
    # unique real sites: a site's delta is one row
    keys = sites[:, 0].long() * W + sites[:, 1].long()
    first = torch.tensor([int((keys[:i] == keys[i]).sum()) == 0 for i in range(n)], dtype=torch.bool)
    sites[~first & (sites[:, 0] >= 0)] = -1
    delta = torch.randn(n, cin, generator=g, dtype=torch.float64)
    delta[torch.rand(n, cin, generator=g) < data.draw(st.floats(0, 1), "zero share")] = 0.0
    weight = torch.randn(cout, k, k, cin, generator=g, dtype=torch.float64)
    Ho, Wo = (H * s, W * s) if transposed else ((H + 2 * p - k) // s + 1, (W + 2 * p - k) // s + 1)
    if Ho < 1 or Wo < 1:
        return
    acc = torch.randn(Ho, Wo, cout, generator=g, dtype=torch.float64)
    active = torch.rand(Ho, Wo, generator=g) > 0.3 if data.draw(st.booleans(), "out_active") else None
    count = torch.tensor([data.draw(st.integers(0, n + 2), "count")]) if data.draw(st.booleans(), "count?") else None
    choice = data.draw(st.sampled_from([0.0, 0.85, 2.0, -1.0]), "channel_sparse")
    ref_acc, ref_reached = sops._scatter_reference(acc, sites, delta, weight, s, p, transposed, active, count)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        got = acc.to(dtype, copy=True)  # float64: not acc itself, which the next dtype starts from
        reached, err = outcome(sops.scatter_, got, sites, delta.to(dtype), weight.to(dtype), s, p, transposed, active,
                               count, choice)
        assert_no_error(err, f"scatter_ channel_sparse={choice} {dtype}")
        scale = float(ref_acc.abs().max()) if ref_acc.numel() else 1.0
        assert_close(got, ref_acc, rtol=0, atol=tol * max(scale, 1.0), what=f"acc {dtype} channel_sparse={choice}")
        assert torch.equal(reached, ref_reached)
    bad = data.draw(st.sampled_from([float("nan"), "0.5", None, True]), "bad channel_sparse")
    _, err = outcome(sops.scatter_, acc.clone(), sites, delta, weight, s, p, transposed, active, count, bad)
    assert_clear_error(err, ValueError, ["channel_sparse"], f"channel_sparse={bad!r}")


def _drones(data, n):
    return np.array([[data.draw(st.floats(-10, 100), f"x{i}"), data.draw(st.floats(-50, 50), f"y{i}"),
                      data.draw(st.floats(-10, 10), f"z{i}"), 0.7, 0.7, 0.3,
                      data.draw(st.floats(-3.1, 3.1), f"h{i}")] for i in range(n)]).reshape(n, 7)


@fuzz
@given(data=st.data())
def test_whole_view_annos_keep_exactly_the_objects_in_range(data):
    calib = KittiCalib.default()
    n = data.draw(st.integers(0, 6), "drones")
    boxes = _drones(data, n)
    names = [data.draw(st.sampled_from(["Drone", "DontCare", "Car"]), f"name{i}") for i in range(n)]
    gt = kitti.annos_from_labels(boxes_to_kitti_labels(boxes, names, calib, visibility=np.ones(n)))
    rng = [0, -40.32, -8, 80.64, 40.32, 8]
    # centres on the range's faces go either way through the camera frame's float64 round trip
    assume(all((np.abs(boxes[:, i] - rng[i]) > 1e-3).all() and (np.abs(boxes[:, i] - rng[i + 3]) > 1e-3).all()
               for i in range(3)))
    out = kitti.whole_view_annos(gt, calib, rng)
    keep = np.array([nm != "DontCare" for nm in names], bool) & \
        ((boxes[:, :3] >= np.array(rng[:3])) & (boxes[:, :3] <= np.array(rng[3:]))).all(1)
    assert "bbox" not in out and "alpha" not in out and (out["truncated"] == 0).all()
    assert out["name"].tolist() == [nm for nm, k in zip(names, keep) if k]
    back = camera_to_lidar_boxes(out["location"], out["dimensions"][:, [1, 2, 0]], out["rotation_y"], calib)
    assert np.allclose(back[:, :6], boxes[keep, :6], atol=1e-4)
    # detections equal to the drones in range score every one of them: no missed and no false drone
    drones = keep & (np.array(names) == "Drone")
    pred = {"boxes": torch.from_numpy(boxes[drones]), "scores": torch.linspace(0.9, 0.5, int(drones.sum())),
            "labels": torch.ones(int(drones.sum()), dtype=torch.int64)}
    results, err = outcome(kitti.KittiEvaluator(["Drone"], camera=False, point_cloud_range=rng),
                           [pred], [{"annos": gt, "calib": calib}])
    assert_no_error(err, "KittiEvaluator(camera=False)")
    if drones.any():  # (with no object on either side the evaluator's printout keeps every metric, at 0)
        # R11 counts recall position 0, which KITTI's threshold rule fills even for one object (R40 starts at 1)
        assert results[0]["Drone_3d_moderate_R11"] > 0 and results[0]["Drone_bev_moderate_R11"] > 0
        assert not any(k.startswith(("Drone_bbox", "Drone_aos")) for k in results[0])


@fuzz
@given(bad=st.one_of(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=8),
                     st.just([0, 0, 0, 0, 0, 0])))
def test_whole_view_evaluator_names_a_bad_range(bad):
    good = len(bad) == 6 and all(np.isfinite(bad)) and all(bad[i] < bad[i + 3] for i in range(3))
    ev, err = outcome(kitti.KittiEvaluator, ["Drone"], camera=False, point_cloud_range=bad)
    if good:
        assert_no_error(err, f"point_cloud_range={bad}")
    else:
        assert_clear_error(err, ValueError, ["point_cloud_range"], f"point_cloud_range={bad}")


@fuzz
@given(data=st.data())
def test_delta_backbone_channel_sparse_and_dense_refresh(data):
    """Any ``channel_sparse`` (sparse always, never, or by the share of zeros) and a refresh given any share of the
    grid (dense convolutions from half of it, or the sparse ops): the output equals the sparse backbone's full
    recomputation after the refresh and after each of a few random steps; bad values are refused by name."""
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), "seed"))
    H, W = 8 * data.draw(st.integers(1, 3), "H / 8"), 8 * data.draw(st.integers(1, 3), "W / 8")
    bb = small_backbone(seed=data.draw(st.integers(0, 5), "weights"), negative_bias=data.draw(st.sampled_from([0.0, 0.8])))
    choice = data.draw(st.sampled_from([None, 0.0, 0.5, 2.0, -1.0]), "channel_sparse")
    dense = data.draw(st.sampled_from([0.5, 2.0]), "DENSE_REFRESH")
    saved = delta_module.DENSE_REFRESH["cpu"]
    delta_module.DENSE_REFRESH["cpu"] = dense
    try:
        db = delta_module.DeltaBackbone(bb, (H, W), torch.float64, "cpu", channel_sparse=choice)
        state = {}
        for k in torch.randperm(H * W, generator=g)[:int(data.draw(st.floats(0, 1), "share given") * H * W)].tolist():
            state[k] = torch.rand(8, generator=g, dtype=torch.float64)

        def current():
            keys = torch.tensor(sorted(state), dtype=torch.long)
            feats = torch.stack([state[k] for k in keys.tolist()]) if len(keys) else torch.zeros(0, 8, dtype=torch.float64)
            return torch.stack([keys // W, keys % W], 1).int(), feats

        def full():
            sites, feats = current()
            coords = torch.cat([torch.zeros(len(sites), 1, dtype=torch.int32), sites], 1)
            with torch.no_grad():
                return bb(SparseConvTensor(feats, coords, [H, W], 1), mode="sparse")

        out = db.refresh(*current())
        ref = full()
        assert_close(out, ref, rtol=0, atol=1e-12 * max(float(ref.abs().max()), 1.0), what="after the refresh")
        for step in range(data.draw(st.integers(1, 3), "steps")):
            keys = torch.randperm(H * W, generator=g)[:data.draw(st.integers(0, H * W), f"changes {step}")].tolist()
            removed = [k in state and bool(torch.rand(1, generator=g) < 0.3) for k in keys]
            feats = []
            for k, gone in zip(keys, removed):
                if gone:
                    del state[k]
                    feats.append(torch.zeros(8, dtype=torch.float64))
                else:
                    state[k] = torch.rand(8, generator=g, dtype=torch.float64)
                    feats.append(state[k])
            sites = torch.tensor([[k // W, k % W] for k in keys], dtype=torch.int32).view(-1, 2)
            out = db.update(sites, torch.stack(feats) if feats else torch.zeros(0, 8, dtype=torch.float64),
                            torch.tensor(removed, dtype=torch.bool))
            ref = full()
            assert_close(out, ref, rtol=0, atol=1e-12 * max(float(ref.abs().max()), 1.0), what=f"step {step}")
    finally:
        delta_module.DENSE_REFRESH["cpu"] = saved
    bad = data.draw(st.sampled_from([float("nan"), "0.5", True, [0.5]]), "bad channel_sparse")
    _, err = outcome(delta_module.DeltaBackbone, bb, (H, W), torch.float64, "cpu", channel_sparse=bad)
    assert_clear_error(err, ValueError, ["channel_sparse"], f"channel_sparse={bad!r}")
