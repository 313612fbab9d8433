"""lidarops.train: the one-cycle schedule against its formula, OpenPCDet config reading, gradient clipping,
AMP on CPU, checkpoint contents and loading errors, resume identity (mid-epoch, with workers, after a
crash, after a time budget), keep_last, evaluation, and DDP on CPU (gloo, 2 processes): equivalence with
one process on the concatenated batch and evaluation gathering every frame once.

Toy models and datasets only: an MLP regressing a fixed linear map, whose loss is a mean over frames."""
from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import os
import random
import socket
import time

import numpy as np
import pytest
import torch
from torch import nn
from torch.optim.optimizer import register_optimizer_step_pre_hook
from torch.utils.data import Dataset

import lidarops
from lidarops.train import TrainConfig, build_optimizer, evaluate, fit, load_checkpoint
from lidarops.train import loop as train_loop

W_TRUE = torch.tensor([[1.0, -2.0], [0.5, 1.0], [3.0, 0.0], [-1.0, 1.0]])


class ToyFrames(Dataset):
    """Frames ``x (4,)``, ``y = x @ W_TRUE + 1`` (2,), ``frame_id``; with ``noise``, x is jittered by a
    generator seeded from ``(epoch, index)`` (the augmentation pattern that survives mid-epoch resumes)."""

    def __init__(self, n: int, noise: float = 0.0, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 4, generator=g)
        self.y = self.x @ W_TRUE + 1.0
        self.noise = noise
        self.epoch = 0
        self.epochs_set: list[int] = []

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        self.epochs_set.append(epoch)

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> dict:
        x = self.x[i]
        if self.noise:
            g = torch.Generator().manual_seed(1000 * self.epoch + i)
            x = x + self.noise * torch.randn(4, generator=g)
        return {"x": x, "y": self.y[i], "frame_id": i, "epoch": self.epoch}


def collate(items: list[dict]) -> dict:
    return {"x": torch.stack([it["x"] for it in items]), "y": torch.stack([it["y"] for it in items]),
            "frame_id": [it["frame_id"] for it in items], "epoch": [it["epoch"] for it in items],
            "batch_size": len(items)}


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclasses.dataclass
class ToyConfig:
    """A model config as the trainer reads one: ``to_dict()`` and ``class_names``."""

    hidden: int
    class_names: list

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class ToyModel(nn.Module):
    """MLP 4 -> 8 -> 2 with optional dropout; loss = mean over frames of the squared error.

    ``clock`` (FakeClock) advances ``step_seconds`` per training forward; ``crash_at`` raises on that
    training forward (1-based), like a kill in the middle of a step."""

    def __init__(self, dropout: float = 0.0, seed: int = 0, loss_scale: float = 1.0, clock=None,
                 step_seconds: float = 10.0, crash_at: int | None = None) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(4, 8), nn.Tanh(), nn.Dropout(dropout), nn.Linear(8, 2))
        self.loss_scale, self.clock, self.step_seconds, self.crash_at = loss_scale, clock, step_seconds, crash_at
        self.forwards = 0
        self.epochs_seen: list[int] = []
        self.autocast_dtypes: list = []

    def forward(self, batch: dict):
        pred = self.net(batch["x"])
        if not self.training:
            return pred
        self.forwards += 1
        if self.crash_at == self.forwards:
            raise RuntimeError("simulated kill")
        if self.clock is not None:
            self.clock.t += self.step_seconds
        self.epochs_seen += batch["epoch"]
        if torch.is_autocast_enabled("cpu"):
            self.autocast_dtypes.append(torch.get_autocast_dtype("cpu"))
        err = pred.float() - batch["y"]
        loss = self.loss_scale * (err ** 2).sum(-1).mean()
        return {"loss": loss, "loss_abs": err.abs().mean().detach(), "not_a_scalar": err.detach()}

    def postprocess(self, raw, batch):
        return [{"y": r, "frame_id": torch.tensor(f)} for r, f in zip(raw, batch["frame_id"])]


def config(**kw) -> TrainConfig:
    base = dict(epochs=3, batch_size=4, num_workers=0, seed=0, log_every=1, progress=False, tensorboard=False,
                ckpt_every_min=None, keep_last=None, device="cpu", grad_norm_clip=10.0)
    base.update(kw)
    return TrainConfig(**base)


