"""lidarops.models.pointpillars (PointPillars and its parts: pillar_vfe, anchor_head, losses, postprocess):
OpenPCDet's state-dict layout and anchor order, the pillar features and losses against values computed here by
hand, post-processing, configs, bad input, export, and an overfit run on simulated frames."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.nn import functional as F

import lidarops
from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError, load_config
from lidarops.models.config import PointPillarsConfig
from lidarops.models.losses import sigmoid_focal_loss
from lidarops.models.pillar_vfe import PillarVFE
from lidarops.models.pointpillars import PointPillars
from lidarops.models.postprocess import postprocess, postprocess_padded

from helpers.models import TINY


def openpcdet_pointpillar_keys() -> dict[str, tuple]:
    """The state dict of OpenPCDet's PointPillar (pointpillar.yaml) written from its module tree:
    Detector3DTemplate's global_step; PillarVFE's one PFNLayer (Linear 10 -> 64 without bias,
    BatchNorm1d); BaseBEVBackbone blocks [ZeroPad2d, Conv, BN, ReLU] + [Conv, BN, ReLU] x n and deblocks
    [ConvTranspose2d, BN, ReLU]; AnchorHeadSingle's three 1x1 convolutions over 6 anchors per location."""
    keys = {"global_step": (1,)}

    def bn(prefix, c):
        keys.update({f"{prefix}.weight": (c,), f"{prefix}.bias": (c,), f"{prefix}.running_mean": (c,),
                     f"{prefix}.running_var": (c,), f"{prefix}.num_batches_tracked": ()})

    keys["vfe.pfn_layers.0.linear.weight"] = (64, 10)
    bn("vfe.pfn_layers.0.norm", 64)
    c_in = 64
    for i, (c, n, cu, u) in enumerate(zip([64, 128, 256], [3, 5, 5], [128, 128, 128], [1, 2, 4])):
        keys[f"backbone_2d.blocks.{i}.1.weight"] = (c, c_in, 3, 3)
        bn(f"backbone_2d.blocks.{i}.2", c)
        for j in range(n):
            keys[f"backbone_2d.blocks.{i}.{4 + 3 * j}.weight"] = (c, c, 3, 3)
            bn(f"backbone_2d.blocks.{i}.{5 + 3 * j}", c)
        keys[f"backbone_2d.deblocks.{i}.0.weight"] = (c, cu, u, u)
        bn(f"backbone_2d.deblocks.{i}.1", cu)
        c_in = c
    for name, out in (("conv_cls", 6 * 3), ("conv_box", 6 * 7), ("conv_dir_cls", 6 * 2)):
        keys[f"dense_head.{name}.weight"] = (out, 384, 1, 1)
        keys[f"dense_head.{name}.bias"] = (out,)
    return keys


def test_state_dict_is_openpcdet_pointpillar():
    model = PointPillars()
    got = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert got == openpcdet_pointpillar_keys()
    assert sum(p.numel() for p in model.parameters()) == 4_834_888  # OpenPCDet reports 4.8 M


def test_kitti_anchor_count_and_head_layout():
    model = PointPillars()
    head = model.dense_head
    assert head.anchors_flat.shape == (216 * 248 * 6, 7) == (321_408, 7)
    assert head.num_anchors_per_location == 6
    raw = head(torch.zeros(1, 384, 248, 216))
    assert raw["cls_preds"].shape == (1, 248, 216, 18) and raw["dir_cls_preds"].shape == (1, 248, 216, 12)
    # location (y=0, x=1): anchors 6..11 are Car 0, Car pi/2, Ped 0, Ped pi/2, Cyc 0, Cyc pi/2
    a = head.anchors_flat[6:12]
    step = 69.12 / 215
    assert torch.allclose(a[:, 0], torch.full((6,), step)) and torch.allclose(a[:, 1], torch.full((6,), -39.68))
    assert torch.allclose(a[:, 3], torch.tensor([3.9, 3.9, 0.8, 0.8, 1.76, 1.76]))
    assert torch.allclose(a[:, 6], torch.tensor([0, 1.57, 0, 1.57, 0, 1.57]))
    assert torch.allclose(a[0, 2], torch.tensor(-1.78 + 1.56 / 2))


def test_vfe_features_by_hand():
    """Two points in pillar (x=2, y=1) of a 1 m grid starting at (0, -4): the 10 features, with the
    linear layer an identity on them and BatchNorm an identity."""
    vfe = PillarVFE(4, [1.0, 1.0, 4.0], [0.0, -4.0, -3.0, 8.0, 4.0, 1.0], num_filters=[10]).eval()
    with torch.no_grad():
        vfe.pfn_layers[0].linear.weight.copy_(torch.eye(10))
        vfe.pfn_layers[0].norm.running_var.fill_(1 - 1e-3)  # with eps 1e-3: scale exactly 1
    p = torch.tensor([[2.2, -2.9, -1.0, 0.5], [2.6, -2.3, -0.5, 0.25]])
    voxels = torch.zeros(1, 4, 4)
    voxels[0, :2] = p
    out = vfe(voxels, torch.tensor([2]), torch.tensor([[0, 0, 1, 2]]))
    mean = p[:, :3].mean(0)
    centre = torch.tensor([2.5, -2.5, -1.0])  # (x + 0.5) m, -4 + (y + 0.5) m, z range centre
    feats = torch.cat([p, p[:, :3] - mean, p[:, :3] - centre], 1)
    expected = torch.relu(feats).amax(0)  # the two empty slots add zeros, below relu(.)
    assert torch.allclose(out[0], expected, atol=1e-6), (out, expected)


def test_vfe_empty_slots_take_part_like_openpcdet():
    """OpenPCDet lets the zero-feature padding slots through BatchNorm and ReLU into the max: with a
    positive BatchNorm shift a pillar of negative responses outputs relu(shift), not relu(x + shift)."""
    vfe = PillarVFE(4, [1.0, 1.0, 4.0], [0.0, -4.0, -3.0, 8.0, 4.0, 1.0], num_filters=[1]).eval()
    with torch.no_grad():
        vfe.pfn_layers[0].linear.weight.zero_()
        vfe.pfn_layers[0].linear.weight[0, 0] = -1.0  # -x
        vfe.pfn_layers[0].norm.running_var.fill_(1 - 1e-3)
        vfe.pfn_layers[0].norm.bias.fill_(0.5)
    voxels = torch.zeros(2, 3, 4)
    voxels[:, 0] = torch.tensor([[3.2, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.0]])
    out = vfe(voxels, torch.tensor([1, 3]), torch.tensor([[0, 0, 4, 3], [0, 0, 4, 0]]))
    # pillar 0: one point (-3.2 + 0.5 < 0) and two empty slots giving relu(0.5)
    # pillar 1: three "points" (the zeros count as points): max(relu(-0.2 + 0.5), relu(0.5)) = 0.5
    assert torch.allclose(out[:, 0], torch.tensor([0.5, 0.5]))


def test_pfn_inference_folds_batchnorm_exactly_enough():
    """In eval mode the last PFN layer folds BatchNorm into the linear map and takes the max before the
    ReLU; against Linear -> BatchNorm (running statistics, some scales negative) -> ReLU -> max in float64."""
    from lidarops.models.pillar_vfe import PFNLayer

    g = torch.Generator().manual_seed(3)
    layer = PFNLayer(10, 16, use_norm=True, last_layer=True).double()
    with torch.no_grad():
        layer.norm.weight.copy_(torch.randn(16, generator=g, dtype=torch.float64))
        layer.norm.bias.copy_(torch.randn(16, generator=g, dtype=torch.float64))
        layer.norm.running_mean.copy_(torch.randn(16, generator=g, dtype=torch.float64))
        layer.norm.running_var.copy_(torch.rand(16, generator=g, dtype=torch.float64) + 0.1)
    x = torch.randn(50, 7, 10, generator=g, dtype=torch.float64)
    n = layer.norm
    y = F.linear(x, layer.linear.weight)
    y = (y - n.running_mean) / torch.sqrt(n.running_var + n.eps) * n.weight + n.bias
    expected = torch.relu(y).amax(dim=1, keepdim=True)
    assert (n.weight < 0).any()
    assert torch.allclose(layer.eval()(x), expected, rtol=1e-12, atol=1e-12)


def test_focal_loss_formula():
    logits = torch.tensor([-2.0, 0.0, 1.5, 3.0])
    targets = torch.tensor([0.0, 1.0, 1.0, 0.0])
    got = sigmoid_focal_loss(logits, targets)
    for x, t, g in zip(logits.tolist(), targets.tolist(), got.tolist()):
        p = 1 / (1 + math.exp(-x))
        pt = p if t == 1 else 1 - p
        alpha = 0.25 if t == 1 else 0.75
        assert abs(g - alpha * (1 - pt) ** 2 * -math.log(pt)) < 1e-6


