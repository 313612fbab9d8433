"""CAS-Net in front of a frozen PointNet (lidarops.models.casnet_pointnet) and two steps of the trainer with
configs/casnet/casnet_pointnet_objects.yaml on a handful of simulated objects."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch.nn import functional as F

from lidarops.config import ConfigError, load_config
from lidarops.models.casnet import casnet_loss
from lidarops.models.casnet_pointnet import CASNetPointNet, CASNetPointNetConfig
from lidarops.models.pointnet import PointNet, PointNetConfig
from lidarops.train import TrainableModel, TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "configs" / "casnet" / "casnet_pointnet_objects.yaml"
NAMES = ["a", "b", "c"]
#: a narrow PointNet and a 64 -> 8 point CAS-Net: built and run in milliseconds
TASK = PointNetConfig(class_names=NAMES, mlp=[8, 8, 8, 16, 32], fc=[16, 8]).to_dict()
SMALL = dict(class_names=NAMES, num_points=64, ratio=8, k=4, neighbors="knn", task=TASK)


def batch_of(b=4, n=64, c=3, k=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"points": torch.randn(b, n, c, generator=g), "labels": torch.randint(0, k, (b,), generator=g)}


@pytest.mark.parametrize("variant", ["full", "fast"])
@pytest.mark.parametrize("in_channels", [3, 4])
def test_shapes_in_training_and_eval(variant, in_channels):
    task = {**TASK, "in_channels": in_channels}
    model = CASNetPointNet(CASNetPointNetConfig(**{**SMALL, "variant": variant, "in_channels": in_channels,
                                                   "task": task}))
    assert isinstance(model, TrainableModel) and model.casnet.num_out == 8
    assert len(model.casnet.attention) == (3 if variant == "full" else 1)
    batch = batch_of(c=in_channels + 1)  # an extra column is ignored
    out = model.train()(batch)
    assert set(out) == {"loss", "loss_task", "loss_chamfer", "loss_cosine", "accuracy", "duplicates"}
    assert all(v.shape == () for v in out.values()) and out["loss"].requires_grad
    assert 0 <= float(out["duplicates"]) < 8
    logits = model.eval()(batch)
    assert logits.shape == (4, 3)
    preds = model.predict(batch)
    assert len(preds) == 4 and preds[0]["probs"].shape == (3,)
    assert torch.equal(torch.stack([p["label"] for p in preds]), logits.argmax(1))


def test_eval_classifies_the_sampled_points():
    model = CASNetPointNet(SMALL).eval()
    batch = batch_of()
    sampled = model.casnet(batch["points"])
    assert sampled.indices.shape == (4, 8)
    kept = torch.stack([batch["points"][b, sampled.indices[b]] for b in range(4)])
    assert torch.allclose(model(batch), model.task.network(kept)[0], atol=1e-6)


def test_the_pointnet_is_frozen_and_casnet_learns():
    torch.manual_seed(0)
    model = CASNetPointNet(SMALL).train()
    assert not model.task.training and model.casnet.training
    assert all(not p.requires_grad for p in model.task.parameters())
    task_state = {k: v.clone() for k, v in model.task.state_dict().items()}
    casnet_before = {k: v.clone() for k, v in model.casnet.named_parameters()}
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    out = model(batch_of())
    out["loss"].backward()
    assert all(p.grad is None for p in model.task.parameters())
    head = model.casnet.head.layers[0].weight  # the task's gradient reaches CAS-Net through the sampled points
    assert head.grad is not None and head.grad.abs().sum() > 0
    opt.step()
    for k, v in model.task.state_dict().items():  # weights and BatchNorm running statistics
        assert torch.equal(v, task_state[k]), k
    changed = [k for k, p in model.casnet.named_parameters() if not torch.equal(p, casnet_before[k])]
    assert len(changed) > len(casnet_before) // 2
    model.train(True)
    assert not model.task.training  # train() again leaves it in eval mode


@pytest.mark.parametrize("form", ["paper", "frobenius"])
def test_the_loss_is_the_sum_of_its_terms(form):
    model = CASNetPointNet({**SMALL, "alpha": 0.5, "beta": 2.0, "cosine_form": form}).train()
    batch = batch_of()
    torch.manual_seed(1)
    out = model(batch)
    # the same step again, term by term (no dropout reaches the sampler: same sample, same logits)
    torch.manual_seed(1)
    sampled = model.casnet(batch["points"])
    logits = model.task.network(sampled.sampled)[0]
    task = F.cross_entropy(logits, batch["labels"])
    terms = casnet_loss(sampled, batch["points"], task, 0.5, 2.0, form)
    for key in ("loss_task", "loss_chamfer", "loss_cosine"):
        assert torch.allclose(out[key], terms[key], atol=1e-6), key
    assert torch.allclose(out["loss_task"], task, atol=1e-6)
    total = out["loss_task"] + 0.5 * out["loss_chamfer"] + 2.0 * out["loss_cosine"]
    assert torch.allclose(out["loss"], total, atol=1e-6)


def test_a_task_checkpoint_is_loaded_and_checked(tmp_path):
    task = PointNet(PointNetConfig.from_dict(TASK))
    path = task.save(tmp_path / "pointnet.pth")
    model = CASNetPointNet({**SMALL, "task": None, "task_checkpoint": str(path)})
    assert model.config.task == TASK and model.config.task_checkpoint == str(path)
    for k, v in task.state_dict().items():
        assert torch.equal(model.task.state_dict()[k], v)
    with pytest.raises(ConfigError, match="MODEL.TASK_CHECKPOINT .* classifies"):
        CASNetPointNet({**SMALL, "class_names": ["x", "y", "z"], "task": None, "task_checkpoint": str(path)})
    with pytest.raises(ConfigError, match="MODEL.TASK disagrees"):
        CASNetPointNet({**SMALL, "task": {**TASK, "fc": [16]}, "task_checkpoint": str(path)})
    with pytest.raises(ConfigError, match="MODEL.TASK_CHECKPOINT"):
        CASNetPointNet({**SMALL, "task_checkpoint": str(tmp_path / "missing.pth")})


def test_save_and_from_checkpoint_round_trip(tmp_path):
    model = CASNetPointNet(SMALL).train()
    model(batch_of())  # moves CAS-Net's BatchNorm statistics
    path = model.save(tmp_path / "m.pth")
    loaded = CASNetPointNet.from_checkpoint(path).eval()
    assert loaded.config == model.config
    assert torch.equal(loaded(batch_of(seed=3)), model.eval()(batch_of(seed=3)))


@pytest.mark.parametrize("key, value, match", [
    ("RATIO", 0, "MODEL.RATIO must be an int >= 1"),
    ("RATIO", 2.0, "MODEL.RATIO must be an int"),
    ("RATIO", 4096, "MODEL.RATIO 4096 leaves no point of DATA_CONFIG.NUM_POINTS 1024"),
    ("VARIANT", "huge", "MODEL.VARIANT must be one of"),
    ("NEIGHBORS", "radius", "MODEL.NEIGHBORS must be one of"),
    ("ALPHA", -1.0, "MODEL.ALPHA must be a finite number >= 0"),
    ("BETA", float("nan"), "MODEL.BETA must be a finite number"),
    ("TEMPERATURE", 0, "MODEL.TEMPERATURE must be a finite number > 0"),
    ("COSINE_FORM", "sum", "MODEL.COSINE_FORM must be one of"),
    ("K", True, "MODEL.K must be an int"),
    ("TASK_CHECKPOINT", 3, "MODEL.TASK_CHECKPOINT must be a file path"),
    ("TASK", {"MLP": []}, "MODEL.TASK.MLP must be a non-empty list"),
    ("TASK", {"DROPOUT": 1.5}, "MODEL.TASK.DROPOUT must be"),
    ("TASK", [1], "MODEL.TASK must be a mapping"),
    ("SIZE", 3, r"unknown MODEL keys \['SIZE'\]"),
])
def test_bad_config_values_name_the_key(key, value, match):
    cfg = load_config(CONFIG)
    cfg["MODEL"][key] = value
    with pytest.raises(ConfigError, match=match):
        CASNetPointNetConfig.from_openpcdet(cfg)


def test_bad_config_fields_and_dicts():
    with pytest.raises(ConfigError, match="DATA_CONFIG.NUM_POINTS must be an int >= 1"):
        CASNetPointNetConfig(num_points=0)
    with pytest.raises(ConfigError, match="CLASS_NAMES must be a non-empty list"):
        CASNetPointNetConfig(class_names=[])
    with pytest.raises(ConfigError, match="MODEL.TASK: the PointNet classifies"):
        CASNetPointNetConfig(class_names=["x", "y", "z"], task=TASK)
    with pytest.raises(ConfigError, match="unknown CASNetPointNetConfig keys"):
        CASNetPointNetConfig.from_dict({"ratio": 2, "size": 1})
    with pytest.raises(ConfigError, match="MODEL.NAME must be 'CASNetPointNet'"):
        CASNetPointNetConfig.from_openpcdet(load_config(REPO / "configs" / "casnet" / "pointnet_objects.yaml"))


def test_the_shipped_config_builds():
    cfg = load_config(CONFIG)
    c = CASNetPointNetConfig.from_openpcdet(cfg)
    assert (c.ratio, c.num_out, c.variant, c.task_checkpoint) == (8, 128, "full", "runs/pointnet_objects/final.pth")
    opt = TrainConfig.from_openpcdet(cfg["OPTIMIZATION"])
    assert (opt.optimizer, opt.lr, opt.weight_decay, opt.batch_size) == ("adam", 5e-5, 1e-3, 12)
    assert (opt.decay_epochs, opt.lr_decay) == ((20, 40, 60, 80), 0.7)
    base = load_config(REPO / "configs" / "casnet" / "pointnet_objects.yaml")
    assert cfg["CLASS_NAMES"] == base["CLASS_NAMES"] and cfg["DATA_CONFIG"] == base["DATA_CONFIG"]


def test_two_steps_of_the_trainer_with_the_shipped_config(tmp_path):
    from torch.utils.data import Subset

    from lidarops.data.object_sets import datasets_from_config
    from lidarops.eval.classification import ClassificationEvaluator
    from lidarops.train import fit, load_checkpoint

    cfg = load_config(CONFIG)
    cfg["DATA_CONFIG"]["OBJECT_SET"]["SCENES"] = {"driving_highway": 1}
    cfg["DATA_CONFIG"]["NUM_POINTS"] = 64
    task_cfg = PointNetConfig(class_names=cfg["CLASS_NAMES"], mlp=[8, 8, 8, 16, 32], fc=[16, 8])
    task_path = PointNet(task_cfg).save(tmp_path / "pointnet.pth")
    cfg["MODEL"].update(TASK_CHECKPOINT=str(task_path), K=4)
    train_set, test_set, collate = datasets_from_config(cfg, data_path=tmp_path / "objects")
    assert len(train_set) >= 8 and len(test_set) >= 2
    model = CASNetPointNet(cfg)
    task_state = {k: v.clone() for k, v in model.task.state_dict().items()}
    config = TrainConfig.from_openpcdet(cfg["OPTIMIZATION"], epochs=1, batch_size=4, device="cpu", num_workers=0,
                                        progress=False, tensorboard=False, ckpt_every_min=None)
    result = fit(model, Subset(train_set, range(8)), collate, config, tmp_path / "run",
                 val_dataset=Subset(test_set, range(min(4, len(test_set)))),
                 evaluator=ClassificationEvaluator(model.config.class_names))
    assert result.finished and result.global_step == 2 and result.checkpoint.name == "final.pth"
    assert set(result.losses) >= {"loss", "loss_task", "loss_chamfer", "loss_cosine", "accuracy", "duplicates"}
    for k, v in model.task.state_dict().items():
        assert torch.equal(v, task_state[k]), k
    ckpt = load_checkpoint(result.checkpoint)
    assert ckpt["model_class"] == "CASNetPointNet" and ckpt["model_config"]["task"] == task_cfg.to_dict()
    task_path.unlink()  # the run's checkpoint holds the PointNet too
    loaded = CASNetPointNet.from_checkpoint(result.checkpoint).eval()
    batch = collate([test_set[i] for i in range(2)])
    model.eval()
    assert torch.equal(loaded(batch), model(batch))