def params_of(model: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def assert_same_params(a: dict, b: dict, atol: float = 0.0) -> None:
    assert a.keys() == b.keys()
    for k in a:
        diff = (a[k] - b[k]).abs().max().item()
        assert diff <= atol, f"{k}: max difference {diff:.3e} (allowed {atol:.1e})"


def read_log(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def strip_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if not k.startswith(("frames_per_s", "time_s"))} for r in rows]


# ---- optimisation semantics ----

def _cos(start: float, end: float, pct: float) -> float:
    return end + (start - end) / 2 * (math.cos(math.pi * pct) + 1)


def test_onecycle_lr_and_beta1_follow_the_formula():
    """Cosine one cycle: lr/div -> lr over pct_start of the steps, then -> lr/div/1e4; beta1 0.95 -> 0.85
    -> 0.95 (OpenPCDet's adam_onecycle), checked at every step of a 50-step run."""
    cfg = config(lr=0.003, div_factor=10.0, pct_start=0.4, moms=(0.95, 0.85), weight_decay=0.01)
    total = 50
    opt, sched = build_optimizer(nn.Linear(3, 2), cfg, total, 10)
    assert isinstance(opt, torch.optim.AdamW) and opt.param_groups[0]["betas"][1] == 0.99
    peak = cfg.pct_start * total - 1  # torch's indexing: the peak is step 19
    low, floor = cfg.lr / cfg.div_factor, cfg.lr / cfg.div_factor / 1e4
    lrs = []
    for s in range(total):
        if s <= peak:
            lr, b1 = _cos(low, cfg.lr, s / peak), _cos(0.95, 0.85, s / peak)
        else:
            pct = (s - peak) / (total - 1 - peak)
            lr, b1 = _cos(cfg.lr, floor, pct), _cos(0.85, 0.95, pct)
        g = opt.param_groups[0]
        lrs.append(g["lr"])
        assert g["lr"] == pytest.approx(lr, rel=1e-9, abs=1e-15), f"lr at step {s}"
        assert g["betas"][0] == pytest.approx(b1, rel=1e-9), f"beta1 at step {s}"
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(low) and max(lrs) == lrs[19] == pytest.approx(cfg.lr)
    assert lrs[-1] == pytest.approx(floor)


def test_weight_decay_is_decoupled():
    """With a zero gradient the Adam update is zero; AdamW still multiplies by 1 - lr * wd (OpenPCDet's
    true_wd), where L2-coupled Adam would leave the weight unchanged."""
    p = nn.Parameter(torch.full((4,), 2.0, dtype=torch.float64))
    opt, _ = build_optimizer([p], config(weight_decay=0.01), 50, 10)
    lr0 = opt.param_groups[0]["lr"]
    p.grad = torch.zeros_like(p)
    opt.step()
    assert torch.allclose(p.detach(), torch.full((4,), 2.0 * (1 - lr0 * 0.01), dtype=torch.float64), rtol=0, atol=1e-15)


def test_adam_step_decay_schedule():
    """adam / adamw: lr times LR_DECAY at each DECAY_STEP_LIST epoch, never below LR_CLIP."""
    cfg = config(optimizer="adam", lr=0.01, decay_epochs=(2, 3, 4), lr_decay=0.1, lr_clip=5e-5)
    opt, sched = build_optimizer(nn.Linear(2, 2), cfg, 60, 10)
    assert type(opt) is torch.optim.Adam
    lrs = []
    for _ in range(60):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[19] == pytest.approx(0.01) and lrs[20] == pytest.approx(0.001)
    assert lrs[30] == pytest.approx(1e-4) and lrs[40] == pytest.approx(5e-5) and lrs[59] == pytest.approx(5e-5)