def test_losses_by_hand():
    """Tiny grid, one gt box equal to one anchor: the loss terms computed anchor by anchor here."""
    torch.manual_seed(0)
    model = PointPillars(TINY)
    head = model.dense_head
    anchors = head.anchors_flat  # (4 * 4 * 2, 7), align_center: x in {1, 3, 5, 7}, y in {-3, -1, 1, 3}
    k = 2 * (4 * 1 + 2) + 1  # y index 1, x index 2, rotation pi/2
    gt = anchors[k].clone()
    gt[0] += 0.1
    gt[6] += 0.2
    gt_boxes = torch.cat([gt, torch.tensor([1.0])])[None, None]
    g = torch.Generator().manual_seed(1)
    preds = {"cls_preds": torch.randn(1, 4, 4, 2, generator=g), "box_preds": torch.randn(1, 4, 4, 14, generator=g) * 0.1,
             "dir_cls_preds": torch.randn(1, 4, 4, 4, generator=g)}
    out = head.loss(preds, gt_boxes)
    labels = head.target_assigner.assign_targets(head.anchors, gt_boxes)["box_cls_labels"][0]
    assert labels[k] == 1 and (labels == 1).sum() == 1  # the matched anchor; others ignored or background
    cls = preds["cls_preds"].reshape(-1)
    box = preds["box_preds"].reshape(-1, 7)
    dirl = preds["dir_cls_preds"].reshape(-1, 2)
    loss_cls = loss_box = loss_dir = 0.0
    for i in range(anchors.shape[0]):
        lab = int(labels[i])
        if lab >= 0:
            p = 1 / (1 + math.exp(-float(cls[i])))
            t = 1.0 if lab == 1 else 0.0
            pt = p if t else 1 - p
            loss_cls += (0.25 if t else 0.75) * (1 - pt) ** 2 * -math.log(pt)
        if lab == 1:
            a = anchors[i].tolist()
            diag = math.hypot(a[3], a[4])
            target = [(gt[0] - a[0]) / diag, (gt[1] - a[1]) / diag, (gt[2] - a[2]) / a[5], math.log(gt[3] / a[3]),
                      math.log(gt[4] / a[4]), math.log(gt[5] / a[5]), gt[6] - a[6]]
            b = box[i].tolist()
            for c in range(7):
                bp, tp = (b[c], float(target[c])) if c < 6 else (math.sin(b[6]) * math.cos(target[6]),
                                                                  math.cos(b[6]) * math.sin(target[6]))
                d = abs(bp - tp)
                loss_box += 0.5 * d * d * 9 if d < 1 / 9 else d - 0.5 / 9
            rot = (float(gt[6]) - 0.78539) % (2 * math.pi)
            bin_ = int(rot // math.pi)
            z = dirl[i].tolist()
            loss_dir += -(z[bin_] - math.log(math.exp(z[0]) + math.exp(z[1])))
    assert abs(out["loss_cls"].item() - loss_cls) < 1e-5
    assert abs(out["loss_box"].item() - 2.0 * loss_box) < 1e-5
    assert abs(out["loss_dir"].item() - 0.2 * loss_dir) < 1e-5
    assert abs(out["loss"].item() - (loss_cls + 2.0 * loss_box + 0.2 * loss_dir)) < 1e-5


def _hand_case():
    """Two classes, four decoded anchors: two overlapping cars, a pedestrian apart, one below threshold."""
    cfg = PointPillarsConfig(**{**TINY, "class_names": ["Car", "Pedestrian"],
                                "anchor_generator_config": TINY["anchor_generator_config"] + [
                                    {**TINY["anchor_generator_config"][0], "class_name": "Pedestrian"}]})
    boxes = torch.tensor([[[1.0, 0, 0, 4, 2, 1.5, 0], [1.2, 0, 0, 4, 2, 1.5, 0], [10, 0, 0, 4, 2, 1.5, 0],
                           [20, 0, 0, 1, 1, 1, 0]]])
    logit = lambda p: math.log(p / (1 - p))  # noqa: E731
    cls = torch.tensor([[[logit(0.9), logit(0.2)], [logit(0.95), logit(0.1)], [logit(0.05), logit(0.3)],
                         [logit(0.01), logit(0.09)]]])
    return cfg, boxes, cls


def test_postprocess_threshold_and_nms():
    cfg, boxes, cls = _hand_case()
    out = postprocess(cls, boxes, cfg)[0]
    # box 1 (0.95) suppresses box 0 (IoU > 0.01); box 2 is a Pedestrian at 0.3; box 3 is below 0.1
    assert out["labels"].tolist() == [1, 2] and torch.allclose(out["scores"], torch.tensor([0.95, 0.3]))
    assert torch.equal(out["boxes"], boxes[0, [1, 2]])
    multi = postprocess(cls, boxes, PointPillarsConfig(**{**cfg.to_dict(), "multi_classes_nms": True}))[0]
    # per class, on each class's own scores: Car keeps box 1 (0.95; box 0 suppressed); Pedestrian keeps box 2
    # (0.3) and box 0 (0.2, apart from box 2) and suppresses box 1 (0.1, overlapping box 0)
    assert multi["labels"].tolist() == [1, 2, 2]
    assert torch.allclose(multi["scores"], torch.tensor([0.95, 0.3, 0.2]))
    assert torch.equal(multi["boxes"], boxes[0, [1, 2, 0]])


@pytest.mark.parametrize("multi", [False, True])
@pytest.mark.parametrize("direction", [True, False])
def test_cpu_postprocess_decodes_only_the_anchors_above_the_threshold(multi, direction, monkeypatch):
    """On the CPU, PointPillars.postprocess decodes only the anchors with a class at or above the score threshold:
    the detections of decoding every anchor (scores and labels bit for bit), per frame of a batch (one frame with
    nothing above), per class or not, with and without the direction classifier; a box out of range above the
    threshold raises the same error."""
    cfg = {**TINY, "class_names": ["Car", "Pedestrian"], "multi_classes_nms": multi, "score_thresh": 0.45,
           "nms_thresh": 0.1, "use_direction_classifier": direction,
           "anchor_generator_config": TINY["anchor_generator_config"] + [
               {**TINY["anchor_generator_config"][0], "class_name": "Pedestrian", "anchor_sizes": [[0.8, 0.6, 1.7]]}]}
    torch.manual_seed(3)
    model = PointPillars(cfg).eval()
    head = model.dense_head
    g = torch.Generator().manual_seed(4)
    frames = [torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
              for n in (300, 80, 5)]
    with torch.no_grad():
        head.conv_box.bias.normal_(0, 0.3, generator=g)
        raw = model(_batch(frames))
        # logits around -1.2: some anchors above 0.45 (logit -0.2), most below
        raw["cls_preds"].copy_(torch.randn(raw["cls_preds"].shape, generator=g) - 1.2)
    B, A = 3, head.anchors_flat.shape[0]
    scores = torch.sigmoid(raw["cls_preds"].view(B, A, -1))
    above = (scores >= 0.45).any(-1)
    assert 0 < int(above[0].sum()) < A // 2, "some anchors above the threshold, most below"
    with torch.no_grad():  # a frame with no anchor above the threshold
        raw["cls_preds"][2] = -1.0
    asked = []
    decode_rows = head._decode_rows
    monkeypatch.setattr(head, "_decode_rows",
                        lambda p, b, anchors: asked.append((b, anchors)) or decode_rows(p, b, anchors))
    with torch.no_grad():
        got = model.postprocess(raw)
        want = postprocess(*head.decode(raw), model.config)
    for b in range(B):
        assert torch.equal(got[b]["labels"], want[b]["labels"]) and torch.equal(got[b]["scores"], want[b]["scores"]), b
        assert torch.allclose(got[b]["boxes"], want[b]["boxes"], rtol=1e-6, atol=1e-6), b
    assert sum(len(w["labels"]) for w in want) > 0 and len(want[2]["labels"]) == 0
    assert {b for b, _ in asked} >= {0, 1}  # frames with anchors above the threshold decode them here
    for b, anchors in asked:  # only anchors above the threshold were decoded
        assert bool(above[b, anchors].all()) and anchors.numel() <= int(above[b].sum()) * (2 if multi else 1), b
    with torch.no_grad():
        raw["box_preds"][0].view(A, -1)[above[0].nonzero()[0, 0], 3:6] = 80.0  # exp(80): beyond every size
        with pytest.raises(ValueError, match="boxes must hold"):
            postprocess(*head.decode(raw), model.config)
        with pytest.raises(ValueError, match="boxes must hold"):
            model.postprocess(raw)


def _assert_padded_equals(padded: dict, eager: list[dict], what: str) -> None:
    for b, want in enumerate(eager):
        n = int(padded["count"][b])
        assert n == want["scores"].numel(), f"{what} frame {b}: {n} boxes, eager {want['scores'].numel()}"
        assert torch.equal(padded["labels"][b, :n], want["labels"]), what
        assert torch.equal(padded["scores"][b, :n], want["scores"]), what
        assert torch.equal(padded["boxes"][b, :n], want["boxes"]), what
        assert not padded["labels"][b, n:].any() and not padded["boxes"][b, n:].any(), f"{what}: padding rows"


@pytest.mark.parametrize("multi", [False, True])
@pytest.mark.parametrize("pre,post", [(4096, 500), (30, 8), (5, 500)])
def test_postprocess_padded_equals_postprocess(device, multi, pre, post):
    """Random decoded anchors of 2 frames and 3 classes, with tied scores (logits on a coarse grid) and
    boxes clustered so NMS suppresses: the fixed-size post-processing keeps postprocess's boxes, in its order."""
    cfg = PointPillarsConfig(**{**TINY, "multi_classes_nms": multi, "nms_pre_maxsize": pre, "nms_post_maxsize": post,
                                "nms_thresh": 0.1})
    g = torch.Generator().manual_seed(pre + post + multi)
    B, A, C = 2, 300, 3
    cls = ((torch.randn(B, A, C, generator=g) * 2 - 1) * 4).round() / 4
    boxes = torch.cat([torch.rand(B, A, 2, generator=g) * 12, torch.zeros(B, A, 1),
                       1 + torch.rand(B, A, 3, generator=g) * 3, torch.rand(B, A, 1, generator=g) * 6], -1)
    cls, boxes = cls.to(device), boxes.to(device)
    eager = postprocess(cls, boxes, cfg)
    assert all(0 < e["scores"].numel() for e in eager)
    padded = postprocess_padded(cls, boxes, cfg)
    k = min(A, pre, post) * (C if multi else 1)
    assert padded["boxes"].shape == (B, k, 7) and padded["count"].shape == (B,)
    _assert_padded_equals(padded, eager, f"multi={multi} pre={pre} post={post}")


def test_postprocess_padded_hand_case():
    """The hand-made case of test_postprocess_threshold_and_nms through the padded path."""
    cfg, boxes, cls = _hand_case()
    out = postprocess_padded(cls, boxes, cfg)
    assert int(out["count"][0]) == 2 and out["labels"][0].tolist() == [1, 2, 0, 0]
    multi = postprocess_padded(cls, boxes, PointPillarsConfig(**{**cfg.to_dict(), "multi_classes_nms": True}))
    assert int(multi["count"][0]) == 3 and multi["labels"][0, :3].tolist() == [1, 2, 2]
    assert torch.equal(multi["boxes"][0, :3], boxes[0, [1, 2, 0]])


def _batch(points_per_frame: list[torch.Tensor], gt: list[list[list[float]]] | None = None) -> dict:
    pts = [torch.cat([torch.full((p.shape[0], 1), float(i)), p], 1) for i, p in enumerate(points_per_frame)]
    batch = {"points": torch.cat(pts) if pts else torch.zeros(0, 5), "batch_size": len(points_per_frame)}
    if gt is not None:
        m = max(1, max(len(g) for g in gt))
        boxes = torch.zeros(len(gt), m, 8)
        for i, g in enumerate(gt):
            if g:
                boxes[i, :len(g)] = torch.tensor(g)
        batch["gt_boxes"] = boxes
    return batch


def test_empty_and_out_of_range_clouds():
    torch.manual_seed(0)
    model = PointPillars(TINY)
    far = torch.tensor([[100.0, 100.0, 0.0, 0.5], [-5.0, 0.0, 0.0, 0.1]])
    for clouds in ([torch.zeros(0, 4)], [far], [far, far]):
        preds = model.predict(_batch(clouds))
        assert len(preds) == len(clouds) and all(p["boxes"].shape == (0, 7) for p in preds)
    # an empty scan is a batch of its own: inside a batch, a frame without points is refused by index
    with pytest.raises(ValueError, match=r"names no point of frame\(s\) \[0\] of batch\['batch_size'\]=2"):
        model.predict(_batch([torch.zeros(0, 4), far]))
    model.train()
    out = model(_batch([far, far], gt=[[], [[3.0, 0.0, -1.0, 2.0, 1.0, 1.5, 0.0, 1.0]]]))
    assert torch.isfinite(out["loss"]) and out["loss"].requires_grad


def test_bad_batches_raise():
    model = PointPillars(TINY)
    with pytest.raises(ValueError, match="batch must be a dict"):
        model([1, 2])
    with pytest.raises(ValueError, match=r"batch\['points'\] must be a floating \(P, 1 \+ 4\)"):
        model({"points": torch.zeros(5, 3), "batch_size": 1})
    with pytest.raises(ValueError, match="batch_size"):
        model({"points": torch.zeros(5, 5), "batch_size": 0})
    with pytest.raises(ValueError, match=r"gt_boxes'\] must be \(batch_size=1, M, 8\)"):
        model.train()({"points": torch.zeros(5, 5), "batch_size": 1, "gt_boxes": torch.zeros(1, 2, 7)})


def _points(n: int = 50, frames: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    p = torch.rand(n, 5, generator=g) * torch.tensor([0.0, 60.0, 60.0, 3.0, 1.0]) - torch.tensor([0.0, 0.0, 30.0, 2.0, 0.0])
    p[:, 0] = torch.arange(n) % frames
    return p


@pytest.mark.parametrize("frame, why", [(3.0, "beyond batch_size"), (0.5, "fractional"), (-1.0, "negative"),
                                        (math.nan, "NaN")])
def test_points_of_no_frame_raise(frame, why):
    """A point whose frame index names no frame of the batch was silently left out of every frame."""
    points = _points()
    points[7, 0] = frame
    with pytest.raises(ValueError, match=r"batch\['points'\]\[:, 0\] \(frame index\) must be an integer in \[0, 1\).*row 7"):
        PointPillars(TINY).eval()({"points": points, "batch_size": 1})


@pytest.mark.parametrize("value", [math.nan, math.inf, 1e30])
def test_invalid_intensity_raises_before_it_poisons_a_pillar(value):
    points = _points()
    points[3, 4] = value
    with pytest.raises(ValueError, match=r"batch\['points'\]\[:, 4:\].*first row 3"):
        PointPillars(TINY).predict({"points": points, "batch_size": 1})
    points[3, 1:4] = math.nan  # a no-return beam (NaN x, y, z) is outside the range: left out, as voxelize does
    points[3, 4] = 0.0
    assert len(PointPillars(TINY).predict({"points": points, "batch_size": 1})) == 1


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_other_float_dtypes_run_in_the_weights_dtype(dtype):
    model = PointPillars(TINY).eval()
    points = _points(200, frames=2)
    want = model({"points": points, "batch_size": 2})
    got = model({"points": points.to(dtype), "batch_size": 2})
    exact = points.to(dtype).float()
    want = model({"points": exact, "batch_size": 2})  # the same float32 values
    for k in want:
        assert torch.equal(got[k], want[k]), k


def test_gt_boxes_of_a_class_must_be_real_boxes():
    model = PointPillars(TINY).train()
    for bad in ([math.nan] * 7, [10.0, 0.0, -1.0, -3.9, 1.6, 1.5, 0.0], [10.0, 0.0, -1.0, 3.9, 0.0, 1.5, 0.0],
                [10.0, 0.0, -1.0, 3.9, 1.6, 1.5, math.inf]):
        gt = torch.tensor([[bad + [1.0], [0.0] * 8]])
        with pytest.raises(ValueError, match=r"batch\['gt_boxes'\] rows with a class must hold finite boxes"):
            model({"points": _points(), "batch_size": 1, "gt_boxes": gt})
    pad = torch.tensor([[[math.nan] * 7 + [0.0]]] * 2)  # class 0 rows are padding: never read
    assert torch.isfinite(model({"points": _points(frames=2), "batch_size": 2, "gt_boxes": pad})["loss"])


def test_checkpoint_of_another_config_names_the_keys(tmp_path):
    three = PointPillars()
    all_classes = PointPillars(load_config("configs/pointpillars/pointpillars_synth_all.yaml"))
    torch.save({"model_state": all_classes.state_dict()}, tmp_path / "eight.pth")
    with pytest.raises(CheckpointError, match=r"shape mismatch.*dense_head\.conv_cls\.weight"):
        PointPillars.from_checkpoint(tmp_path / "eight.pth", config=three.config)
    state = three.state_dict()
    del state["vfe.pfn_layers.0.norm.weight"]
    state["extra.weight"] = torch.zeros(1)
    with pytest.raises(CheckpointError, match=r"missing \(1\): vfe\.pfn_layers\.0\.norm\.weight.*unexpected"):
        three.load_weights(state)
    # an OpenPCDet-style checkpoint of the right config loads strictly and gives the same outputs
    torch.save({"model_state": three.state_dict(), "epoch": 80}, tmp_path / "pcdet.pth")
    again = PointPillars.from_checkpoint(tmp_path / "pcdet.pth", config="configs/pointpillars/pointpillars_kitti.yaml")
    assert all(torch.equal(a, b) for a, b in zip(three.state_dict().values(), again.state_dict().values()))


def test_openpcdet_train_py_checkpoint_loads(tmp_path):
    """OpenPCDet's train.py saves its one-cycle learning rates and betas as numpy.float64 in optimizer_state:
    safe loading must accept those (and only data: an object that would run code is still refused)."""
    model = PointPillars(TINY)
    optimizer = {"state": {}, "param_groups": [{"lr": np.float64(7.5e-4), "betas": (np.float64(0.925), 0.99),
                                                "step": np.int64(3), "params": [0]}]}
    torch.save({"epoch": 2, "it": 40, "model_state": model.state_dict(), "optimizer_state": optimizer,
                "version": "pcdet+0.6.0"}, tmp_path / "checkpoint_epoch_2.pth")
    again = PointPillars.from_checkpoint(tmp_path / "checkpoint_epoch_2.pth", config=TINY)
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), again.state_dict().values()))
    torch.save({"model_state": model.state_dict(), "note": math.gcd}, tmp_path / "code.pth")  # a function
    with pytest.raises(CheckpointError, match="safe loading refuses"):
        PointPillars.from_checkpoint(tmp_path / "code.pth", config=TINY)


