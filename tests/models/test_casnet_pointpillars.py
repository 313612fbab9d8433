"""CASNetPointPillars (lidarops/models/casnet_pointpillars.py): CAS-Net in front of a frozen PointPillars. The
pillars built from the kept points are the detector's own, the detector's loss reaches CAS-Net and nothing
else, inference keeps each frame's budget of distinct real points, and one trainer step of the detection
task runs on CPU."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lidarops.config import ConfigError, load_config
from lidarops.models.casnet_pointpillars import CASNetPointPillars, CASNetPointPillarsConfig, sample_frames
from lidarops.models.pointpillars import PointPillars

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "configs" / "casnet" / "casnet_pointpillars_synth.yaml"
DEMO = REPO / "configs" / "pointpillars" / "pointpillars_demo.yaml"


def _detector(tmp_path) -> Path:
    torch.manual_seed(0)
    model = PointPillars(DEMO)
    for m in model.modules():  # non-trivial BatchNorm statistics, so eval mode is not the identity
        if isinstance(m, torch.nn.BatchNorm2d | torch.nn.BatchNorm1d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    from lidarops.checkpoint import format_fields, save_checkpoint

    path = tmp_path / "detector.pth"
    save_checkpoint({**format_fields(), "model_class": "PointPillars", "model_config": model.config.to_dict(),
                     "class_names": list(model.config.class_names), "model_state": model.state_dict()}, [path])
    return path


def _model(tmp_path, **over) -> CASNetPointPillars:
    kw = dict(ratio=4, segment_points=256, k=8, radius=2.0, task_checkpoint=str(_detector(tmp_path)))
    kw.update(over)
    torch.manual_seed(1)
    return CASNetPointPillars(CASNetPointPillarsConfig(**kw))


def _frames(n_frames=2, n=600, seed=0):
    """LiDAR-like points in the demo detector's range: a ground plane and a few boxes of points."""
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(n_frames):
        m = n + 37 * b  # ragged
        xyz = torch.rand(m, 3, generator=g) * torch.tensor([30.0, 30.0, 0.3]) + torch.tensor([0.2, -15.0, -1.8])
        blobs = torch.randint(0, m, (m // 3,), generator=g)
        xyz[blobs[: m // 3], 2] += torch.rand(m // 3, generator=g) * 1.5
        inten = torch.rand(m, 1, generator=g)
        rows.append(torch.cat([torch.full((m, 1), float(b)), xyz, inten], 1))
    points = torch.cat(rows)
    gt = torch.tensor([[[10.0, 0.0, -1.0, 3.9, 1.6, 1.56, 0.3, 1.0]], [[20.0, 5.0, -1.0, 3.9, 1.6, 1.56, -1.0, 1.0]]])
    return {"points": points, "batch_size": n_frames, "gt_boxes": gt[:n_frames]}


def _rows_of(rows, frame) -> bool:
    """Every row of ``rows`` is, bit for bit, a row of ``frame``."""
    return bool((rows.detach()[:, None, :] == frame[None]).all(-1).any(1).all())


def test_pillars_are_the_detectors_own(tmp_path):
    model = _model(tmp_path).eval()
    batch = _frames()
    got = model.pillars(batch["points"], 2)
    want = model.task.voxelize(batch["points"], 2)
    for g, w in zip(got, want):
        assert torch.equal(g, w)


def test_the_detector_loss_reaches_casnet_and_nothing_else(tmp_path):
    model = _model(tmp_path).train()
    task_state = {k: v.clone() for k, v in model.task.state_dict().items()}
    out = model(_frames())
    assert set(out) >= {"loss", "loss_task", "loss_chamfer", "loss_cosine", "loss_cls", "loss_box", "duplicates",
                        "kept_points"}
    torch.testing.assert_close(out["loss"], out["loss_task"] + out["loss_chamfer"] + out["loss_cosine"])
    # the task term alone (alpha = beta = 0) still moves the sampling head: the straight-through path
    model.zero_grad()
    model.config.alpha = model.config.beta = 0.0
    out = model(_frames())
    out["loss"].backward()
    head = [p.grad for p in model.casnet.head.parameters()]
    assert all(g is not None for g in head) and sum(float(g.abs().sum()) for g in head) > 0
    assert all(p.grad is None for p in model.task.parameters())
    assert all(not m.training for m in model.task.modules())
    for k, v in model.task.state_dict().items():  # BatchNorm statistics did not move
        assert torch.equal(v, task_state[k]), k


def test_training_keeps_m_rows_per_segment(tmp_path):
    model = _model(tmp_path).train()
    batch = _frames()
    kept, out, segments = sample_frames(model.casnet, batch["points"], 2, 256)
    n0, n1 = 600, 637
    segs = [-(-n0 // 256), -(-n1 // 256)]
    assert kept.shape == (sum(segs) * 64, 5) and segments.shape == (sum(segs), 256, 4)
    assert torch.equal(kept[:, 0], torch.repeat_interleave(torch.tensor([0.0, 1.0]), torch.tensor(segs) * 64))
    # every kept row is a row of its own frame
    for b in range(2):
        frame = batch["points"][batch["points"][:, 0] == b]
        rows = kept[kept[:, 0] == b]
        assert _rows_of(rows, frame)


def test_dedup_in_training_gives_distinct_rows(tmp_path):
    model = _model(tmp_path, dedup=True).train()
    batch = _frames()
    kept, out, _ = model.sample(batch["points"], 2)
    assert int(out.num_duplicates.sum()) == 0
    for seg in kept.reshape(-1, 64, 5):
        assert torch.unique(seg, dim=0).shape[0] == 64


def test_inference_keeps_the_budget_of_distinct_real_points(tmp_path):
    model = _model(tmp_path, dedup=True).eval()
    batch = _frames()
    kept = model.keep(batch["points"], 2)
    for b, n in enumerate((600, 637)):
        rows = kept[kept[:, 0] == b]
        assert rows.shape[0] == n // 4 and torch.unique(rows, dim=0).shape[0] == n // 4
        frame = batch["points"][batch["points"][:, 0] == b]
        assert _rows_of(rows, frame)
    raw = _model(tmp_path).eval().keep(batch["points"], 2)  # the paper's picks: the budget, repeats allowed
    assert [int((raw[:, 0] == b).sum()) for b in range(2)] == [600 // 4, 637 // 4] and _rows_of(raw, batch["points"])
    preds = model.predict({"points": batch["points"], "batch_size": 2})
    assert len(preds) == 2 and all(set(p) >= {"boxes", "scores", "labels"} for p in preds)


def test_checkpoint_round_trip_and_load_casnet(tmp_path):
    from lidarops.models import load_model
    from lidarops.models.casnet import load_casnet

    model = _model(tmp_path).eval()
    path = model.save(tmp_path / "m.pth")
    (tmp_path / "detector.pth").unlink()  # the checkpoint carries the detector
    loaded = load_model(path)
    assert isinstance(loaded, CASNetPointPillars)
    batch = {"points": _frames()["points"], "batch_size": 2}
    raw_a, raw_b = model(batch), loaded(batch)
    for k in raw_a:
        assert torch.equal(raw_a[k], raw_b[k]), k
    cas = load_casnet(path)
    for k, v in model.casnet.state_dict().items():
        assert torch.equal(cas.state_dict()[k], v)
    alone = load_casnet(cas.save(tmp_path / "cas.pth", task="detector.pth"))
    assert alone.config == cas.config
    for k, v in cas.state_dict().items():
        assert torch.equal(alone.state_dict()[k], v), k


@pytest.mark.parametrize("key, value, match", [
    ("RATIO", 1, "MODEL.RATIO"), ("RATIO", 2.0, "MODEL.RATIO"), ("SEGMENT_POINTS", 1, "MODEL.SEGMENT_POINTS"),
    ("VARIANT", "tiny", "MODEL.VARIANT"), ("NEIGHBORS", "grid", "MODEL.NEIGHBORS"), ("RADIUS", 0.0, "MODEL.RADIUS"),
    ("ALPHA", -1.0, "MODEL.ALPHA"), ("COSINE_FORM", "l2", "MODEL.COSINE_FORM"), ("WINGS", 2, "unknown MODEL keys"),
    ("TASK_CHECKPOINT", 3, "MODEL.TASK_CHECKPOINT"), ("DEDUP", 1, "MODEL.DEDUP"),
])
def test_bad_config_values_name_the_key(key, value, match):
    cfg = load_config(CONFIG)
    cfg["MODEL"][key] = value
    with pytest.raises(ConfigError, match=match):
        CASNetPointPillarsConfig.from_openpcdet(cfg)


def test_a_missing_task_checkpoint_is_named(tmp_path):
    cfg = load_config(CONFIG)
    cfg["MODEL"]["TASK_CHECKPOINT"] = str(tmp_path / "none.pth")
    with pytest.raises(ConfigError, match="MODEL.TASK_CHECKPOINT .*none.pth"):
        CASNetPointPillars(cfg)


def test_the_shipped_config_builds_on_the_shipped_detector():
    from lidarops.models import weights

    model = CASNetPointPillars(CONFIG)
    c = model.config
    assert (c.ratio, c.segment_points, c.num_out, c.k, c.radius, c.neighbors) == (8, 8192, 1024, 32, 2.0, "ball")
    shipped = weights.load("pointpillars_synth")
    for k, v in shipped.state_dict().items():
        assert torch.equal(model.task.state_dict()[k], v), k
    assert c.class_names == ["Car", "Pedestrian", "Cyclist"]


@pytest.mark.slow  # a trainer step on simulated KITTI frames: seconds
def test_one_step_of_the_trainer_on_simulated_frames(tmp_path):
    from lidarops.cli import main
    from lidarops.data.detection import DetectionConfig, collate_batch, train_val_datasets
    from lidarops.eval.kitti import KittiEvaluator
    from lidarops.train import TrainConfig, fit

    data = tmp_path / "synth"
    assert main(["data", "synth", "--scenario", "driving_city", "--frames", "3", "--val-fraction", "0.34",
                 "--out", str(data), "--no-progress", "--seed", "3"]) == 0
    cfg = load_config(CONFIG)
    cfg["MODEL"].update(SEGMENT_POINTS=2048, K=8)
    model = CASNetPointPillars(cfg)
    task_state = {k: v.clone() for k, v in model.task.state_dict().items()}
    data_cfg = DetectionConfig.from_openpcdet(cfg["DATA_CONFIG"])
    train_set, val_set = train_val_datasets(data, model.config.class_names, data_cfg, seed=0)
    config = TrainConfig.from_openpcdet(cfg["OPTIMIZATION"], epochs=1, batch_size=2, device="cpu", num_workers=0,
                                        progress=False, tensorboard=False, ckpt_every_min=None)
    result = fit(model, train_set, collate_batch, config, tmp_path / "run", val_dataset=val_set,
                 evaluator=KittiEvaluator(model.config.class_names))
    assert result.finished and result.global_step == 1
    assert set(result.losses) >= {"loss", "loss_task", "loss_chamfer", "loss_cosine", "duplicates"}
    for k, v in model.task.state_dict().items():
        assert torch.equal(v, task_state[k]), k
    assert any(k.startswith("Car_3d") for k in result.metrics)


def test_anchored_head_trains_on_the_share_inference_keeps(tmp_path):
    from lidarops.models.samplers import spatial_segments

    model = _model(tmp_path, head="anchored", candidates=6).train()
    batch = _frames()
    kept, out, segments = model.sample(batch["points"], 2)
    frames = [batch["points"][batch["points"][:, 0] == b] for b in range(2)]
    # each segment of n points keeps n // ratio rows (not num_out), each a row of its own frame
    for b in range(2):
        want = sum(seg.numel() // 4 for seg in spatial_segments(frames[b][:, 1:4], 256))
        rows = kept[kept[:, 0] == b]
        assert rows.shape[0] == want and _rows_of(rows, frames[b])
    assert segments.shape[1] == 256 and out.indices.shape[1] == max(int(n) // 4 for n in out.lengths)
    out = model(batch)
    out["loss"].backward()
    assert model.casnet.head.key.weight.grad.abs().sum() > 0
    # inference keeps the same budget per frame: n // ratio
    model.eval()
    kept_eval = model.keep(batch["points"], 2)
    assert [int((kept_eval[:, 0] == b).sum()) for b in range(2)] == [f.shape[0] // 4 for f in frames]