def test_from_openpcdet_reads_pointpillar_optimization():
    block = {"BATCH_SIZE_PER_GPU": 4, "NUM_EPOCHS": 80, "OPTIMIZER": "adam_onecycle", "LR": 0.003,
             "WEIGHT_DECAY": 0.01, "MOMENTUM": 0.9, "MOMS": [0.95, 0.85], "PCT_START": 0.4, "DIV_FACTOR": 10,
             "DECAY_STEP_LIST": [35, 45], "LR_DECAY": 0.1, "LR_CLIP": 0.0000001, "LR_WARMUP": False,
             "WARMUP_EPOCH": 1, "GRAD_NORM_CLIP": 10}
    cfg = TrainConfig.from_openpcdet({"OPTIMIZATION": block}, amp="bf16")
    assert (cfg.batch_size, cfg.epochs, cfg.optimizer, cfg.lr, cfg.weight_decay) == (4, 80, "adam_onecycle", 0.003, 0.01)
    assert (cfg.moms, cfg.pct_start, cfg.div_factor, cfg.grad_norm_clip, cfg.amp) == ((0.95, 0.85), 0.4, 10, 10, "bf16")
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match=r"OPTIMIZER 'sgd' is not supported.*adam_onecycle"):
        TrainConfig.from_openpcdet({**block, "OPTIMIZER": "sgd"})
    with pytest.raises(ValueError, match=r"unsupported OPTIMIZATION keys \['LR_SCHEDULE'\]"):
        TrainConfig.from_openpcdet({**block, "LR_SCHEDULE": "poly"})
    with pytest.raises(ValueError, match="LR_WARMUP"):
        TrainConfig.from_openpcdet({**block, "LR_WARMUP": True})
    with pytest.raises(ValueError, match="amp must be one of"):
        TrainConfig(amp="fp8")


# ---- the step ----

def test_gradients_are_clipped_before_the_step(tmp_path):
    """A global optimizer pre-step hook sees the gradient norm the optimizer uses: <= GRAD_NORM_CLIP, while
    the logged (pre-clip) norm is far above it; without clipping the hook sees the large norm."""
    seen = []

    def hook(opt, args, kwargs):
        seen.append(torch.norm(torch.stack([p.grad.norm() for g in opt.param_groups for p in g["params"]])).item())

    handle = register_optimizer_step_pre_hook(hook)
    try:
        fit(ToyModel(loss_scale=1000.0), ToyFrames(16), collate, config(epochs=2, grad_norm_clip=0.5), tmp_path / "a")
        clipped, seen[:] = list(seen), []
        fit(ToyModel(loss_scale=1000.0), ToyFrames(16), collate, config(epochs=2, grad_norm_clip=None), tmp_path / "b")
    finally:
        handle.remove()
    assert len(clipped) == 8 and max(clipped) <= 0.5 * (1 + 1e-5), clipped
    logged = [float(r["grad_norm"]) for r in read_log(tmp_path / "a" / "log.csv")]
    assert min(logged) > 5.0, logged
    assert min(seen) > 5.0, seen


@pytest.mark.parametrize("amp", ["bf16", "fp16"])
def test_amp_runs_on_cpu(tmp_path, amp):
    model = ToyModel()
    before = params_of(model)
    result = fit(model, ToyFrames(16), collate, config(amp=amp, epochs=2), tmp_path)
    want = torch.bfloat16 if amp == "bf16" else torch.float16
    assert model.autocast_dtypes == [want] * 8
    assert result.finished and math.isfinite(result.losses["loss"])
    for k, v in params_of(model).items():
        assert v.dtype == torch.float32 and torch.isfinite(v).all() and not torch.equal(v, before[k]), k
    scaler_state = load_checkpoint(tmp_path / "final.pth")["scaler_state"]
    assert (scaler_state is not None) == (amp == "fp16")


def test_model_without_loss_gets_a_clear_error(tmp_path):
    class NoLoss(ToyModel):
        def forward(self, batch):
            return {"total": super().forward(batch)["loss"]}

    with pytest.raises(ValueError, match=r"must return a dict with a scalar tensor 'loss'.*\['total'\]"):
        fit(NoLoss(), ToyFrames(8), collate, config(), tmp_path / "a")

    class VectorLoss(ToyModel):
        def forward(self, batch):
            return {"loss": (self.net(batch["x"]) - batch["y"]).pow(2).mean(-1)}

    with pytest.raises(ValueError, match=r"'loss'\] must be a scalar tensor.*shape \(4,\)"):
        fit(VectorLoss(), ToyFrames(8), collate, config(), tmp_path / "b")


