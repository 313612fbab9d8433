"""CounterNet (lidarops/models/counternet.py): shapes per partition, the loss as its parts, counting on hand-made
heatmaps (thresholds, Otsu, overlapping regions merged once), the evaluator, an overfit run whose counts become
exact, config errors, checkpoints and one step of `lidarops train`."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lidarops.config import ConfigError, load_config
from lidarops.models.counternet import CounterNet, CounterNetConfig

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "configs" / "counternet" / "counternet_synth.yaml"


def _tiny_cfg(partitions=1, delta=0.0, **head):
    """A 15.36 m x 15.36 m map of 0.32 m pillars, a two-block backbone of output stride 2: 24 x 24 heatmaps."""
    cfg = load_config(CONFIG)
    cfg["CLASS_NAMES"] = ["Car", "Pedestrian"]
    cfg["DATA_CONFIG"]["POINT_CLOUD_RANGE"] = [0, -7.68, -3, 15.36, 7.68, 1]
    cfg["DATA_CONFIG"]["DATA_PROCESSOR"][2]["VOXEL_SIZE"] = [0.32, 0.32, 4]
    cfg["MODEL"]["VFE"]["NUM_FILTERS"] = [16]
    cfg["MODEL"]["MAP_TO_BEV"]["NUM_BEV_FEATURES"] = 16
    cfg["MODEL"]["BACKBONE_2D"].update(LAYER_NUMS=[1, 1], LAYER_STRIDES=[2, 2], NUM_FILTERS=[16, 32],
                                       UPSAMPLE_STRIDES=[1, 2], NUM_UPSAMPLE_FILTERS=[16, 16])
    cfg["MODEL"]["COUNT_HEAD"].update(SHARED_CHANNELS=16, HEAD_CHANNELS=16, PARTITIONS=partitions, OVERLAP=delta,
                                      **head)
    return cfg


def _scene(seed, boxes):
    """Points on the ground and on each box (x, y, class id 1-based); gt_boxes (1, M, 8)."""
    g = torch.Generator().manual_seed(seed)
    ground = torch.rand(600, 3, generator=g) * torch.tensor([15.0, 15.0, 0.1]) + torch.tensor([0.1, -7.5, -1.8])
    parts = [ground]
    rows = []
    for x, y, c in boxes:
        size = (3.9, 1.6, 1.5) if c == 1 else (0.8, 0.6, 1.7)
        pts = (torch.rand(80, 3, generator=g) - 0.5) * torch.tensor(size) + torch.tensor([x, y, -1.0])
        parts.append(pts)
        rows.append([x, y, -1.0, *size, 0.0, float(c)])
    xyz = torch.cat(parts)
    points = torch.cat([torch.zeros(len(xyz), 1), xyz, torch.rand(len(xyz), 1, generator=g)], 1)
    return points, torch.tensor([rows])


def _batch(scenes):
    points, gts = [], []
    m = max(g.shape[1] for _, g in scenes)
    for b, (p, g) in enumerate(scenes):
        p = p.clone()
        p[:, 0] = b
        points.append(p)
        gts.append(torch.nn.functional.pad(g, (0, 0, 0, m - g.shape[1])))
    return {"points": torch.cat(points), "batch_size": len(scenes), "gt_boxes": torch.cat(gts)}


SCENES = [[(4.0, 2.0, 1), (10.0, -3.0, 1), (7.0, 4.0, 2)], [(3.0, -4.0, 2), (12.0, 3.0, 1), (6.0, 0.5, 2),
                                                             (8.5, -5.0, 2)]]


@pytest.mark.parametrize("partitions, delta", [(1, 0.0), (4, 0.0), (4, 0.2), (9, 0.1), (2, 0.0)])
def test_shapes_per_partition(partitions, delta):
    torch.manual_seed(0)
    model = CounterNet(_tiny_cfg(partitions, delta))
    assert model.map_size == (24, 24) and model.regions.shape == (partitions, 4)
    batch = _batch([_scene(i, s) for i, s in enumerate(SCENES)])
    out = model.train()(batch)
    assert set(out) == {"loss", "loss_heatmap", "loss_count", "count_error"} and out["loss"].requires_grad
    raw = model.eval()(batch)
    for hm, (y0, y1, x0, x1) in zip(raw["heatmaps"], model.regions.tolist()):
        assert hm.shape == (2, 2, y1 - y0, x1 - x0) and bool(((hm > 0) & (hm < 1)).all())
    frames = model.postprocess(raw, batch)
    assert len(frames) == 2 and all(f["counts"].shape == (2,) and f["centres"].shape[1] == 4 for f in frames)
    assert [f["true_counts"].tolist() for f in frames] == [[2, 1], [1, 3]]


def test_untrained_heads_start_at_one_tenth():
    model = CounterNet(_tiny_cfg()).eval()
    raw = model(_batch([_scene(0, SCENES[0])]))
    # bias -2.19: sigmoid = 0.1 before training moves anything (BN in eval mode passes zeros through)
    assert abs(float(model.count_head.heatmaps[0][-1].bias.detach().mean()) + 2.19) < 1e-6
    assert raw["heatmaps"][0].shape == (1, 2, 24, 24)


def test_counting_on_hand_made_heatmaps():
    model = CounterNet(_tiny_cfg(OTSU=False)).eval()
    hm = torch.full((1, 2, 24, 24), 0.01)
    for y, x in ((3, 4), (3, 12), (20, 20)):   # three cars, far apart
        hm[0, 0, y, x] = 0.9
    hm[0, 0, 3, 5] = 0.6   # beside a peak: not a peak of its own (r = 2)
    hm[0, 1, 10, 10] = 0.4  # below t = 0.5
    frames = model.postprocess({"heatmaps": [hm], "features": torch.zeros(1, 16)})
    assert frames[0]["counts"].tolist() == [3, 0]
    centres = frames[0]["centres"]
    # cell (y, x) = (3, 4): x = 0 + (4 + 0.5) * 0.32 * 2, y = -7.68 + (3 + 0.5) * 0.64
    want = torch.tensor([4.5 * 0.64, -7.68 + 3.5 * 0.64])
    assert bool(((centres[:, :2] - want).abs().max(1).values < 1e-5).any())


def test_overlapping_regions_count_an_object_once():
    model = CounterNet(_tiny_cfg(4, 0.25, OTSU=False)).eval()
    full = torch.full((1, 2, 24, 24), 0.01)
    full[0, 0, 11, 11] = 0.9   # near the centre of the map: inside all four grown regions
    full[0, 1, 2, 2] = 0.8     # in one region only
    heatmaps = [full[:, :, y0:y1, x0:x1] for y0, y1, x0, x1 in model.regions.tolist()]
    assert sum(int((h[0, 0] == 0.9).sum()) for h in heatmaps) == 4   # seen by every region
    frames = model.postprocess({"heatmaps": heatmaps, "features": torch.zeros(1, 16)})
    assert frames[0]["counts"].tolist() == [1, 1]
    from lidarops.models.counting import count_peaks

    assert sum(int(count_peaks(h, 0.5)[0, 0]) for h in heatmaps) == 4   # what the regions find before merging


def test_otsu_raises_the_threshold_above_t():
    model = CounterNet(_tiny_cfg()).eval()
    hm = torch.full((1, 2, 24, 24), 0.05)
    hm[0, 0, 4, 4] = 0.95
    hm[0, 0, 15, 15] = 0.55   # above t = 0.5: counted only if the frame's Otsu threshold is below it
    hm[0, 0, 20, 4] = 0.97
    from skimage.filters import threshold_otsu

    otsu = threshold_otsu(hm.reshape(-1).numpy(), nbins=256)
    frames = model.postprocess({"heatmaps": [hm], "features": torch.zeros(1, 16)})
    expected = int((np.array([0.95, 0.55, 0.97]) >= max(otsu, 0.5)).sum())
    assert frames[0]["counts"].tolist() == [expected, 0]


def test_the_loss_is_its_parts():
    from lidarops.models.counting import focal_loss, partition_weights, soft_count

    torch.manual_seed(0)
    model = CounterNet(_tiny_cfg(4, 0.0, COUNT_WEIGHT=0.5)).train()
    batch = _batch([_scene(i, s) for i, s in enumerate(SCENES)])
    out = model(batch)
    target = model.targets(batch["gt_boxes"])
    model.eval()
    raw = model(batch)
    # BN in train vs eval mode differ: recompute the train-mode heatmaps
    model.train()
    from lidarops.models.pointpillars import voxelize_frames

    floor = model.config.floor_config()
    _, logits = model.network(*voxelize_frames(batch["points"], 2, floor, True), 2)
    heat = [torch.sigmoid(x) for x in logits]
    hm, err, true = [], [], []
    for pred, (y0, y1, x0, x1) in zip(heat, model.regions.tolist()):
        t = target[:, :, y0:y1, x0:x1]
        hm.append(focal_loss(pred, t))
        n = (t == 1).sum(dim=(2, 3)).float()
        err.append((soft_count(pred, 0.5, 2, 0.05) - n).abs().mean(1))
        true.append(n.sum(1))
    w = partition_weights(torch.stack(true, 1))
    want = torch.stack(hm).mean() + 0.5 * (w * torch.stack(err, 1)).sum(1).mean()
    torch.testing.assert_close(out["loss"], want, rtol=1e-5, atol=1e-6)
    assert raw["features"].shape == (2, 16)


@pytest.mark.slow  # about 20 s on two cores
def test_overfits_two_frames_until_the_counts_are_exact():
    torch.manual_seed(0)
    model = CounterNet(_tiny_cfg())
    batch = _batch([_scene(i, s) for i, s in enumerate(SCENES)])
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    first = None
    for step in range(150):
        model.train()
        out = model(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        first = first if first is not None else float(out["loss"].detach())
    assert float(out["loss"].detach()) < 0.2 * first
    # BatchNorm's running statistics (OpenPCDet's momentum 0.01) lag 150 steps of a moving network: set them to
    # the final network's statistics of these frames (precise BN), as an overfit check of eval mode needs
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None
    with torch.no_grad():
        model.train()(batch)
    model.eval()
    frames = model.predict(batch)
    assert [f["counts"].tolist() for f in frames] == [[2, 1], [1, 3]]


@pytest.mark.parametrize("partitions, delta", [(1, 0.0), (4, 0.25)])
def test_cpu_predict_runs_an_inference_copy_with_the_models_counts(partitions, delta):
    """On the CPU predict runs an inference copy (BatchNorm and padding folded, channels-last; the count head reading
    the upsampled maps one by one): the model's own counts and centres up to rounding, made again after an in-place
    update; eager_predict() runs the model itself."""
    from helpers.models import randomize_bn

    from lidarops.models.pointpillars import eager_predict

    torch.manual_seed(1)
    model = CounterNet(_tiny_cfg(partitions, delta))
    randomize_bn(model.backbone_2d, 2)
    randomize_bn(model.count_head, 3)
    with torch.no_grad():  # heatmaps around 0.5 with peaks: something to count
        for branch in model.count_head.heatmaps:
            branch[-1].bias.zero_()
            branch[-1].weight.mul_(20)
    model.eval()
    batch = _batch([_scene(i, s) for i, s in enumerate(SCENES)])

    def own():
        with torch.no_grad():
            return model.postprocess(model(batch), batch)

    for step in range(2):
        got, want = model.predict(batch), own()
        copy = model.__dict__["_predict_copy"].graphs["copy"][1]
        assert copy is not model and not any(isinstance(m, torch.nn.BatchNorm2d) for m in copy.modules())
        for g, w in zip(got, want, strict=True):
            assert g["counts"].tolist() == w["counts"].tolist(), step
            assert torch.allclose(g["centres"], w["centres"], atol=1e-5), step
            assert torch.allclose(g["features"], w["features"], atol=1e-5), step
        assert sum(int(w["counts"].sum()) for w in want) > 0
        with torch.no_grad():  # an in-place update: the next predict makes the copy again
            model.count_head.shared_conv[0].weight.mul_(1.5)
    with eager_predict():
        mine = model.predict(batch)
    assert all(torch.equal(m["centres"], w["centres"]) for m, w in zip(mine, own()))


def test_counting_evaluator_by_hand():
    from lidarops.eval.counting import CountingEvaluator

    ev = CountingEvaluator(["Car", "Pedestrian"])
    preds = [{"counts": torch.tensor([2, 1]), "true_counts": torch.tensor([2, 1])},
             {"counts": torch.tensor([3, 0]), "true_counts": torch.tensor([1, 3])}]
    metrics, text = ev(preds, [{}, {}])
    assert metrics["counting_accuracy_Car"] == 50.0 and metrics["counting_accuracy_Pedestrian"] == 50.0
    assert metrics["count_mae_Car"] == 1.0 and metrics["count_mae_Pedestrian"] == 1.5
    assert metrics["counting_accuracy"] == 50.0 and "Pedestrian" in text
    with pytest.raises(ValueError, match="true_counts"):
        ev([{"counts": torch.tensor([1, 1])}], [{}])


@pytest.mark.parametrize("key, value, match", [
    ("PARTITIONS", 3, "PARTITIONS"), ("OVERLAP", -0.1, "OVERLAP"), ("THRESHOLD", 1.0, "THRESHOLD"),
    ("PEAK_RADIUS", -1, "PEAK_RADIUS"), ("OTSU", "yes", "OTSU"), ("WINGS", 1, "unknown MODEL.COUNT_HEAD keys"),
])
def test_bad_config_values_name_the_key(key, value, match):
    cfg = load_config(CONFIG)
    cfg["MODEL"]["COUNT_HEAD"][key] = value
    with pytest.raises(ConfigError, match=match):
        CounterNetConfig.from_openpcdet(cfg)


def test_the_shipped_config_builds_and_round_trips(tmp_path):
    from lidarops.checkpoint import format_fields, save_checkpoint
    from lidarops.models import load_model

    model = CounterNet(CONFIG)
    c = model.config
    assert c.class_names == ["Car", "Truck", "Bus", "Pedestrian", "Cyclist", "Barrier", "TrafficCone"]
    assert model.map_size == (248, 216) and c.merge_radius == pytest.approx(0.32)
    assert CounterNetConfig.from_dict(c.to_dict()) == c
    small = CounterNet(_tiny_cfg(4, 0.2)).eval()
    path = tmp_path / "cn.pth"
    save_checkpoint({**format_fields(), "model_class": "CounterNet", "model_config": small.config.to_dict(),
                     "class_names": small.config.class_names, "model_state": small.state_dict()}, [path])
    loaded = load_model(path)
    batch = _batch([_scene(0, SCENES[0])])
    assert torch.equal(loaded(batch)["heatmaps"][2], small(batch)["heatmaps"][2])


@pytest.mark.slow  # simulates three frames and trains one step: seconds
def test_one_step_of_lidarops_train(tmp_path):
    from lidarops.cli import main

    data = tmp_path / "synth"
    assert main(["data", "synth", "--scenario", "driving_city", "--frames", "3", "--val-fraction", "0.34",
                 "--object-counts", "dense", "--out", str(data), "--no-progress", "--seed", "3"]) == 0
    run = tmp_path / "run"
    code = main(["train", "--config", str(CONFIG), "--data", str(data), "--out", str(run), "--epochs", "1",
                 "--batch-size", "2", "--workers", "0", "--no-progress", "--device", "cpu",
                 "--set", "MODEL.BACKBONE_2D.LAYER_NUMS", "[1, 1, 1]", "OPTIMIZATION.OPTIMIZER", "adam",
                 "OPTIMIZATION.DECAY_STEP_LIST", "[1]"])
    assert code == 0 and (run / "final.pth").is_file()
    ckpt = torch.load(run / "final.pth", weights_only=False)
    assert ckpt["model_class"] == "CounterNet"
    evals = sorted(run.glob("eval_epoch_*.json"))
    assert evals and "counting_accuracy" in evals[-1].read_text()
