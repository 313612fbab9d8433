"""PointNet, the classifier (lidarops.models.pointnet), its evaluator (lidarops.eval.classification) and
one tiny run of the trainer on simulated objects with configs/casnet/pointnet_objects.yaml."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError, load_config
from lidarops.eval.classification import ClassificationEvaluator, classification_metrics, confusion_matrix
from lidarops.models.pointnet import PointNet, PointNetConfig
from lidarops.train import TrainableModel, TrainConfig

from helpers.devices import DEVICES

# small tensors: one intra-op thread (OpenMP wake-ups on a shared machine cost more than the work)
pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "configs" / "casnet" / "pointnet_objects.yaml"
#: a narrow PointNet: the tests of shapes and errors build it in milliseconds
SMALL = dict(class_names=["a", "b", "c"], mlp=[8, 8, 8, 16, 32], fc=[16, 8])


def batch_of(b=4, n=32, c=3, k=3, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    return {"points": torch.randn(b, n, c, generator=g).to(device),
            "labels": torch.randint(0, k, (b,), generator=g).to(device)}


# ---------------------------------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("transforms", [False, True], ids=["vanilla", "transforms"])
@pytest.mark.parametrize("in_channels", [3, 4])
def test_shapes_in_training_and_eval(device, transforms, in_channels):
    torch.manual_seed(0)
    model = PointNet(PointNetConfig(**SMALL, in_channels=in_channels, input_transform=transforms,
                                    feature_transform=transforms)).to(device)
    batch = batch_of(5, 40, in_channels + 1, device=device)  # one column more than read: ignored
    out = model(batch)
    assert {"loss", "loss_cls", "accuracy", "logits"} <= set(out) and ("loss_reg" in out) == transforms
    assert out["loss"].shape == () and out["loss"].requires_grad and out["logits"].shape == (5, 3)
    if transforms:
        assert torch.allclose(out["loss"], out["loss_cls"] + out["loss_reg"])
    else:
        assert out["loss"] is out["loss_cls"]
    out["loss"].backward()
    model.eval()
    logits = model(batch)
    assert isinstance(logits, torch.Tensor) and logits.shape == (5, 3) and logits.device.type == device
    preds = model.postprocess(logits, batch)
    assert len(preds) == 5
    for p, row in zip(preds, logits):
        assert p["label"].dtype == torch.int64 and p["label"].shape == () and p["probs"].shape == (3,)
        assert int(p["label"]) == int(row.argmax()) and torch.isclose(p["probs"].sum(), torch.tensor(1.0, device=device))
        assert torch.isclose(p["score"], p["probs"].max())
    assert [int(p["label"]) for p in model.predict(batch)] == [int(p["label"]) for p in preds]
    assert not model.training  # predict leaves the mode as it found it
    model.train()
    model.predict(batch)
    assert model.training


def test_the_default_network_is_pointnet_vanilla():
    model = PointNet()
    keys = list(model.state_dict())
    convs = [model.mlp[i].conv for i in range(5)]
    assert [(c.in_channels, c.out_channels) for c in convs] == [(3, 64), (64, 64), (64, 64), (64, 128), (128, 1024)]
    assert [(m.in_features, m.out_features) for m in (model.head.fc1.linear, model.head.fc2.linear, model.head.fc3)] \
        == [(1024, 512), (512, 256), (256, 8)]
    assert model.head.dp1.p == pytest.approx(0.3) and list(model.head)[-2] is model.head.dp1  # before the last layer
    assert not any(k.startswith(("input_transform", "feature_transform")) for k in keys)
    assert keys[:2] == ["mlp.conv1.conv.weight", "mlp.conv1.bn.weight"] and keys[-2:] == ["head.fc3.weight",
                                                                                          "head.fc3.bias"]
    assert model.config.label_smoothing == 0.0 and model.config.num_classes == 8


def test_the_transforms_start_as_the_identity():
    model = PointNet(PointNetConfig(**SMALL, input_transform=True, feature_transform=True)).eval()
    x = torch.randn(2, 3, 16)
    assert torch.equal(model.input_transform(x), torch.eye(3).expand(2, 3, 3))
    assert any(k.startswith("feature_transform.conv1") for k in model.state_dict())


def test_the_logits_are_differentiable_in_the_points():
    # a learned sampler in front trains through the classifier: the gradient must reach the points
    model = PointNet(PointNetConfig(**SMALL)).eval()
    pts = torch.randn(2, 20, 3, requires_grad=True)
    logits, _ = model.network(pts)
    logits[:, 0].sum().backward()
    assert pts.grad is not None and pts.grad.abs().sum() > 0


# ---------------------------------------------------------------------------------------------------- the loss
@pytest.mark.parametrize("smoothing", [0.0, 0.2])
def test_loss_is_the_hand_computed_cross_entropy(smoothing):
    # fc3 with zero weights outputs its bias for every object: logits (1, -0.5, 2), whatever the points
    model = PointNet(PointNetConfig(**SMALL, label_smoothing=smoothing))
    with torch.no_grad():
        model.head.fc3.weight.zero_()
        model.head.fc3.bias.copy_(torch.tensor([1.0, -0.5, 2.0]))
    labels = [0, 2, 1, 2]
    out = model({"points": torch.randn(4, 10, 3), "labels": torch.tensor(labels)})
    z = [1.0, -0.5, 2.0]
    log_sum = math.log(sum(math.exp(v) for v in z))
    nll = [log_sum - z[y] for y in labels]                     # -log softmax(z)[y]
    uniform = sum(log_sum - v for v in z) / 3                   # -mean_k log softmax(z)[k]
    want = sum((1 - smoothing) * v + smoothing * uniform for v in nll) / len(labels)
    assert float(out["loss"].detach()) == pytest.approx(want, rel=1e-6)
    assert float(out["loss_cls"].detach()) == pytest.approx(want, rel=1e-6)
    assert float(out["accuracy"]) == pytest.approx(2 / 4)        # argmax is class 2 for every object
    assert torch.allclose(out["logits"], torch.tensor(z).expand(4, 3))


def test_feature_transform_loss_is_zero_at_the_identity_and_weighted():
    model = PointNet(PointNetConfig(**SMALL, feature_transform=True, feature_transform_weight=0.5))
    out = model(batch_of())
    assert float(out["loss_reg"].detach()) == pytest.approx(0.0, abs=1e-10)  # starts as the identity
    with torch.no_grad():
        model.feature_transform.transform.bias.mul_(2.0)  # A = 2 I: |I - 4 I|^2 = 9 * 8 per object
    out = model(batch_of())
    assert float(out["loss_reg"].detach()) == pytest.approx(0.5 * 9 * 8, rel=1e-5)


# ---------------------------------------------------------------------------------------------------- training
def two_class_objects(n_per_class=4, points=32, seed=0):
    """Elongated objects (class 0: a 4 x 0.5 x 0.5 box surface, like a car seen flat) and tall thin ones
    (class 1: a 0.5 x 0.5 x 2 column, like a pedestrian), each randomly sampled and placed."""
    g = torch.Generator().manual_seed(seed)
    clouds, labels = [], []
    for label, size in ((0, (4.0, 0.5, 0.5)), (1, (0.5, 0.5, 2.0))):
        for _ in range(n_per_class):
            u = torch.rand(points, 3, generator=g) - 0.5
            clouds.append(u * torch.tensor(size) + 0.2 * torch.randn(1, 3, generator=g))
            labels.append(label)
    return torch.stack(clouds), torch.tensor(labels)


def test_overfits_eight_objects_of_two_classes_quickly():
    torch.manual_seed(0)
    points, labels = two_class_objects()
    model = PointNet(PointNetConfig(class_names=["long", "tall"]))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    t0 = time.perf_counter()
    steps, acc = 0, 0.0
    for steps in range(1, 61):
        model.train()
        opt.zero_grad()
        out = model({"points": points, "labels": labels})
        out["loss"].backward()
        opt.step()
        if steps % 5 == 0:
            model.eval()
            with torch.no_grad():
                acc = float((model({"points": points}).argmax(1) == labels).float().mean())
            if acc == 1.0 and float(out["accuracy"]) == 1.0:
                break
    seconds = time.perf_counter() - t0
    assert acc == 1.0, f"eval accuracy {acc} after {steps} steps"
    assert seconds < 5.0, f"{steps} steps took {seconds:.1f} s"


@pytest.mark.parametrize("device", DEVICES)
def test_eval_mode_is_deterministic_and_per_object(device):
    torch.manual_seed(1)
    model = PointNet(PointNetConfig(**SMALL)).to(device)
    for _ in range(3):  # running statistics away from their initial values
        model(batch_of(8, 32, device=device))
    model.eval()
    batch = batch_of(6, 32, seed=3, device=device)
    first, second = model(batch), model(batch)
    assert torch.equal(first, second)
    alone = model({"points": batch["points"][2:3]})
    assert torch.allclose(alone[0], first[2], atol=1e-5)  # an object's logits do not depend on its batch
    shuffled = model({"points": batch["points"][:, torch.randperm(32)]})
    assert torch.allclose(shuffled, first, atol=1e-5)    # nor on the order of its points
    # the global feature is a max over the points: repeating points (resampling an object with fewer points
    # than num_points) changes nothing
    repeated = model({"points": torch.cat([batch["points"], batch["points"][:, :5]], dim=1)})
    assert torch.allclose(repeated, first, atol=1e-5)


# ---------------------------------------------------------------------------------------------------- bad input
BAD_BATCHES = [
    ("no points", lambda b: {"labels": b["labels"]}, "'points'"),
    ("not a dict", lambda b: b["points"], "batch must be a dict"),
    ("2-D points", lambda b: {**b, "points": b["points"][0]}, r"batch\['points'\]"),
    ("integer points", lambda b: {**b, "points": b["points"].long()}, r"batch\['points'\]"),
    ("too few columns", lambda b: {**b, "points": b["points"][..., :2]}, r"batch\['points'\]"),
    ("no points per object", lambda b: {**b, "points": b["points"][:, :0]}, r"batch\['points'\]"),
    ("NaN", lambda b: {**b, "points": b["points"].index_fill(0, torch.tensor([1]), float("nan"))},
     r"batch\['points'\] must be finite; object\(s\) \[1\]"),
    ("no labels", lambda b: {"points": b["points"]}, r"batch\['labels'\]"),
    ("labels of another length", lambda b: {**b, "labels": b["labels"][:3]}, r"batch\['labels'\]"),
    ("float labels", lambda b: {**b, "labels": b["labels"].float()}, r"batch\['labels'\]"),
    ("labels (B, 1)", lambda b: {**b, "labels": b["labels"][:, None]}, r"batch\['labels'\]"),
    ("label out of range", lambda b: {**b, "labels": torch.tensor([0, 1, 3, 0])}, r"batch\['labels'\].*\[3\]"),
    ("negative label", lambda b: {**b, "labels": torch.tensor([0, -1, 2, 0])}, r"batch\['labels'\].*\[-1\]"),
    ("one object in training", lambda b: {"points": b["points"][:1], "labels": b["labels"][:1]},
     r"batch\['points'\] holds 1 object"),
]


@pytest.mark.parametrize("make, match", [pytest.param(m, r, id=name) for name, m, r in BAD_BATCHES])
def test_bad_batches_are_refused_naming_the_key(make, match):
    model = PointNet(PointNetConfig(**SMALL))
    with pytest.raises(ValueError, match=match):
        model(make(batch_of()))


def test_eval_needs_no_labels_and_takes_one_object():
    model = PointNet(PointNetConfig(**SMALL)).eval()
    assert model({"points": torch.randn(1, 5, 3)}).shape == (1, 3)
    with pytest.raises(ValueError, match="raw must be the eval-mode logits"):
        model.postprocess(torch.zeros(2, 4))


@pytest.mark.parametrize("field, value, key", [
    ("dropout", 1.0, "MODEL.DROPOUT"), ("dropout", float("nan"), "MODEL.DROPOUT"),
    ("label_smoothing", -0.1, "MODEL.LABEL_SMOOTHING"), ("in_channels", 2, "used_feature_list"),
    ("in_channels", 3.0, "used_feature_list"), ("mlp", [], "MODEL.MLP"), ("mlp", [64, 0], r"MODEL.MLP\[1\]"),
    ("fc", [512, True], r"MODEL.FC\[1\]"), ("input_transform", 1, "MODEL.INPUT_TRANSFORM"),
    ("class_names", [], "CLASS_NAMES"), ("class_names", ["a", "a"], "CLASS_NAMES"),
])
def test_bad_config_values_name_the_key(field, value, key):
    with pytest.raises(ConfigError, match=key):
        PointNetConfig(**{**SMALL, field: value})


def test_feature_transform_needs_three_layers():
    with pytest.raises(ConfigError, match="MODEL.FEATURE_TRANSFORM needs at least 3"):
        PointNetConfig(**{**SMALL, "mlp": [8, 8], "feature_transform": True})


# ---------------------------------------------------------------------------------------------------- config, files
def test_the_shipped_config_builds_the_paper_model():
    cfg = load_config(CONFIG)
    assert load_config("pointnet_objects") == cfg  # shipped: found by name
    model = PointNet(cfg)
    assert isinstance(model, TrainableModel) and PointNet(CONFIG).config == model.config
    assert model.config.to_dict() == PointNetConfig(class_names=cfg["CLASS_NAMES"]).to_dict()
    assert PointNetConfig.from_dict(model.config.to_dict()) == model.config
    train = TrainConfig.from_openpcdet(cfg["OPTIMIZATION"])
    assert (train.optimizer, train.lr, train.batch_size, train.weight_decay) == ("adam", 1e-3, 32, 0.0)
    assert (train.lr_decay, train.lr_clip, train.grad_norm_clip) == (0.7, 1e-5, None)
    cfg["MODEL"]["DROPUT"] = 0.5
    with pytest.raises(ConfigError, match=r"unknown MODEL keys \['DROPUT'\]"):
        PointNet(cfg)


def test_a_saved_model_loads_back_with_the_same_outputs(tmp_path):
    torch.manual_seed(0)
    model = PointNet(PointNetConfig(**SMALL, in_channels=4))
    model(batch_of(6, 16, 4))  # running statistics away from their initial values
    model.eval()
    path = model.save(tmp_path / "pn.pth", data_recipe={"source": "test"})
    loaded = PointNet.from_checkpoint(path).eval()
    batch = batch_of(3, 16, 4, seed=5)
    assert torch.equal(loaded(batch), model(batch))
    assert loaded.config == model.config
    with pytest.raises(CheckpointError, match=r"shape mismatch .*mlp\.conv1\.conv\.weight"):
        PointNet.from_checkpoint(path, config=PointNetConfig(**SMALL, in_channels=3))
    with pytest.raises(CheckpointError, match=r"missing .*input_transform"):
        PointNet.from_checkpoint(path, config=PointNetConfig(**SMALL, in_channels=4, input_transform=True))
    state = model.state_dict()
    state["head.fc3.bias"] = torch.full_like(state["head.fc3.bias"], float("nan"))
    torch.save({"model_state": state}, tmp_path / "nan.pth")
    with pytest.raises(CheckpointError, match=r"head\.fc3\.bias"):
        PointNet.from_checkpoint(tmp_path / "nan.pth", config=model.config)


# ---------------------------------------------------------------------------------------------------- the evaluator
def test_classification_metrics_by_hand():
    names = ["Car", "Pedestrian", "Drone"]
    conf = confusion_matrix([0, 0, 1, 0, 1], [0, 0, 0, 1, 1], 3)
    assert conf.tolist() == [[2, 1, 0], [1, 1, 0], [0, 0, 0]]
    m = classification_metrics(conf, names)
    assert m["accuracy"] == pytest.approx(60.0) and m["num_objects"] == 5
    assert m["accuracy_Car"] == pytest.approx(200 / 3) and m["accuracy_Pedestrian"] == pytest.approx(50.0)
    assert m["mean_class_accuracy"] == pytest.approx((200 / 3 + 50) / 2)  # Drone has no objects: left out
    assert "accuracy_Drone" not in m
    with pytest.raises(ValueError, match="target holds class id 3"):
        confusion_matrix([0], [3], 3)


def test_the_evaluator_reads_postprocess_and_collate_output():
    ev = ClassificationEvaluator(["a", "b"])
    preds = [{"label": torch.tensor(1)}, {"label": torch.tensor(0)}, {"label": torch.tensor(1)}]
    metrics, text = ev(preds, [{"gt_label": 1}, {"gt_label": 1}, {"gt_label": 1}])
    assert metrics["accuracy"] == pytest.approx(200 / 3) and ev.confusion.tolist() == [[0, 0], [1, 2]]
    assert "overall accuracy 66.67 %" in text and "no test objects of a" in text
    with pytest.raises(ValueError, match="has no 'gt_label'"):
        ev(preds[:1], [{"frame_id": 0}])


# ---------------------------------------------------------------------------------------------------- the trainer
def test_two_steps_of_the_trainer_with_the_shipped_config(tmp_path):
    # under a second (one highway scene simulated, two steps of 4 objects): CPU CI trains the classifier
    from torch.utils.data import Subset

    from lidarops.data.object_sets import datasets_from_config
    from lidarops.train import fit, load_checkpoint

    cfg = load_config(CONFIG)
    cfg["DATA_CONFIG"]["OBJECT_SET"]["SCENES"] = {"driving_highway": 1}  # a handful of objects, ~0.5 s
    train_set, test_set, collate = datasets_from_config(cfg, data_path=tmp_path / "objects")
    assert len(train_set) >= 8 and len(test_set) >= 2
    model = PointNet(cfg)
    config = TrainConfig.from_openpcdet(cfg["OPTIMIZATION"], epochs=1, batch_size=4, device="cpu", num_workers=0,
                                        progress=False, tensorboard=False, ckpt_every_min=None)
    result = fit(model, Subset(train_set, range(8)), collate, config, tmp_path / "run",
                 val_dataset=Subset(test_set, range(min(4, len(test_set)))),
                 evaluator=ClassificationEvaluator(model.config.class_names),
                 extra_checkpoint={"data_recipe": train_set.recipe})
    assert result.finished and result.global_step == 2 and result.checkpoint.name == "final.pth"
    assert set(result.losses) >= {"loss", "loss_cls", "accuracy"}
    report = json.loads((tmp_path / "run" / "eval_epoch_1.json").read_text())
    assert {"accuracy", "mean_class_accuracy", "num_objects"} <= set(report["metrics"])
    ckpt = load_checkpoint(result.checkpoint)
    assert ckpt["model_class"] == "PointNet" and ckpt["class_names"] == cfg["CLASS_NAMES"]
    assert ckpt["data_recipe"]["num_points"] == 1024 and ckpt["data_recipe"]["scenarios"] == {"driving_highway": 1}
    loaded = PointNet.from_checkpoint(result.checkpoint).eval()
    batch = collate([test_set[i] for i in range(2)])
    model.eval()
    assert torch.equal(loaded(batch), model(batch))
    assert np.isfinite(result.losses["loss"])