# ---- checkpoints ----

def test_checkpoint_contents(tmp_path):
    """A training checkpoint is a lidarops.checkpoint file that says which model it holds (from model.config)."""
    extra = {"data_recipe": {"scenario": "toy"}, "train_command": "lidarops train --config toy.yaml"}
    model = ToyModel()
    model.config = ToyConfig(hidden=8, class_names=["Car", "Pedestrian"])
    result = fit(model, ToyFrames(10), collate, config(epochs=2), tmp_path, extra_checkpoint=extra)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["checkpoint_epoch_1.pth", "checkpoint_epoch_2.pth", "final.pth", "latest.pth", "log.csv",
                     "summary.json", "train.log"]  # no temporary files left behind
    assert result.checkpoint == tmp_path / "final.pth" and result.global_step == 6
    ckpt = load_checkpoint(tmp_path / "final.pth")
    assert ckpt["format"] == "lidarops.checkpoint" and ckpt["format_version"] == 2
    assert ckpt["version"].startswith("lidarops+") and ckpt["lidarops_version"] == lidarops.__version__
    assert (ckpt["epoch"], ckpt["step_in_epoch"], ckpt["it"], ckpt["steps_per_epoch"], ckpt["world_size"]) == (2, 0, 6, 3, 1)
    assert_same_params(ckpt["model_state"], params_of(model))
    assert ckpt["optimizer_state"]["state"][0]["step"].item() == 6
    assert ckpt["scheduler_state"]["last_epoch"] == 6 and ckpt["scaler_state"] is None
    assert TrainConfig.from_dict(ckpt["config"]) == config(epochs=2)
    assert set(ckpt["rng"][0]) == {"torch", "numpy", "python"} and len(ckpt["rng"]) == 1
    assert ckpt["model_class"] == "ToyModel" and ckpt["class_names"] == ["Car", "Pedestrian"]
    assert ckpt["model_config"] == {"hidden": 8, "class_names": ["Car", "Pedestrian"]}
    assert ckpt["data_recipe"] == extra["data_recipe"] and ckpt["train_command"] == extra["train_command"]
    # the model's own entries are the trainer's to write: an extra one is refused, naming it
    with pytest.raises(ValueError, match=r"\['model_config'\] are reserved"):
        fit(ToyModel(), ToyFrames(10), collate, config(epochs=1), tmp_path / "again",
            extra_checkpoint={"model_config": {"hidden": 8}})
    # a model without a config: the class is still recorded
    fit(ToyModel(), ToyFrames(10), collate, config(epochs=1), tmp_path / "plain")
    plain = load_checkpoint(tmp_path / "plain" / "final.pth")
    assert plain["model_class"] == "ToyModel" and "model_config" not in plain and "class_names" not in plain
    first = load_checkpoint(tmp_path / "checkpoint_epoch_1.pth")
    assert (first["epoch"], first["it"]) == (1, 3)
    log = read_log(tmp_path / "log.csv")
    assert [int(r["step"]) for r in log] == [1, 2, 3, 4, 5, 6]
    assert {"lr", "beta1", "grad_norm", "loss", "loss_abs", "frames_per_s", "frames_per_s_total"} <= set(log[0])
    assert "not_a_scalar" not in log[0]


def test_load_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "nope.pth")
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(ValueError, match="not a lidarops checkpoint: torch.load failed"):
        load_checkpoint(tmp_path / "text.pth")
    torch.save({"model_state": {}, "epoch": 3}, tmp_path / "pcdet.pth")
    with pytest.raises(ValueError, match="looks like an OpenPCDet checkpoint"):
        load_checkpoint(tmp_path / "pcdet.pth")
    # a shipped model (lidarops 0.1's layout: model_state + model_config) holds nothing to resume
    torch.save({"model_state": {}, "model_config": {}}, tmp_path / "shipped.pth")
    with pytest.raises(ValueError, match=r"without training state.*lidarops.models.load_model"):
        load_checkpoint(tmp_path / "shipped.pth")
    fit(ToyModel(), ToyFrames(8), collate, config(epochs=1, optimizer="adamw"), tmp_path / "run")
    ckpt = torch.load(tmp_path / "run" / "final.pth", weights_only=True)
    del ckpt["rng"], ckpt["optimizer_state"]
    torch.save(ckpt, tmp_path / "damaged.pth")
    with pytest.raises(ValueError, match=r"missing keys \['optimizer_state', 'rng'\]"):
        load_checkpoint(tmp_path / "damaged.pth")