def test_openpcdet_yaml_with_base_config(tmp_path):
    """OpenPCDet's layout: tools/cfgs/kitti_models/pointpillar.yaml naming its base relative to tools/."""
    import shutil
    cfgs = tmp_path / "tools" / "cfgs"
    (cfgs / "dataset_configs").mkdir(parents=True)
    (cfgs / "kitti_models").mkdir()
    shutil.copy("configs/datasets/kitti.yaml", cfgs / "dataset_configs" / "kitti_dataset.yaml")
    text = open("configs/pointpillars/pointpillars_kitti.yaml").read().replace("_BASE_CONFIG_: datasets/kitti.yaml",
                                                                  "_BASE_CONFIG_: cfgs/dataset_configs/kitti_dataset.yaml")
    (cfgs / "kitti_models" / "pointpillar.yaml").write_text(text)
    cfg = load_config(cfgs / "kitti_models" / "pointpillar.yaml")
    assert cfg["DATA_CONFIG"]["FOV_POINTS_ONLY"] is True  # from the base
    assert cfg["DATA_CONFIG"]["POINT_CLOUD_RANGE"] == [0, -39.68, -3, 69.12, 39.68, 1]  # overridden
    assert PointPillarsConfig.from_openpcdet(cfg) == PointPillarsConfig()
    (cfgs / "kitti_models" / "bad.yaml").write_text(text.replace("dataset_configs/kitti_dataset", "nowhere/x"))
    with pytest.raises(ConfigError, match="_BASE_CONFIG_ 'cfgs/nowhere/x.yaml' not found"):
        load_config(cfgs / "kitti_models" / "bad.yaml")