def test_fit_guards(tmp_path):
    fit(ToyModel(), ToyFrames(8), collate, config(epochs=1, optimizer="adamw"), tmp_path)
    with pytest.raises(FileExistsError, match="resume=True"):
        fit(ToyModel(), ToyFrames(8), collate, config(epochs=1, optimizer="adamw"), tmp_path)
    with pytest.raises(ValueError, match=r"different optimisation: lr 0.003 -> 0.01"):
        fit(ToyModel(), ToyFrames(8), collate, config(epochs=1, optimizer="adamw", lr=0.01), tmp_path, resume=True)
    with pytest.raises(TypeError, match=r"extra_checkpoint\['recipe'\] is a object"):
        fit(ToyModel(), ToyFrames(8), collate, config(), tmp_path / "b", extra_checkpoint={"recipe": object()})
    with pytest.raises(ValueError, match=r"keys \['epoch'\] are reserved"):
        fit(ToyModel(), ToyFrames(8), collate, config(), tmp_path / "b", extra_checkpoint={"epoch": 1})


def test_keep_last_epoch_checkpoints(tmp_path):
    fit(ToyModel(), ToyFrames(8), collate, config(epochs=5, keep_last=2), tmp_path)
    assert sorted(p.name for p in tmp_path.glob("checkpoint_epoch_*.pth")) == ["checkpoint_epoch_4.pth",
                                                                                "checkpoint_epoch_5.pth"]


# ---- resume ----

N_FRAMES = 22  # batches of 4: 6 steps an epoch, the last of 2 frames; 3 epochs = 18 steps


def _straight(tmp_path, **kw):
    model = ToyModel(dropout=0.2)
    data = ToyFrames(N_FRAMES, noise=0.1)
    result = fit(model, data, collate, config(**kw), tmp_path / "straight")
    return model, data, result


@pytest.mark.parametrize("num_workers", [0, 2])
def test_resume_mid_epoch_is_identical(tmp_path, num_workers):
    """Straight 18 steps vs 8 steps (stopped mid-epoch 2), then a resume into a fresh model: identical
    parameters, optimizer state and log (dropout and epoch-seeded augmentation included)."""
    ref_model, ref_data, ref = _straight(tmp_path, num_workers=num_workers)
    assert ref.finished and ref.global_step == 18
    assert ref_data.epochs_set == [0, 1, 2] and ref_model.epochs_seen == [0] * 22 + [1] * 22 + [2] * 22
    run = tmp_path / "split"
    first = fit(ToyModel(dropout=0.2), ToyFrames(N_FRAMES, noise=0.1), collate,
                config(num_workers=num_workers, max_steps=8), run)
    assert (first.stop_reason, first.epoch, first.step_in_epoch, first.global_step) == ("max_steps", 1, 2, 8)
    assert not (run / "final.pth").exists()
    model = ToyModel(dropout=0.2, seed=123)  # different initial weights: everything must come from the checkpoint
    second = fit(model, ToyFrames(N_FRAMES, noise=0.1), collate, config(num_workers=num_workers), run, resume=True)
    assert second.finished and second.steps == 10 and second.global_step == 18
    assert model.epochs_seen == [1] * 14 + [2] * 22  # the first 2 batches of epoch 2 are not loaded again
    assert_same_params(params_of(model), params_of(ref_model))
    a, b = load_checkpoint(ref.checkpoint), load_checkpoint(second.checkpoint)
    for k, v in a["optimizer_state"]["state"][0].items():
        assert torch.equal(v, b["optimizer_state"]["state"][0][k]), k
    assert strip_timing(read_log(run / "log.csv")) == strip_timing(read_log(tmp_path / "straight" / "log.csv"))


def test_resume_after_a_crash_redoes_only_the_lost_steps(tmp_path, monkeypatch):
    """A kill in step 11, after latest.pth was written at step 9 (every 30 s of a fake clock, 10 s a
    step): resuming takes steps 10..18 once more, and ends where the straight run does."""
    ref_model, _, _ = _straight(tmp_path)
    clock = FakeClock()
    monkeypatch.setattr(train_loop, "_clock", clock)
    run = tmp_path / "crash"
    with pytest.raises(RuntimeError, match="simulated kill"):
        fit(ToyModel(dropout=0.2, clock=clock, crash_at=11), ToyFrames(N_FRAMES, noise=0.1), collate,
            config(ckpt_every_min=0.5), run)
    latest = load_checkpoint(run / "latest.pth")
    assert (latest["it"], latest["epoch"], latest["step_in_epoch"]) == (9, 1, 3)
    assert not list(run.glob(".*.tmp"))
    model = ToyModel(dropout=0.2, seed=7)
    result = fit(model, ToyFrames(N_FRAMES, noise=0.1), collate, config(ckpt_every_min=0.5), run, resume=True)
    assert result.steps == 9 and result.global_step == 18
    assert_same_params(params_of(model), params_of(ref_model))


def test_max_minutes_stops_at_a_step_boundary_and_resumes(tmp_path, monkeypatch):
    """A 1-minute budget at 10 s a step: each call takes 6 steps, stops with latest.pth before a step
    that would end past the budget, and three calls equal the straight run."""
    ref_model, _, _ = _straight(tmp_path)
    run = tmp_path / "budget"
    model = None
    for call in range(3):
        clock = FakeClock()
        monkeypatch.setattr(train_loop, "_clock", clock)
        model = ToyModel(dropout=0.2, seed=call, clock=clock)
        result = fit(model, ToyFrames(N_FRAMES, noise=0.1), collate, config(max_minutes=1.0), run, resume=call > 0)
        assert clock.t <= 60.0 and result.steps == 6 and result.global_step == 6 * (call + 1)
        assert result.stop_reason == ("finished" if call == 2 else "max_minutes")
        assert load_checkpoint(result.checkpoint)["it"] == 6 * (call + 1)
    assert_same_params(params_of(model), params_of(ref_model))


# ---- evaluation and throughput ----

def recording_evaluator(sink: list, predictions, frames):
    sink.append((predictions, frames))
    err = torch.stack([p["y"] for p in predictions]) - torch.stack([f["y"] for f in frames])
    return {"frames": len(predictions), "mse": err.pow(2).sum(-1).mean().item()}, f"{len(predictions)} frames"


def collate_with_targets(items):
    return {**collate(items), "y_list": [it["y"] for it in items], "y": torch.stack([it["y"] for it in items])}


def _eval_frames(frames):
    return [{"y": f["y_list"], "frame_id": f["frame_id"]} for f in frames]


def test_evaluation_every_k_epochs_in_dataset_order(tmp_path):
    sink = []

    def evaluator(predictions, frames):
        torch.rand(3), np.random.rand(), random.random()  # an evaluator drawing random numbers (bootstrap ...)
        return recording_evaluator(sink, predictions, _eval_frames(frames))

    model = ToyModel(dropout=0.2)
    result = fit(model, ToyFrames(N_FRAMES, noise=0.1), collate_with_targets, config(eval_every=2), tmp_path,
                 val_dataset=ToyFrames(7, seed=5), evaluator=evaluator)
    assert sorted(p.name for p in tmp_path.glob("eval_epoch_*.json")) == ["eval_epoch_2.json", "eval_epoch_3.json"]
    report = json.loads((tmp_path / "eval_epoch_3.json").read_text())
    assert report["metrics"] == result.metrics and report["metrics"]["frames"] == 7 and report["global_step"] == 18
    assert "7 frames" in (tmp_path / "train.log").read_text()
    predictions, frames = sink[-1]
    assert [f["frame_id"] for f in frames] == list(range(7))
    val = ToyFrames(7, seed=5)
    model.eval()
    with torch.no_grad():
        expected = model.net(val.x)
    for i, p in enumerate(predictions):
        assert p["y"].device.type == "cpu" and int(p["frame_id"]) == i
        assert torch.allclose(p["y"], expected[i], rtol=0, atol=1e-6)
    # evaluation leaves the training RNG alone: same parameters as without it
    ref_model, _, _ = _straight(tmp_path)
    assert_same_params(params_of(model), params_of(ref_model))
    # the same evaluation on its own (what `lidarops eval` calls), in batches of another size
    metrics, text = evaluate(model, val, collate_with_targets, evaluator, batch_size=3, device="cpu")
    assert metrics == pytest.approx(result.metrics, rel=1e-6) and text == "7 frames"