@pytest.mark.parametrize("key,value,pattern", [
    ("VFE", {"NAME": "DynamicPillarVFE"}, "MODEL.VFE.NAME = 'DynamicPillarVFE' is not supported"),
    ("DENSE_HEAD", {"NAME": "AnchorHeadMulti"}, "MODEL.DENSE_HEAD.NAME"),
])
def test_unsupported_openpcdet_options(key, value, pattern):
    cfg = load_config("configs/pointpillars/pointpillars_kitti.yaml")
    cfg["MODEL"][key] = {**cfg["MODEL"][key], **value}
    with pytest.raises(ConfigError, match=pattern):
        PointPillarsConfig.from_openpcdet(cfg)


def test_config_round_trip_and_checks():
    cfg = PointPillarsConfig.from_openpcdet(load_config("configs/pointpillars/pointpillars_synth_all.yaml"))
    assert PointPillarsConfig.from_dict(cfg.to_dict()) == cfg
    assert not cfg.match_height
    yaml = load_config("configs/pointpillars/pointpillars_kitti.yaml")
    yaml["MODEL"]["DENSE_HEAD"]["TARGET_ASSIGNER_CONFIG"]["MATCH_HEIGHT"] = True
    height = PointPillarsConfig.from_openpcdet(yaml)
    assert height.match_height and PointPillarsConfig.from_dict(height.to_dict()) == height
    assert PointPillars(height).dense_head.target_assigner.match_height
    with pytest.raises(ConfigError, match="MATCH_HEIGHT"):
        PointPillarsConfig(match_height="yes")
    assert len(cfg.class_names) == 8
    with pytest.raises(ConfigError, match="whole number of VOXEL_SIZE cells"):
        PointPillarsConfig(voxel_size=[0.17, 0.16, 4.0])
    with pytest.raises(ConfigError, match="one entry per class"):
        PointPillarsConfig(class_names=["Car"])


class _Network(torch.nn.Module):
    """PointPillars' exportable part: pillars -> the head's three outputs."""

    def __init__(self, m):
        super().__init__()
        self.m = m

    def forward(self, voxels, num_points, coords):
        out = self.m.network(voxels, num_points, coords, 1)
        return out["cls_preds"], out["box_preds"], out["dir_cls_preds"]


def _pillars_of(model, n, seed):
    pts = torch.rand(n, 4, generator=torch.Generator().manual_seed(seed)) * torch.tensor([8.0, 8.0, 4.0, 1.0]) \
        + torch.tensor([0, -4.0, -3, 0])
    return model.voxelize(torch.cat([torch.zeros(n, 1), pts], 1), 1)


def test_torch_export_of_the_network():
    torch.manual_seed(0)
    model = PointPillars(TINY).eval()
    pts = torch.tensor([[1.5, -2.5, -1.0, 0.3], [1.2, -2.1, -0.5, 0.1], [6.5, 3.5, 0.0, 0.9]])
    voxels, num_points, coords = model.voxelize(torch.cat([torch.zeros(3, 1), pts], 1), 1)
    ep = torch.export.export(_Network(model), (voxels, num_points, coords))
    for a, b in zip(ep.module()(voxels, num_points, coords), _Network(model)(voxels, num_points, coords)):
        assert torch.allclose(a, b, atol=1e-6)


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_onnx_export_of_the_network(tmp_path):
    """ONNX (torch.onnx's dynamo exporter) of the network with a dynamic number of pillars, run in
    onnxruntime on frames with other pillar counts than the exported one."""
    pytest.importorskip("onnxscript")
    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    model = PointPillars(TINY).eval()
    net = _Network(model)
    program = torch.onnx.export(net, _pillars_of(model, 300, 0), dynamo=True, verbose=False,
                                dynamic_shapes=({0: "pillars"}, {0: "pillars"}, {0: "pillars"}))
    program.save(str(tmp_path / "pointpillars.onnx"))
    session = ort.InferenceSession(str(tmp_path / "pointpillars.onnx"))
    counts = set()
    for n, seed in ((300, 1), (40, 2)):
        inputs = _pillars_of(model, n, seed)
        counts.add(inputs[0].shape[0])
        got = session.run(None, {i.name: x.numpy() for i, x in zip(session.get_inputs(), inputs)})
        for g, want in zip(got, net(*inputs)):
            assert g.shape == tuple(want.shape)
            assert torch.allclose(torch.from_numpy(g), want, atol=1e-5)
    assert len(counts) == 2


def test_sparse_backbone_mode_runs():
    torch.manual_seed(0)
    dense = PointPillars(TINY).eval()
    sparse = PointPillars({**TINY, "backbone_mode": "sparse"}).eval()
    sparse.load_weights(dense.state_dict())
    batch = _batch([torch.tensor([[1.5, -2.5, -1.0, 0.3], [6.5, 3.5, 0.0, 0.9]])])
    with torch.no_grad():
        a, b = dense(batch), sparse(batch)
    assert all(a[k].shape == b[k].shape for k in a)


def test_sparse_mode_trains_under_autocast():
    """The trainer's --amp: the sparse backbone under bfloat16 autocast gives the float32 loss to bfloat16's
    precision and gradients for every backbone weight (its convolutions once refused float32 weights with
    bfloat16 features)."""
    torch.manual_seed(0)
    model = PointPillars({**TINY, "backbone_mode": "sparse"}).train()
    g = torch.Generator().manual_seed(3)
    clouds = [torch.rand(300, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
              for _ in range(2)]
    batch = _batch(clouds, [[[3.0, 0.0, -1.0, 2.0, 1.0, 1.5, 0.3, 1.0]], []])
    state = {k: v.clone() for k, v in model.state_dict().items()}
    ref = model(batch)["loss"].item()
    model.load_state_dict(state)  # BatchNorm's running statistics moved: start again from the same state
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = model(batch)["loss"]
    assert abs(loss.item() - ref) <= 0.03 * abs(ref), (loss.item(), ref)
    loss.backward()
    for name, p in model.backbone_2d.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def _synthetic_frames(n: int):
    from lidarops.data.synthetic import SyntheticFrames

    frames = SyntheticFrames("driving_city", num_frames=n, seed=5, object_counts={"Car": 8, "Pedestrian": 0,
                                                                                   "Cyclist": 0})
    out = []
    for i in range(n):
        f = frames[i]
        keep = (f.labels == 0) & (f.num_points_in_box >= 20)
        out.append((torch.from_numpy(f.points), torch.from_numpy(f.boxes[keep])))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["dense", "sparse"])