def test_throughput_is_reported(tmp_path):
    result = fit(ToyModel(), ToyFrames(N_FRAMES), collate, config(log_every=3), tmp_path)
    assert result.frames_per_s > 0 and result.frames_per_s_total == result.frames_per_s
    assert result.train_seconds > 0 and result.world_size == 1
    rows = read_log(tmp_path / "log.csv")
    assert [int(r["step"]) for r in rows] == [3, 6, 9, 12, 15, 18]
    assert all(float(r["frames_per_s"]) > 0 for r in rows)


class SlowFrames(ToyFrames):
    """Frames whose loading moves a fake clock 0.25 s each."""

    def __init__(self, n: int, clock: FakeClock) -> None:
        super().__init__(n)
        self.clock = clock

    def __getitem__(self, i: int) -> dict:
        self.clock.t += 0.25
        return super().__getitem__(i)


def test_data_wait_is_measured(tmp_path, monkeypatch):
    """The time spent fetching batches (a loader in the main process here, on a clock only loading moves)."""
    clock = FakeClock()
    monkeypatch.setattr(train_loop, "_clock", clock)

    result = fit(ToyModel(), SlowFrames(8, clock), collate, config(epochs=2), tmp_path)
    assert result.data_seconds == pytest.approx(0.25 * 16)
    assert result.train_seconds == pytest.approx(result.data_seconds)  # nothing else moved the clock
    assert "(100 % waiting for data)" in (tmp_path / "train.log").read_text()


def test_summary_json_says_where_the_time_went(tmp_path, monkeypatch):
    """summary.json: training (data wait within it), evaluation and checkpoint time apart, on a clock only
    loading (0.25 s a frame), steps (2 s each) and the evaluator (3 s a call) move."""
    clock = FakeClock()
    monkeypatch.setattr(train_loop, "_clock", clock)

    def evaluator(predictions, frames):
        clock.t += 3.0
        return {"frames": float(len(predictions))}, ""

    result = fit(ToyModel(clock=clock, step_seconds=2.0), SlowFrames(8, clock), collate, config(epochs=2, eval_every=1),
                 tmp_path, val_dataset=ToyFrames(5, seed=3), evaluator=evaluator)
    summary = json.loads((tmp_path / "summary.json").read_text())
    # 2 epochs x 2 steps of 4 frames: 16 frames loaded (4 s), 4 steps (8 s); 2 evaluations (6 s)
    assert summary["frames"] == 16 and summary["steps"] == 4 and summary["world_size"] == 1
    assert summary["train_seconds"] == pytest.approx(12.0) and summary["eval_seconds"] == pytest.approx(6.0)
    assert summary["ranks"] == [{"rank": 0, "frames": 16, "steps": 4, "train_seconds": pytest.approx(12.0),
                                 "data_seconds": pytest.approx(4.0), "frames_per_s": pytest.approx(12 / 9)}]
    assert summary["wall_seconds"] == pytest.approx(18.0)  # nothing else moved the clock
    assert summary["global_batch_size"] == 4 and summary["metrics"] == {"frames": 5.0}
    assert result.eval_seconds == pytest.approx(6.0) and result.wall_seconds == pytest.approx(18.0)


# ---- DDP on CPU (gloo, 2 processes) ----

DDP_BATCH = 4  # per process; the single-process reference takes 8


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_config(batch_size: int) -> TrainConfig:
    return config(epochs=3, batch_size=batch_size, grad_norm_clip=0.5)