def test_overfit_a_few_frames(mode):
    """A narrow PointPillars on 2 simulated frames: the loss falls and the cars come back (BEV IoU > 0.5),
    with either backbone (the sparse one trained as such)."""
    cfg = dict(TINY, backbone_mode=mode, point_cloud_range=[0.0, -20.48, -3.0, 40.96, 20.48, 1.0], voxel_size=[0.32, 0.32, 4.0],
               vfe_num_filters=[32], num_filters=[32, 32, 64], num_upsample_filters=[32, 32, 32],
               anchor_generator_config=[{**TINY["anchor_generator_config"][0], "anchor_sizes": [[3.9, 1.6, 1.56]],
                                         "align_center": False}])
    torch.manual_seed(0)
    model = PointPillars(cfg)
    data = _synthetic_frames(2)
    lo, hi = torch.tensor(cfg["point_cloud_range"][:3]), torch.tensor(cfg["point_cloud_range"][3:])
    clouds, gts = [], []
    for pts, boxes in data:
        clouds.append(pts[((pts[:, :3] >= lo) & (pts[:, :3] < hi)).all(1)])
        inside = ((boxes[:, :2] >= lo[:2] + 2) & (boxes[:, :2] < hi[:2] - 2)).all(1)
        gts.append(torch.cat([boxes[inside], torch.ones(int(inside.sum()), 1)], 1).tolist())
    assert sum(len(g) for g in gts) >= 4
    batch = _batch(clouds, gts)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    model.train()
    losses = []
    for _ in range(120):
        out = model(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(out["loss"].item())
    assert np.mean(losses[-10:]) < 0.2 * np.mean(losses[:5]), losses[::20]
    # BatchNorm's running statistics (momentum 0.01) lag 120 steps behind: take this batch's statistics
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None
    with torch.no_grad():
        model(batch)
    import lidarops

    for pred, gt in zip(model.predict(batch), gts):
        gt = torch.tensor(gt)[:, :7]
        iou = lidarops.box_iou_bev(gt, pred["boxes"].float())
        assert (iou.amax(1) > 0.5).float().mean() >= 0.75, iou.amax(1)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("mode", ["dense", "sparse"])
def test_cuda_matches_cpu(mode):
    """The whole model on CUDA against CPU: head outputs to float tolerance, losses, and detections."""
    torch.manual_seed(0)
    model = PointPillars(dict(TINY, backbone_mode=mode)).eval()
    g = torch.Generator().manual_seed(3)
    clouds = [torch.rand(300, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
              for _ in range(2)]
    batch = _batch(clouds, [[[3.0, 0.0, -1.0, 2.0, 1.0, 1.5, 0.3, 1.0]], []])
    cuda_batch = {k: v.cuda() if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
    with torch.no_grad():
        cpu, gpu = model(batch), model.cuda()(cuda_batch)
        for k in cpu:
            assert torch.allclose(cpu[k], gpu[k].cpu(), atol=1e-4, rtol=1e-4), k
        model.cpu().train()
        loss_cpu = model(batch)
        loss_gpu = model.cuda()(cuda_batch)
        for k in ("loss_cls", "loss_box", "loss_dir"):
            assert abs(loss_cpu[k].item() - loss_gpu[k].item()) < 1e-4 * max(1.0, abs(loss_cpu[k].item())), k
        model.eval()
        cls_gpu, boxes_gpu = model.dense_head.decode(model(cuda_batch))
        cls_cpu, boxes_cpu = model.cpu().dense_head.decode(model(batch))
    assert torch.allclose(cls_cpu, cls_gpu.cpu(), atol=1e-4) and torch.allclose(boxes_cpu, boxes_gpu.cpu(), atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_padded_network_captures_in_a_cuda_graph():
    """Padded voxelization, the dense network and the decode record into one CUDA graph (no host copy
    or read inside) and its replay on a new frame equals the eager call on that frame."""
    from lidarops.ops.voxelize import voxelize

    torch.manual_seed(0)
    model = PointPillars(TINY).cuda().eval()
    cfg = model.config
    g = torch.Generator().manual_seed(5)
    frames = [(torch.rand(400, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
               + torch.tensor([0, -4.0, -3, 0])).cuda() for _ in range(2)]
    static = frames[0].clone()

    def body(points):
        with torch.no_grad(), lidarops.validation(False):
            v, c, n = voxelize(points, cfg.voxel_size, cfg.point_cloud_range, cfg.max_points_per_voxel,
                               cfg.max_voxels_test, overflow="drop", padded=True)
            coords = torch.cat([(c[:, :1] >= 0).to(c.dtype) - 1, c], 1)  # frame 0, padding rows -1
            return model.dense_head.decode(model.network(v, n, coords, 1))

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        body(static)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = body(static)
    static.copy_(frames[1])
    graph.replay()
    want = body(frames[1])
    for got, ref in zip(out, want):
        assert torch.allclose(got, ref, atol=1e-5, rtol=1e-5)


def _same_as_predict(model, frame, det, what: str) -> int:
    """Asserts ``det`` holds the detections of the eager ``model.predict`` on ``frame`` alone; returns how many."""
    from lidarops.models.pointpillars import eager_predict

    with eager_predict():
        want = model.predict({"points": F.pad(frame, (1, 0)), "batch_size": 1})[0]
    assert det["labels"].tolist() == want["labels"].tolist(), what
    assert torch.allclose(det["scores"], want["scores"], atol=1e-5), what
    assert torch.allclose(det["boxes"], want["boxes"], atol=1e-4), what
    return len(want["labels"])


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_graphed_pointpillars_equals_predict():
    """The whole inference (voxelization to NMS) replayed as one CUDA graph gives predict's detections on
    frames of other sizes, an empty one included; bad frames get the eager call's errors."""
    from lidarops.models.cuda_graph import GraphedPointPillars

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda().eval()
    with torch.no_grad():  # scores around 0.5 instead of the prior's 0.01, so that boxes pass 0.3
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(7)
    frames = [(torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
               + torch.tensor([0, -4.0, -3, 0])).cuda() for n in (400, 1000, 0, 37)]
    graphed = GraphedPointPillars(model, capacity=1000)
    kept = 0
    for i, f in enumerate(frames):
        kept += _same_as_predict(model, f, graphed(f), f"frame {i}")
    assert kept > 0, "the case must keep boxes"
    with pytest.raises(ValueError, match="more than capacity=1000"):
        graphed(torch.zeros(1001, 4, device="cuda"))
    bad = frames[0].clone()
    bad[3, 3] = float("nan")
    with pytest.raises(ValueError, match="intensity"):
        graphed(bad)
    with pytest.raises(ValueError, match="backbone_mode='dense'"):
        GraphedPointPillars(PointPillars({**TINY, "backbone_mode": "sparse"}).cuda())


def _same_detections(got: list[dict], want: list[dict], what: str) -> int:
    assert len(got) == len(want), what
    for b, (d, w) in enumerate(zip(got, want)):
        assert d["labels"].tolist() == w["labels"].tolist(), f"{what}, frame {b}"
        assert torch.allclose(d["scores"], w["scores"], atol=1e-5), f"{what}, frame {b}"
        assert torch.allclose(d["boxes"], w["boxes"], atol=1e-4), f"{what}, frame {b}"
    return sum(len(w["labels"]) for w in want)


def test_inference_copy_merges_the_anchor_heads_convolutions():
    """The optimized copy of a PointPillars folds BatchNorm, runs the head's class, box and direction
    convolutions as one reading the upsampled maps one by one: its raw outputs equal the model's (float64 to
    1e-10), the model keeps its modules and weights, and the copy's detections are the model's."""
    from lidarops.models.cuda_graph import inference_copy

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.2}).double().eval()
    with torch.no_grad():  # BatchNorm statistics and head biases away from their initial values
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
        for conv in (model.dense_head.conv_cls, model.dense_head.conv_box, model.dense_head.conv_dir_cls):
            conv.bias.uniform_(-1.0, 1.0)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = inference_copy(model)
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())
    assert type(model.dense_head).__name__ == "AnchorHeadSingle" and not model.map_to_bev.channels_last
    assert fast.map_to_bev.channels_last
    assert fast.dense_head.merged.whole.out_channels == sum(
        c.out_channels for c in (model.dense_head.conv_cls, model.dense_head.conv_box, model.dense_head.conv_dir_cls))
    # no padded copies, no 1 x 1 transposed convolution, every convolution's ReLU taken into it
    kinds = [type(m).__name__ for m in fast.backbone_2d.modules()]
    assert "ZeroPad2d" not in kinds and "ReLU" in kinds and kinds.count("_ConvReLU") == sum(
        isinstance(m, torch.nn.Conv2d) or (isinstance(m, torch.nn.ConvTranspose2d) and m.kernel_size == (1, 1))
        for m in model.backbone_2d.modules())
    assert all(d[0].kernel_size != (1, 1) for d in fast.backbone_2d.inner.deblocks
               if isinstance(d[0], torch.nn.ConvTranspose2d))
    g = torch.Generator().manual_seed(3)
    points = torch.rand(800, 4, generator=g, dtype=torch.float64) * torch.tensor([8.0, 8.0, 4.0, 1.0],
                                                                                  dtype=torch.float64)
    points += torch.tensor([0, -4.0, -3, 0], dtype=torch.float64)
    batch = {"points": F.pad(points, (1, 0)), "batch_size": 1}
    with torch.no_grad():
        raw = model.network(*model.voxelize(batch["points"], 1), 1)
        raw_fast = fast.network(*fast.voxelize(batch["points"], 1), 1)
        assert raw.keys() == raw_fast.keys() == {"cls_preds", "box_preds", "dir_cls_preds"}
        for k in raw:
            assert raw[k].shape == raw_fast[k].shape and raw_fast[k].is_contiguous()
            torch.testing.assert_close(raw_fast[k], raw[k], rtol=0, atol=1e-10)
        kept = _same_detections(fast.predict(batch), model.predict(batch), "the optimized copy")
    assert kept > 0, "the case must keep boxes"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_inference_copys_conv_relu_is_one_cudnn_call_in_half_precision(dtype, monkeypatch):
    """The optimized copy's convolution + ReLU on CUDA: one cuDNN call in float16 / bfloat16 (under autocast or on
    half weights), equal to the float64 convolution then ReLU to the precision's rounding; the two modules' calls
    in float32 and where autograd needs the result (its gradient is the reference's)."""
    import copy

    from lidarops.models.cuda_graph import _ConvReLU

    calls = []
    fused_op = torch.cudnn_convolution_relu
    monkeypatch.setattr(torch, "cudnn_convolution_relu", lambda *a: calls.append(1) or fused_op(*a))
    torch.manual_seed(0)
    tol = {torch.float16: 2e-3, torch.bfloat16: 1.6e-2}[dtype]
    for k, stride, pad, bias in ((3, 1, 1, True), (3, 2, 1, True), (1, 1, 0, False), (3, 1, 0, True)):
        conv = torch.nn.Conv2d(32, 48, k, stride=stride, padding=pad, bias=bias).cuda()
        x = torch.randn(2, 32, 21, 18, device="cuda").contiguous(memory_format=torch.channels_last)
        with torch.no_grad():
            want = torch.relu(F.conv2d(x.double(), conv.weight.double(),
                                       None if conv.bias is None else conv.bias.double(), stride, pad))
        scale = float(want.abs().max())
        fused = _ConvReLU(conv)
        with torch.no_grad(), torch.autocast("cuda", dtype):
            got = fused(x)
        assert len(calls) == 1 and got.dtype == dtype and got.shape == want.shape
        assert float((got.double() - want).abs().max()) <= tol * scale
        with torch.no_grad():
            got = _ConvReLU(copy.deepcopy(conv).to(dtype))(x.to(dtype))
        assert len(calls) == 2 and got.dtype == dtype
        assert float((got.double() - want).abs().max()) <= tol * scale
        with torch.no_grad():
            got = fused(x)  # float32: conv then relu (TF32 as torch's settings say)
        assert len(calls) == 2 and got.dtype == torch.float32
        xg = x.clone().requires_grad_()
        with torch.autocast("cuda", dtype):
            fused(xg).float().sum().backward()  # autograd needs the result: the two calls
        xr = x.clone().requires_grad_()
        with torch.autocast("cuda", dtype):
            torch.relu(conv(xr)).float().sum().backward()
        assert len(calls) == 2 and torch.equal(xg.grad, xr.grad)
        calls.clear()


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_predict_replays_a_cuda_graph_from_the_second_call():
    """predict on CUDA: the first call of a size runs eagerly, the next ones replay a recorded graph, with the eager
    call's detections (one frame and three), results that outlive the next call, weights updated in place seen, the
    train/eval mode kept, a new graph for other TF32 settings and inside inference mode, under autocast a graph of
    the optimized copy (made again after an in-place update), and the eager call's errors for a bad intensity, a
    bad frame index and boxes the NMS refuses."""
    from lidarops.models.cuda_graph import inference_copy
    from lidarops.models.pointpillars import eager_predict

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(7)
    frames = [(torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
               + torch.tensor([0, -4.0, -3, 0])).cuda() for n in (400, 1000, 37, 999)]
    one = lambda f: {"points": F.pad(f, (1, 0)), "batch_size": 1}  # noqa: E731
    three = {"points": torch.cat([F.pad(f, (1, 0), value=float(b)) for b, f in enumerate(frames[:3])]),
             "batch_size": 3}

    def eager(batch):
        with eager_predict():
            return model.predict(batch)

    def eager_copy(batch):  # what predict's graph records under autocast, run eagerly
        with eager_predict():
            return inference_copy(model).predict(batch)

    graphs = lambda: model.__dict__["_predict_graphs"].graphs  # noqa: E731
    model.train()
    first = model.predict(one(frames[0]))
    assert model.training and not graphs(), "the first call of a size runs eagerly"
    kept = _same_detections(first, eager(one(frames[0])), "first call")
    second = model.predict(one(frames[1]))
    assert model.training and len(graphs()) == 1, "the second call records a graph"
    kept += _same_detections(second, eager(one(frames[1])), "second call")
    for i, f in enumerate(frames):
        kept += _same_detections(model.predict(one(f)), eager(one(f)), f"replay {i}")
    _same_detections(second, eager(one(frames[1])), "a result after later replays")
    assert kept > 0, "the case must keep boxes"
    model.predict(three)
    _same_detections(model.predict(three), eager(three), "three frames")
    assert len(graphs()) == 2
    with torch.no_grad():  # in place: the replays read the new weights
        model.dense_head.conv_cls.bias.add_(0.4)
        model.dense_head.conv_box.weight.mul_(1.1)
    _same_detections(model.predict(one(frames[1])), eager(one(frames[1])), "weights updated in place")
    old = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = not old
    try:
        for _ in range(2):
            got = model.predict(one(frames[1]))
        assert len(graphs()) == 3, "other TF32 settings: another graph"
    # (KEEP_GRAPHS is 3: the graphs below replace the least recently used)
        assert torch.allclose(got[0]["scores"], eager(one(frames[1]))[0]["scores"], atol=1e-2)
    finally:
        torch.backends.cudnn.allow_tf32 = old
    # under a user's autocast, the warm-up's cast weights must not enter the graph: the cache that holds them is
    # freed when the autocast ends, and the replays after it would read whatever took their memory. The graph
    # records an optimized copy (BatchNorm folded): the eager call's detections to half precision
    for _ in range(3):
        with torch.autocast("cuda", dtype=torch.float16):
            got = model.predict(one(frames[0]))
        junk = [torch.full((1 << 20,), float("nan"), device="cuda") for _ in range(8)]  # noqa: F841
    # (rounding apart, the copy's function is the model's: the copy run eagerly gives the graph's detections)
    assert next(reversed(graphs().values())).optimize, "autocast: the optimized copy"
    with torch.autocast("cuda", dtype=torch.float16):
        kept = _same_detections(got, eager_copy(one(frames[0])), "autocast")
    recorded = model.__dict__["_predict_graphs"].recorded
    with torch.no_grad():  # in place: the copy is made again
        model.dense_head.conv_cls.bias.add_(0.2)
    with torch.autocast("cuda", dtype=torch.float16):
        kept += _same_detections(model.predict(one(frames[0])), eager_copy(one(frames[0])),
                                 "autocast, weights updated in place")
    assert model.__dict__["_predict_graphs"].recorded == recorded + 1 and kept > 0
    two = {"points": torch.cat([F.pad(f, (1, 0), value=float(b)) for b, f in enumerate(frames[2:])]), "batch_size": 2}
    with torch.inference_mode():  # recorded there, replayed after it too
        for _ in range(2):
            got = model.predict(two)
    _same_detections(got, eager(two), "inference mode")
    _same_detections(model.predict(two), eager(two), "after inference mode")
    # the eager call's errors, through the graph
    for what, edit, match in (("intensity", lambda p: p[5, 4].fill_(float("nan")), "intensity"),
                              ("frame index", lambda p: p[5, 0].fill_(2.0), "frame index")):
        batch = one(frames[1])
        edit(batch["points"])
        with pytest.raises(ValueError, match=match) as from_eager:
            eager(batch)
        with pytest.raises(ValueError, match=match) as from_graph:
            model.predict(batch)
        assert str(from_graph.value) == str(from_eager.value), what
    with torch.no_grad():  # sizes of exp(60): boxes the NMS refuses
        model.dense_head.conv_box.bias[3:6].fill_(60.0)
    with pytest.raises(ValueError) as from_eager:
        eager(one(frames[1]))
    with pytest.raises(ValueError) as from_graph:
        model.predict(one(frames[1]))
    assert str(from_graph.value) == str(from_eager.value)
    with lidarops.validation(False):  # no checks: the eager call's result, whatever it is
        _same_detections(model.predict(one(frames[2])), eager(one(frames[2])), "value checks off")


def test_predict_graphs_are_not_copied_with_the_model(tmp_path):
    """A model's predict graphs record its own tensors: a copy or a pickled model starts without them; on the
    CPU predict records none."""
    import copy

    from lidarops.models.cuda_graph import _PredictGraphs

    model = PointPillars(TINY).eval()
    model._predict_graphs = _PredictGraphs()
    model._predict_graphs.graphs["key"] = "a graph"
    model._predict_graphs.recorded = 5
    for other in (copy.deepcopy(model), torch.load(_saved(model, tmp_path), weights_only=False)):
        assert not other._predict_graphs.graphs and other._predict_graphs.recorded == 0
    fresh = PointPillars(TINY).eval()
    fresh.predict({"points": F.pad(torch.rand(50, 4) * 4, (1, 0)), "batch_size": 1})
    assert "_predict_graphs" not in fresh.__dict__


def _bn_trained(model: PointPillars, seed: int) -> PointPillars:
    """BatchNorm statistics and affines away from the identity (what folding must get right), biases that put
    some anchors above the score threshold."""
    from helpers.models import randomize_bn

    randomize_bn(model.backbone_2d, seed)
    randomize_bn(model.vfe, seed + 1)
    with torch.no_grad():
        model.dense_head.conv_cls.bias.fill_(-0.3)
    return model.eval()


def _frames_batch(seed: int, sizes=(300, 120, 40)) -> dict:
    g = torch.Generator().manual_seed(seed)
    return _batch([torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
                   for n in sizes])


def _own_detections(model: PointPillars, batch: dict) -> list[dict]:
    """The model's own forward and post-processing, no inference copy."""
    with torch.no_grad():
        return model.postprocess(model(batch), batch)


def _close_detections(got: list[dict], want: list[dict], tol: float, what: str) -> int:
    for b, (g, w) in enumerate(zip(got, want, strict=True)):
        assert g["labels"].tolist() == w["labels"].tolist(), (what, b)
        assert torch.allclose(g["scores"], w["scores"], rtol=0, atol=tol), (what, b)
        assert torch.allclose(g["boxes"], w["boxes"], rtol=0, atol=tol * 10), (what, b)
    return sum(len(w["labels"]) for w in want)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_cpu_predict_runs_an_inference_copy_with_the_models_detections(dtype, tol):
    """On the CPU predict runs an inference copy (BatchNorm and padding folded, channels-last): the detections of
    the model's own forward and post-processing up to rounding, per frame of a batch; nothing for autograd."""
    model = _bn_trained(PointPillars(TINY), seed=6).to(dtype)
    batch = _frames_batch(7)
    batch["points"] = batch["points"].to(dtype)
    got = model.predict(batch)
    copy = model.__dict__["_predict_copy"].graphs["copy"][1]
    assert copy is not model and not any(isinstance(m, torch.nn.BatchNorm2d) for m in copy.backbone_2d.modules())
    assert _close_detections(got, _own_detections(model, batch), tol, str(dtype)) > 0
    assert not any(d["scores"].requires_grad or d["boxes"].requires_grad for d in got)
    assert model.predict(batch)[0]["scores"].tolist() == got[0]["scores"].tolist()
    assert model.__dict__["_predict_copy"].graphs["copy"][1] is copy  # kept while the model is unchanged


def test_cpu_predict_sees_every_change_of_the_model():
    """The inference copy is made again when the model changes: weights loaded in place, an in-place update of
    one parameter, BatchNorm statistics moved by a training forward, tensors replaced (``.double()``); each
    predict gives the changed model's own detections."""
    model = _bn_trained(PointPillars(TINY), seed=8)
    other = _bn_trained(PointPillars(TINY), seed=9)
    batch = _frames_batch(10)
    before = model.predict(batch)
    _close_detections(before, _own_detections(model, batch), 1e-5, "first")

    def copy():
        return model.__dict__["_predict_copy"].graphs["copy"][1]

    made = copy()
    model.load_state_dict(other.state_dict())
    after = model.predict(batch)
    assert copy() is not made
    assert _close_detections(after, _own_detections(other, batch), 1e-5, "loaded") > 0
    assert [d["scores"].tolist() for d in after] != [d["scores"].tolist() for d in before]
    for change in ("in place", "training forward", "double"):
        made = copy()
        if change == "in place":
            with torch.no_grad():
                model.dense_head.conv_box.bias[:3] += 0.5
        elif change == "training forward":
            model.train()
            with torch.no_grad():
                model({**batch, "gt_boxes": torch.zeros(3, 1, 8)})  # BatchNorm's running statistics move
            model.eval()
        else:
            model.double()
            batch["points"] = batch["points"].double()
        got = model.predict(batch)
        assert copy() is not made, change
        _close_detections(got, _own_detections(model, batch), 1e-5 if change != "double" else 1e-12, change)


def test_cpu_predict_copy_can_be_turned_off(monkeypatch):
    """PREDICT_CPU_COPY = False or eager_predict(): the model's own forward, bit for bit; a model made under
    inference_mode (no version counters to see an update by) runs itself too."""
    from lidarops.models import pointpillars as pp

    torch.manual_seed(0)
    model = _bn_trained(PointPillars(TINY), seed=11)
    batch = _frames_batch(12)
    want = _own_detections(model, batch)
    with pp.eager_predict():
        got = model.predict(batch)
    assert "_predict_copy" not in model.__dict__
    monkeypatch.setattr(pp, "PREDICT_CPU_COPY", False)
    for d in (got, model.predict(batch)):
        assert all(torch.equal(g[k], w[k]) for g, w in zip(d, want) for k in ("boxes", "scores", "labels"))
    assert "_predict_copy" not in model.__dict__
    monkeypatch.setattr(pp, "PREDICT_CPU_COPY", True)
    with torch.inference_mode():
        torch.manual_seed(0)
        frozen = _bn_trained(PointPillars(TINY), seed=11)
        got = frozen.predict(batch)
    assert frozen.__dict__["_predict_copy"].graphs == {}
    assert all(torch.equal(g[k], w[k]) for g, w in zip(got, want) for k in ("boxes", "scores", "labels"))


def test_cpu_predict_copy_refuses_what_the_model_refuses():
    """A bad batch gets the model's own error through the inference copy."""
    from lidarops.models import pointpillars as pp

    model = _bn_trained(PointPillars(TINY), seed=13)
    bad = _frames_batch(14)
    bad["points"][5, 4] = float("nan")  # an intensity
    messages = []
    for ctx in (pp.eager_predict(), torch.no_grad()):
        with ctx, pytest.raises(ValueError) as err:
            model.predict(bad)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "points" in messages[0]


def test_predict_sees_a_changed_config(device):
    """The CPU's inference copy and the CUDA graphs hold the config's thresholds: after a field of
    ``model.config`` is changed in place, or the config replaced, predict gives what the model's own forward and
    post-processing give under the new config (the calls before had made the copy and recorded the graph)."""
    from lidarops.models.pointpillars import eager_predict

    model = _bn_trained(PointPillars({**TINY, "score_thresh": 0.05}), seed=15).to(device)
    batch = _frames_batch(16)
    batch["points"] = batch["points"].to(device)

    def eager():
        with eager_predict():
            return model.predict(batch)

    for _ in range(3):  # on CUDA the second call records a graph, the third replays it
        _close_detections(model.predict(batch), eager(), 1e-5, "before")
    before = sum(len(d["labels"]) for d in eager())
    scores = torch.cat([d["scores"] for d in eager()]).sort().values
    model.config.score_thresh = float(scores[len(scores) // 2])  # in place: about half the boxes go
    for k in range(3):
        assert _close_detections(model.predict(batch), eager(), 1e-5, f"in place {k}") < before
    model.config = dataclasses.replace(model.config, score_thresh=0.05, nms_post_maxsize=1)
    for k in range(3):
        got = model.predict(batch)
        _close_detections(got, eager(), 1e-5, f"replaced {k}")
        assert [len(d["labels"]) for d in got] == [1, 1, 1]


def test_predict_graph_versions_see_in_place_updates():
    """The tensors' version counters that tell an optimized predict graph its copy is stale: they move with an
    in-place update of any parameter or buffer, and are None for a model of inference tensors (no counters)."""
    from lidarops.models.cuda_graph import _PredictGraphs

    model = PointPillars(TINY).eval()
    cache = _PredictGraphs()
    ptrs = cache.current(model)
    before = cache.versions()
    assert before is not None and len(before) == len(ptrs) == len(list(model.parameters())) + len(list(model.buffers()))
    with torch.no_grad():
        model.backbone_2d.blocks[0][2].running_mean.add_(1.0)
    after = cache.versions()
    assert sum(a != b for a, b in zip(before, after)) == 1
    model.load_state_dict(model.state_dict())  # copy_ into every tensor of the state_dict
    assert sum(a != b for a, b in zip(after, cache.versions())) == len(model.state_dict())
    with torch.inference_mode():
        frozen = PointPillars(TINY).eval()
    cache = _PredictGraphs()
    cache.current(frozen)
    assert cache.versions() is None


def _saved(model, tmp_path):
    path = tmp_path / "model.pt"
    torch.save(model, path)
    return path


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_optimized_graph_keeps_the_copy_it_recorded():
    """optimize=True records a BatchNorm-folded copy of the model: its weights must live as long as the graph, or
    later replays read memory that other tensors took."""
    import gc

    from lidarops.models.cuda_graph import GraphedPointPillars

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda().eval()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(7)
    frame = (torch.rand(600, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])).cuda()
    graphed = GraphedPointPillars(model, capacity=1000, optimize=True)
    gc.collect()
    junk = [torch.full((1 << 16,), float("nan"), device="cuda") for _ in range(64)]  # noqa: F841
    det = graphed(frame)
    from lidarops.models.pointpillars import eager_predict

    with eager_predict():
        want = model.predict({"points": F.pad(frame, (1, 0)), "batch_size": 1})[0]
    assert len(want["labels"]) > 0, "the case must keep boxes"
    assert det["labels"].tolist() == want["labels"].tolist()
    assert torch.allclose(det["scores"], want["scores"], atol=1e-3)
    # recorded under fp16: the copy's convolutions hold float16 weights (cast once, not at each replay), the pillar
    # net keeps float32, and the detections are those of the copy run eagerly under the same autocast
    from lidarops.models.cuda_graph import inference_copy, precision_mode

    half = GraphedPointPillars(model, capacity=1000, optimize=True, precision="fp16")
    convs = [m for m in half._graphed_model.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    assert convs and all(c.weight.dtype == torch.float16 for c in convs)
    assert half._graphed_model.vfe.pfn_layers[0].linear.weight.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in model.parameters()), "the model itself is left alone"
    det = half(frame)
    with eager_predict(), precision_mode("fp16"):
        want = inference_copy(model).predict({"points": F.pad(frame, (1, 0)), "batch_size": 1})[0]
    assert det["labels"].tolist() == want["labels"].tolist()
    assert torch.allclose(det["scores"], want["scores"], atol=1e-3)
    assert torch.allclose(det["boxes"], want["boxes"], atol=2e-2)


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_predict_graph_sizes_its_pillar_rows_from_the_frames(monkeypatch):
    """predict's graph takes the pillar rows its frames need (a power of two with a quarter to spare), not every
    frame's capacity; a frame needing more still gets predict's own detections (redone eagerly), and the next call
    records the graph again with more rows."""
    from lidarops.models import cuda_graph
    from lidarops.models.pointpillars import eager_predict

    monkeypatch.setattr(cuda_graph, "MIN_ROWS", 4)
    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda().eval()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(7)
    corner = (torch.rand(50, 4, generator=g) * torch.tensor([1.9, 1.9, 4.0, 1.0])
              + torch.tensor([0, -4.0, -3, 0])).cuda()  # the 4 pillars of a 2 m x 2 m corner
    spread = (torch.rand(900, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
              + torch.tensor([0, -4.0, -3, 0])).cuda()  # all 64 pillars of the grid
    one = lambda f: {"points": F.pad(f, (1, 0)), "batch_size": 1}  # noqa: E731
    graphs = lambda: list(model.__dict__["_predict_graphs"].graphs.values())  # noqa: E731

    def eager(f):
        with eager_predict():
            return model.predict(one(f))

    model.predict(one(corner))
    kept = _same_detections(model.predict(one(corner)), eager(corner), "recorded")
    (first,) = graphs()
    assert first.max_pillars == 8  # 1.25 x 4 + 1 -> 8
    kept += _same_detections(model.predict(one(spread)), eager(spread), "a frame needing more rows")
    assert graphs() == [first], "the replay short of rows was redone eagerly"
    kept += _same_detections(model.predict(one(spread)), eager(spread), "recorded again")
    (second,) = graphs()
    assert second is not first and second.max_pillars == 128  # 1.25 x 64 + 1 -> 128
    kept += _same_detections(model.predict(one(corner)), eager(corner), "a smaller frame in the larger graph")
    assert graphs() == [second] and kept > 0


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_graph_records_while_another_thread_pins_memory():
    """The index build records its graph while its DataLoader's pin-memory thread pins batches: a capture
    in torch's default (global) mode is invalidated by that thread's CUDA calls; the graph must still be
    recorded and give predict's detections."""
    import threading

    from lidarops.models.cuda_graph import GraphedPointPillars

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda().eval()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    stop, started = threading.Event(), threading.Event()

    def pin_loop():
        i = 0
        while not stop.is_set():  # sizes the host allocator has not cached yet, and copies from them
            batch = torch.empty(4096 * (1 + i % 256) + i, dtype=torch.float32).pin_memory()
            batch[:8].cuda()
            started.set()
            i += 1

    thread = threading.Thread(target=pin_loop, daemon=True)
    thread.start()
    try:
        started.wait(30)
        graphed = GraphedPointPillars(model, capacity=1000, batch_size=2)
    finally:
        stop.set()
        thread.join()
    g = torch.Generator().manual_seed(7)
    frames = [(torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
               + torch.tensor([0, -4.0, -3, 0])).cuda() for n in (400, 1000)]
    kept = [_same_as_predict(model, f, det, f"frame {i}") for i, (f, det) in enumerate(zip(frames, graphed(frames)))]
    assert sum(kept) > 0, "the case must keep boxes"


@pytest.mark.parametrize("multi", [False, True])
def test_padded_inference_equals_per_frame_predict(multi):
    """The graph's body run eagerly (any device): a batch of frames padded to one size gives each frame's own
    predict, frames over the pillar capacity (which drop their last pillars on their own, not the batch's),
    an empty frame and duplicate points included; the value check flags the bad frame only."""
    from lidarops.models.cuda_graph import padded_inference

    torch.manual_seed(1)
    cfg = {**TINY, "class_names": ["Car", "Pedestrian"], "score_thresh": 0.3, "nms_thresh": 0.1,
           "multi_classes_nms": multi, "max_voxels_test": 20,
           "anchor_generator_config": TINY["anchor_generator_config"] + [
               {**TINY["anchor_generator_config"][0], "class_name": "Pedestrian", "anchor_sizes": [[0.8, 0.6, 1.7]]}]}
    model = PointPillars(cfg).eval()
    with torch.no_grad():  # scores around 0.5 instead of the prior's 0.01, so that boxes pass 0.3
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(3)
    sizes = (300, 0, 40, 7, 300)
    frames = [torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
              for n in sizes]
    frames[2] = torch.cat([frames[2], frames[2][:10]])  # duplicate points
    n = max(len(f) for f in frames)
    pad = torch.tensor([1000.0, 0, 0, 0])
    buffer = torch.stack([torch.cat([f, pad.expand(n - len(f), 4)]) for f in frames])
    buffer[4, 5, 3] = float("inf")  # frame 4: a bad intensity
    with torch.no_grad():
        out = padded_inference(model, buffer)
    assert out["bad"].tolist() == [False, False, False, False, True]
    kept = 0
    for b, f in enumerate(frames[:4]):
        want = model.predict({"points": F.pad(f, (1, 0)), "batch_size": 1})[0]
        k = int(out["count"][b])
        assert out["labels"][b, :k].tolist() == want["labels"].tolist(), f"frame {b}"
        assert torch.allclose(out["scores"][b, :k], want["scores"], atol=1e-5), f"frame {b}"
        assert torch.allclose(out["boxes"][b, :k], want["boxes"], atol=1e-4), f"frame {b}"
        assert (out["labels"][b, k:] == 0).all()
        kept += k
    assert kept > 0, "the case must keep boxes"
    # frames 0 and 4 hold more pillars than max_voxels_test: each keeps its own first 20
    pillars = [int((f[:, 0].floor() * 8 + (f[:, 1] + 4).floor()).unique().numel()) for f in frames]
    assert pillars[0] > cfg["max_voxels_test"]
    needed = sum(min(n, cfg["max_voxels_test"]) for n in pillars)
    assert int(out["pillars"]) == needed and not bool(out["overflow"])
    # packed into exactly the rows needed: the same detections; one row fewer: flagged
    with torch.no_grad():
        tight = padded_inference(model, buffer, max_pillars=needed)
        short = padded_inference(model, buffer, max_pillars=needed - 1)
    for key in ("count", "labels", "scores", "boxes"):
        assert torch.allclose(tight[key].double(), out[key].double(), atol=1e-5), key
    assert not bool(tight["overflow"]) and bool(short["overflow"]) and int(short["pillars"]) == needed


@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("pre", [4096, 25])
def test_padded_inference_decodes_only_the_nms_candidates(pre, ties, monkeypatch):
    """padded_inference decodes only the anchors its NMS can visit: bit for bit the detections of decoding every
    anchor, with more anchors above the threshold than nms_pre_maxsize and with every score tied; the frames it
    flags for the eager call (a raw box regression beyond the head's safe bound above the threshold) include every
    frame the full check flags, and no frame of a model whose regressions are in range."""
    from lidarops.models.cuda_graph import padded_inference

    torch.manual_seed(2)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1, "nms_pre_maxsize": pre}).eval()
    head = model.dense_head
    with torch.no_grad():  # scores around 0.5, so that many anchors pass 0.3
        head.conv_cls.bias.zero_()
        if ties:
            head.conv_cls.weight.zero_()
    assert 1 <= head.safe_regression <= 10
    g = torch.Generator().manual_seed(5)
    frames = [torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0, -4.0, -3, 0])
              for n in (300, 60, 0)]
    n = max(len(f) for f in frames)
    buffer = torch.stack([torch.cat([f, torch.tensor([1000.0, 0, 0, 0]).expand(n - len(f), 4)]) for f in frames])

    def both():
        with torch.no_grad():
            fast = padded_inference(model, buffer)
            with monkeypatch.context() as m:
                m.setattr(head, "safe_regression", 0.0)  # no bound: every anchor decoded and checked
                full = padded_inference(model, buffer)
        return fast, full

    fast, full = both()
    for key in ("count", "labels", "scores", "boxes"):
        assert torch.equal(fast[key], full[key]), key
    assert int(fast["count"].sum()) > 0 and not fast["bad_boxes"].any() and not full["bad_boxes"].any()
    with torch.no_grad():
        above = (torch.sigmoid(model.network(*model.voxelize(F.pad(frames[0], (1, 0)), 1), 1)["cls_preds"]) >= 0.3)
    assert pre > 30 or int(above.sum()) > pre, "more candidates above the threshold than the NMS takes"
    for shift, flagged in ((60.0, True), (10.5, True)):  # sizes overflow / in range but beyond the safe bound
        with torch.no_grad():
            head.conv_box.bias[3::head.box_coder.code_size] = shift
        fast, full = both()
        assert fast["bad_boxes"].tolist() == [True] * 3  # every frame has anchors above 0.3 (the empty one: 0.5)
        assert full["bad_boxes"].tolist() == [shift > 20] * 3


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_batched_graph_equals_predict():
    """A graph of 3 frames per replay: each frame's detections are its own predict's, over replays with
    fewer frames than the batch and frames of other sizes; replay's padded outputs hold the same rows."""
    from lidarops.models.cuda_graph import GraphedPointPillars

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3, "nms_thresh": 0.1}).cuda().eval()
    with torch.no_grad():
        model.dense_head.conv_cls.bias.zero_()
    g = torch.Generator().manual_seed(7)
    frames = [(torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0])
               + torch.tensor([0, -4.0, -3, 0])).cuda() for n in (400, 1000, 0, 37, 999)]
    graphed = GraphedPointPillars(model, capacity=1000, batch_size=3)
    kept = 0
    for group in (frames[:3], frames[3:], frames[1:2]):
        got = graphed(group)
        assert len(got) == len(group)
        for i, (f, det) in enumerate(zip(group, got)):
            kept += _same_as_predict(model, f, det, f"frame {i}")
    assert kept > 0, "the case must keep boxes"
    out = graphed.replay(frames[:2])
    assert out["count"][2].item() == graphed([frames[2]])[0]["labels"].numel()
    # too few pillar rows for a replay: flagged, and a call gives the eager detections all the same
    small = GraphedPointPillars(model, capacity=1000, batch_size=3, max_pillars=8)
    assert bool(small.replay(frames[:2])["overflow"]) and int(small.replay(frames[:2])["pillars"]) > 8
    for f, det in zip(frames[:2], small(frames[:2])):
        _same_as_predict(model, f, det, "eager fallback")
    with pytest.raises(ValueError, match="1 to batch_size=3"):
        graphed(frames[:4])
    with pytest.raises(ValueError, match=r"frames\[1\] has 1001 rows"):
        graphed([frames[0], torch.zeros(1001, 4, device="cuda")])