def _gathering_evaluator(path, predictions, frames):
    torch.save({"frame_id": [f["frame_id"] for f in frames], "y": torch.stack([p["y"] for p in predictions]),
                "pred_frame_id": [int(p["frame_id"]) for p in predictions]}, path)
    return {"frames": len(predictions)}, ""


def _ddp_worker(rank: int, world: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    result = fit(ToyModel(), ToyFrames(2 * DDP_BATCH), collate, _ddp_config(DDP_BATCH), out_dir,
                 val_dataset=ToyFrames(7, seed=5),
                 evaluator=functools.partial(_gathering_evaluator, os.path.join(out_dir, "gathered.pt")))
    with open(os.path.join(out_dir, f"result_{rank}.json"), "w") as f:
        json.dump({"world_size": result.world_size, "fps": result.frames_per_s, "fps_total": result.frames_per_s_total,
                   "metrics": result.metrics, "global_step": result.global_step}, f)
    # The worker exits normally, and its exit code is checked: a process group that outlived fit (held by DDP's
    # reducer) was torn down in Python's exit, where a gloo rank could abort as its peer tore down (SIGABRT).


@pytest.fixture(scope="module")
def ddp_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ddp")
    procs = torch.multiprocessing.spawn(_ddp_worker, args=(2, _free_port(), str(out)), nprocs=2, join=False)
    deadline = time.monotonic() + 120
    while not procs.join(timeout=2):
        if time.monotonic() > deadline:
            for p in procs.processes:
                p.kill()
            pytest.fail("the 2-process DDP run did not finish in 120 s")
    return out


@pytest.mark.slow
def test_ddp_matches_one_process_on_the_concatenated_batch(ddp_run, tmp_path):
    """2 processes x 4 frames == 1 process x 8 frames, for 3 steps (one cycle, clipping on): DDP averages
    the gradients of per-process mean losses. (BatchNorm would differ: each rank normalises with its own
    frames unless sync_bn.)"""
    ref = ToyModel()
    fit(ref, ToyFrames(2 * DDP_BATCH), collate, _ddp_config(2 * DDP_BATCH), tmp_path)
    ckpt = load_checkpoint(ddp_run / "final.pth")
    assert ckpt["world_size"] == 2 and ckpt["it"] == 3 and len(ckpt["rng"]) == 2
    assert_same_params(ckpt["model_state"], params_of(ref), atol=1e-6)
    results = [json.loads((ddp_run / f"result_{r}.json").read_text()) for r in range(2)]
    assert all(r["world_size"] == 2 and r["global_step"] == 3 for r in results)
    assert results[0]["fps_total"] == pytest.approx(results[0]["fps"] + results[1]["fps"])
    summary = json.loads((ddp_run / "summary.json").read_text())  # written once, by rank 0, of both ranks
    assert summary["world_size"] == 2 and summary["global_batch_size"] == 2 * DDP_BATCH
    assert [r["rank"] for r in summary["ranks"]] == [0, 1]
    assert [r["frames"] for r in summary["ranks"]] == [3 * DDP_BATCH] * 2 and summary["frames"] == 6 * DDP_BATCH
    assert summary["frames_per_s_total"] == pytest.approx(results[0]["fps_total"])


@pytest.mark.slow
def test_ddp_evaluation_gathers_every_frame_once(ddp_run):
    """7 validation frames over 2 ranks (4 + 3, no sampler padding): each once, in dataset order, with the
    metrics on both ranks."""
    gathered = torch.load(ddp_run / "gathered.pt", weights_only=True)
    assert gathered["frame_id"] == list(range(7)) and gathered["pred_frame_id"] == list(range(7))
    model = ToyModel()
    model.load_state_dict(load_checkpoint(ddp_run / "final.pth")["model_state"])
    with torch.no_grad():
        expected = model.net(ToyFrames(7, seed=5).x)
    assert torch.allclose(gathered["y"], expected, atol=1e-6)
    results = [json.loads((ddp_run / f"result_{r}.json").read_text()) for r in range(2)]
    assert results[0]["metrics"] == results[1]["metrics"] == {"frames": 7.0}
