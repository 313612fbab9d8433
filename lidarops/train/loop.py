"""The training loop shared by every lidarops model: :func:`fit` and :func:`evaluate`.

Resume contract: a checkpoint records the position ``(epoch, step_in_epoch)``, the optimizer, scheduler and
scaler states and every rank's RNG states, taken at a step boundary before the next batch is fetched. An
epoch's sample order is a function of ``(seed, epoch)``, so resuming skips the batches already done and
takes exactly the steps that followed the checkpoint, whatever killed the run after it (SIGKILL included):
no step is lost or taken twice relative to that checkpoint.
"""
from __future__ import annotations

import contextlib
import gc
import json
import os
import random
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from lidarops.checkpoint import check_plain, format_fields, model_fields, save_checkpoint
from lidarops.train.checkpoint import (RESERVED_KEYS, capture_rng_state, load_checkpoint, prune_epoch_checkpoints,
                                       restore_rng_state)
from lidarops.train.config import RESUMABLE_CHANGES, TrainConfig
from lidarops.train.data import EpochLoader, batch_lengths, frame_meta, make_loader, move_to_device, shard_indices
from lidarops.train.distributed import DistContext
from lidarops.train.optim import build_optimizer
from lidarops.train.protocol import Evaluator
from lidarops.train.runlog import RunLog

__all__ = ["fit", "evaluate", "FitResult"]

# The wall clock of time budgets and checkpoint intervals (tests replace it).
_clock: Callable[[], float] = time.monotonic


@dataclass
class FitResult:
    """What :func:`fit` did.

    Attributes:
        checkpoint: ``final.pth`` when the run finished, else ``latest.pth`` (resume from it).
        finished: all epochs done.
        stop_reason: ``"finished"``, ``"max_minutes"`` or ``"max_steps"``.
        epoch, step_in_epoch, global_step: the position reached (epochs completed, steps into the next).
        steps: optimisation steps taken in this call.
        frames_per_s: training frames per second of one process in this call (its first step, the warm-up,
            left out when there are others); frames_per_s_total: summed over the processes.
        train_seconds: wall time of those steps.
        data_seconds: of ``train_seconds``, the time this process waited for its next batch (the data
            pipeline's share: near 0 when loading keeps up with the GPU).
        eval_seconds, checkpoint_seconds: time spent evaluating and writing checkpoints in this call (not in
            ``train_seconds``).
        wall_seconds: the whole call, start-up included.
        losses: the last logged loss terms (rank 0).
        metrics: the last evaluation's metrics (every rank), or None.
    """

    out_dir: Path
    checkpoint: Path
    finished: bool
    stop_reason: str
    epoch: int
    step_in_epoch: int
    global_step: int
    steps: int
    world_size: int
    frames_per_s: float
    frames_per_s_total: float
    train_seconds: float
    data_seconds: float
    eval_seconds: float = 0.0
    checkpoint_seconds: float = 0.0
    wall_seconds: float = 0.0
    losses: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, float] | None = None


def _loss_of(out: Any, check: bool) -> Tensor:
    if not isinstance(out, Mapping) or "loss" not in out:
        what = f"a dict with keys {sorted(out)}" if isinstance(out, Mapping) else type(out).__name__
        raise ValueError("model(batch) in train mode must return a dict with a scalar tensor 'loss' (the mean "
                         f"over the batch's frames) and other scalar tensors to log; got {what}")
    loss = out["loss"]
    if check and not (isinstance(loss, Tensor) and loss.numel() == 1 and loss.requires_grad):
        what = (f"a tensor of shape {tuple(loss.shape)}, requires_grad={loss.requires_grad}"
                if isinstance(loss, Tensor) else type(loss).__name__)
        raise ValueError(f"model(batch)['loss'] must be a scalar tensor that requires grad; got {what}")
    return loss.reshape(())


def _scalars(out: Mapping[str, Any]) -> dict[str, float]:
    return {k: float(v.detach()) if isinstance(v, Tensor) else float(v) for k, v in out.items()
            if (isinstance(v, Tensor) and v.numel() == 1) or isinstance(v, (int, float))}


@contextlib.contextmanager
def _rng_untouched(device: torch.device):
    """Whatever runs inside leaves the RNG states as they were (evaluation must not shift training)."""
    state = capture_rng_state(device)
    try:
        yield
    finally:
        restore_rng_state(state, device)


def _evaluate(module: nn.Module, dataset: Dataset, collate_fn: Callable | None, evaluator: Evaluator,
              batch_size: int, num_workers: int, ctx: DistContext) -> tuple[dict[str, float], str]:
    """Every rank predicts its shard; rank 0 puts the frames in dataset order and calls the evaluator;
    the metrics come back to every rank (the text only to rank 0)."""
    postprocess = getattr(module, "postprocess", None)
    if not callable(postprocess):
        raise TypeError(f"{type(module).__name__} has no postprocess(raw, batch) method: evaluation needs it")
    indices = shard_indices(len(dataset), ctx.rank, ctx.world_size)
    loader = make_loader(dataset, indices, batch_size, collate_fn, num_workers, ctx.device.type == "cuda", 0)
    was_training = module.training
    module.eval()
    records = []
    done = 0
    try:
        with torch.no_grad():
            for batch, n in zip(loader, batch_lengths(len(indices), batch_size)):
                on_device = move_to_device(batch, ctx.device, non_blocking=True)
                preds = postprocess(module(on_device), on_device)
                if len(preds) != n:
                    raise ValueError(f"postprocess returned {len(preds)} predictions for a batch of {n} frames")
                metas = frame_meta(batch, n)
                cpu = torch.device("cpu")
                records += [(indices[done + j], move_to_device(preds[j], cpu), metas[j]) for j in range(n)]
                done += n
    finally:
        module.train(was_training)
    gathered = ctx.gather_to_main(records)
    result = None
    if ctx.is_main:
        frames = sorted((r for part in gathered for r in part), key=lambda r: r[0])
        if [r[0] for r in frames] != list(range(len(dataset))):
            raise RuntimeError("evaluation did not gather every validation frame exactly once")
        metrics, text = evaluator([r[1] for r in frames], [r[2] for r in frames])
        result = ({k: float(v) for k, v in metrics.items()}, str(text))
    metrics = ctx.from_main(result[0] if result else None)
    return metrics, (result[1] if result else "")


def evaluate(model: nn.Module, dataset: Dataset, collate_fn: Callable | None, evaluator: Evaluator, *,
             batch_size: int = 1, num_workers: int = 0, device: str = "auto") -> tuple[dict[str, float], str]:
    """Evaluates ``model`` on ``dataset`` (under ``torchrun``: sharded over the processes, gathered on rank 0).

    Returns:
        ``(metrics, text)`` from ``evaluator(predictions, frames)`` (text is empty on ranks other than 0).
    """
    ctx = DistContext.from_env(device)
    try:
        model.to(ctx.device)
        return _evaluate(model, dataset, collate_fn, evaluator, batch_size, num_workers, ctx)
    finally:
        ctx.close()


class _Run:
    """One call of :func:`fit`: the state of the run and the steps that move it."""

    def __init__(self, model: nn.Module, train_dataset: Dataset, collate_fn: Callable | None, config: TrainConfig,
                 out_dir: Path, val_dataset: Dataset | None, evaluator: Evaluator | None,
                 extra: dict[str, Any], ctx: DistContext) -> None:
        self.config, self.out_dir, self.ctx = config, out_dir, ctx
        self.collate_fn, self.val_dataset, self.evaluator, self.extra = collate_fn, val_dataset, evaluator, extra
        self.call_start = _clock()
        self.loader = EpochLoader(train_dataset, config.batch_size, collate_fn, config.num_workers, config.seed,
                                  ctx.rank, ctx.world_size, pin_memory=ctx.device.type == "cuda")
        self.steps_per_epoch = self.loader.steps_per_epoch
        self.module = model.to(ctx.device)
        if config.sync_bn and ctx.distributed and ctx.device.type == "cuda":
            self.module = nn.SyncBatchNorm.convert_sync_batchnorm(self.module)
        self.optimizer, self.scheduler = build_optimizer(self.module, config, config.epochs * self.steps_per_epoch,
                                                         self.steps_per_epoch)
        self.scaler = torch.amp.GradScaler(ctx.device.type) if config.amp == "fp16" else None
        self.amp_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(config.amp)
        self.params = [p for p in self.module.parameters() if p.requires_grad]
        # the position and the counters carried by checkpoints
        self.epoch = self.step_in_epoch = self.global_step = 0
        self.eval_pending = False
        self.elapsed_before = 0.0
        self.frames_before = 0
        # this call's measurements
        self.steps = 0
        self.frames = 0
        self.train_seconds = 0.0
        self.data_seconds = 0.0
        self.first_step = (0, 0.0)  # (frames, seconds) of the warm-up step
        self.step_estimate = 0.0
        self.ckpt_seconds = 0.0
        self.eval_seconds = 0.0
        self.ckpt_total = self.eval_total = 0.0  # this call's sums (the two above are the last ones)
        self.last_ckpt = self.call_start
        self.losses: dict[str, float] = {}
        self.metrics: dict[str, float] | None = None
        self.ddp_model: nn.Module = self.module
        self.log: RunLog | None = None

    def start(self, resumed: bool) -> None:
        """After :meth:`restore`: wraps the model for DDP and opens the logs (trimmed to the checkpoint)."""
        c, ctx = self.config, self.ctx
        if ctx.distributed:
            self.ddp_model = nn.parallel.DistributedDataParallel(
                self.module, device_ids=[ctx.device.index] if ctx.device.type == "cuda" else None,
                find_unused_parameters=c.find_unused_parameters)
        self.log = RunLog(self.out_dir, ctx.is_main, self.global_step if resumed else None, c.tensorboard,
                          c.progress)

    # ---- checkpoints ----
    def restore(self, ckpt: dict[str, Any]) -> None:
        saved = ckpt["config"]
        mine = self.config.to_dict()
        changed = sorted(k for k in mine if k not in RESUMABLE_CHANGES and k in saved and saved[k] != mine[k])
        if changed:
            raise ValueError("cannot resume with a different optimisation: "
                             + ", ".join(f"{k} {saved[k]!r} -> {mine[k]!r}" for k in changed)
                             + f" (only {sorted(RESUMABLE_CHANGES)} may change)")
        if ckpt["world_size"] != self.ctx.world_size or ckpt["steps_per_epoch"] != self.steps_per_epoch:
            raise ValueError(f"cannot resume: the checkpoint ran {ckpt['world_size']} process(es) with "
                             f"{ckpt['steps_per_epoch']} steps per epoch, this run has {self.ctx.world_size} with "
                             f"{self.steps_per_epoch} (same world size and dataset needed)")
        self.module.load_state_dict(ckpt["model_state"])
        self.optimizer.load_state_dict(ckpt["optimizer_state"])
        self.scheduler.load_state_dict(ckpt["scheduler_state"])
        if self.scaler is not None and ckpt["scaler_state"] is not None:
            self.scaler.load_state_dict(ckpt["scaler_state"])
        self.epoch, self.step_in_epoch, self.global_step = ckpt["epoch"], ckpt["step_in_epoch"], ckpt["it"]
        self.eval_pending = bool(ckpt["eval_pending"])
        self.elapsed_before, self.frames_before = float(ckpt["elapsed_s"]), int(ckpt["frames"])
        restore_rng_state(ckpt["rng"][self.ctx.rank], self.ctx.device)

    def checkpoint(self, names: list[str]) -> None:
        """Writes the current state to ``out_dir/<name>`` for each name (all ranks call it)."""
        t0 = _clock()
        rng = self.ctx.gather_to_main(capture_rng_state(self.ctx.device))
        if self.ctx.is_main:
            state = {
                **format_fields(), **model_fields(self.module),
                "model_state": self.module.state_dict(), "optimizer_state": self.optimizer.state_dict(),
                "scheduler_state": self.scheduler.state_dict(),
                "scaler_state": self.scaler.state_dict() if self.scaler is not None else None,
                "epoch": self.epoch, "step_in_epoch": self.step_in_epoch, "it": self.global_step,
                "steps_per_epoch": self.steps_per_epoch, "world_size": self.ctx.world_size,
                "eval_pending": self.eval_pending, "elapsed_s": self.elapsed(), "frames": self.frames_before + self.frames,
                "config": self.config.to_dict(), "rng": rng, **self.extra,
            }
            save_checkpoint(state, [self.out_dir / n for n in names])
        self.ctx.barrier()
        self.last_ckpt = _clock()
        self.ckpt_seconds = self.last_ckpt - t0
        self.ckpt_total += self.ckpt_seconds

    def elapsed(self) -> float:
        return self.elapsed_before + (_clock() - self.call_start)

    # ---- decisions (rank 0's clock, agreed by all) ----
    def budget_left(self) -> float:
        if self.config.max_minutes is None:
            return float("inf")
        return self.config.max_minutes * 60.0 - (_clock() - self.call_start)

    def decide(self) -> tuple[str | None, bool]:
        """Before a step: stop (and why) and whether to write ``latest.pth`` now."""
        c = self.config
        by_steps = c.max_steps is not None and self.global_step >= c.max_steps
        by_time = self.budget_left() < self.step_estimate + self.ckpt_seconds
        save = c.ckpt_every_min is not None and _clock() - self.last_ckpt >= c.ckpt_every_min * 60.0
        by_steps, by_time, save = self.ctx.agree([by_steps, by_time, save])
        return ("max_steps" if by_steps else "max_minutes" if by_time else None), save

    # ---- the step ----
    def train_step(self, batch: Any) -> tuple[dict[str, Any], Tensor | None]:
        batch = move_to_device(batch, self.ctx.device, non_blocking=True)
        self.optimizer.zero_grad(set_to_none=True)
        with (torch.autocast(self.ctx.device.type, dtype=self.amp_dtype) if self.amp_dtype is not None
              else contextlib.nullcontext()):
            out = self.ddp_model(batch)
        loss = _loss_of(out, check=self.steps == 0)
        if self.scaler is not None:
            self.scaler.scale(loss).backward()
            self.scaler.unscale_(self.optimizer)
        else:
            loss.backward()
        clip = self.config.grad_norm_clip
        grad_norm = nn.utils.clip_grad_norm_(self.params, clip) if clip else None
        if self.scaler is not None:
            self.scaler.step(self.optimizer)
            self.scaler.update()
        else:
            self.optimizer.step()
        group = self.optimizer.param_groups[0]
        self.step_lr = (group["lr"], group["betas"][0] if "betas" in group else None)  # this step's values
        if self.scaler is None:
            self.scheduler.step()
        else:  # the scaler skips the optimizer on overflow; the schedule advances regardless (by design)
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step")
                self.scheduler.step()
        return out, grad_norm

    def log_row(self, out: Mapping[str, Any], grad_norm: Tensor | None, interval: tuple[int, float]) -> None:
        self.losses = _scalars(out)
        fps = interval[0] / max(interval[1], 1e-9)
        row: dict[str, Any] = {"step": self.global_step, "epoch": self.epoch + 1, "lr": self.step_lr[0]}
        if self.step_lr[1] is not None:
            row["beta1"] = self.step_lr[1]
        if grad_norm is not None:
            row["grad_norm"] = float(grad_norm)
        row.update(self.losses)
        row.update(frames_per_s=fps, frames_per_s_total=fps * self.ctx.world_size, time_s=self.elapsed())
        self.log.row(row)
        self.log.step(self.step_in_epoch, {k: v for k, v in row.items() if k not in ("step", "epoch", "time_s",
                                                                                     "frames_per_s_total")})

    def run_eval(self) -> None:
        t0 = _clock()
        with _rng_untouched(self.ctx.device):  # a resumed run skips or repeats evaluations: keep them neutral
            self.metrics, text = _evaluate(self.module, self.val_dataset, self.collate_fn, self.evaluator,
                                           self.config.batch_size, self.config.num_workers, self.ctx)
        self.eval_seconds = _clock() - t0
        self.eval_total += self.eval_seconds
        self.eval_pending = False
        if self.ctx.is_main:
            report = {"epoch": self.epoch, "global_step": self.global_step, "metrics": self.metrics, "text": text}
            (self.out_dir / f"eval_epoch_{self.epoch}.json").write_text(json.dumps(report, indent=2) + "\n")
            # the headline per class (KITTI's moderate 3D AP, R40); the whole table follows in ``text``
            # and every metric is in the JSON and the scalars log
            head = {k: v for k, v in self.metrics.items() if k.endswith("_3d_moderate_R40")} or \
                dict(list(self.metrics.items())[:6])
            shown = ", ".join(f"{k} {v:.4g}" for k, v in head.items())
            self.log.say(f"eval after epoch {self.epoch} (step {self.global_step}): {shown}"
                         + (f"\n{text}" if text else ""))
            self.log.scalars("eval", self.metrics, self.global_step)

    def eval_due(self) -> bool:
        c = self.config
        if self.val_dataset is None or self.evaluator is None:
            return False
        return self.epoch == c.epochs or (c.eval_every > 0 and self.epoch % c.eval_every == 0)

    # ---- the loop ----
    def run(self) -> str:
        c = self.config
        if self.eval_pending:
            self.run_eval()
        while self.epoch < c.epochs:
            loader, lengths = self.loader.epoch(self.epoch, self.step_in_epoch)
            self.log.start_epoch(self.epoch, c.epochs, self.steps_per_epoch, self.step_in_epoch)
            batches = iter(loader)
            interval = [0, 0.0]
            t_prev = _clock()
            for n in lengths:
                # decided, and saved, before the next batch is fetched: a data pipeline drawing from the
                # main process's RNG (num_workers=0) then sees the same states after a resume
                reason, save = self.decide()
                if reason or save:
                    self.checkpoint(["latest.pth"])
                    t_prev = _clock()  # the write is not training time
                if reason:
                    self.log.end_epoch()
                    return reason
                t_fetch = _clock()
                batch = next(batches)
                self.data_seconds += _clock() - t_fetch
                out, grad_norm = self.train_step(batch)
                del batch
                self.step_in_epoch += 1
                self.global_step += 1
                self.steps += 1
                log_now = self.global_step % c.log_every == 0 or self.step_in_epoch == self.steps_per_epoch
                if log_now and self.ctx.device.type == "cuda":
                    torch.cuda.synchronize(self.ctx.device)
                now = _clock()
                dt, t_prev = now - t_prev, now
                self.frames += n
                self.train_seconds += dt
                interval[0] += n
                interval[1] += dt
                if self.steps == 1:
                    self.first_step = (n, dt)
                self.step_estimate = max(self.step_estimate if self.steps > 2 else 0.0, dt)
                if log_now:
                    self.log_row(out, grad_norm, (interval[0], interval[1]))
                    interval = [0, 0.0]
                else:
                    self.log.step(self.step_in_epoch, None)
            del batches
            self.log.end_epoch()
            self.epoch += 1
            self.step_in_epoch = 0
            self.eval_pending = self.eval_due()
            self.checkpoint([f"checkpoint_epoch_{self.epoch}.pth", "latest.pth"])
            if self.ctx.is_main:
                prune_epoch_checkpoints(self.out_dir, c.keep_last)
            if self.eval_pending:
                skip = self.ctx.agree([self.eval_seconds > 0 and self.budget_left() < self.eval_seconds])[0]
                if skip:
                    return "max_minutes"
                self.run_eval()
        return "finished"

    def throughput(self) -> tuple[float, float]:
        frames, seconds = self.frames, self.train_seconds
        if self.steps > 1:  # leave the warm-up step out
            frames, seconds = frames - self.first_step[0], seconds - self.first_step[1]
        fps = frames / seconds if seconds > 0 else 0.0
        return fps, self.ctx.sum(fps)


def _share(part: float, whole: float) -> str:
    return f"{100 * part / whole:.0f} %" if whole > 0 else "0 %"


def _write_summary(path: Path, run: "_Run", reason: str, ctx: DistContext, fps_total: float, wall: float,
                   ranks: list[dict]) -> None:
    """``summary.json``: what this call of :func:`fit` did and where its time went, every process's share
    beside the others' (the slowest data pipeline or a straggler shows there)."""
    device = ctx.device
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    c = run.config
    summary = {
        "stop_reason": reason, "epoch": run.epoch, "global_step": run.global_step, "steps": run.steps,
        "world_size": ctx.world_size, "device": name, "batch_size_per_process": c.batch_size,
        "global_batch_size": c.batch_size * ctx.world_size, "lr": c.lr, "amp": c.amp, "sync_bn": c.sync_bn,
        "num_workers": c.num_workers, "trainable_parameters": sum(p.numel() for p in run.params),
        "frames": sum(r["frames"] for r in ranks),
        "frames_per_s_total": fps_total, "train_seconds": run.train_seconds, "eval_seconds": run.eval_total,
        "checkpoint_seconds": run.ckpt_total, "wall_seconds": wall, "ranks": ranks,
        "losses": run.losses, "metrics": run.metrics,
    }
    path.write_text(json.dumps(summary, indent=2) + "\n")


def _seed_all(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


def fit(model: nn.Module, train_dataset: Dataset, collate_fn: Callable | None, config: TrainConfig,
        out_dir: str | os.PathLike, val_dataset: Dataset | None = None, evaluator: Evaluator | None = None,
        resume: bool | str | os.PathLike = False, extra_checkpoint: dict[str, Any] | None = None) -> FitResult:
    """Trains ``model`` (in place) with ``config``; one process, or one per GPU under ``torchrun``.

    Args:
        model: a :class:`~lidarops.train.TrainableModel` (``model(batch)["loss"]`` in train mode,
            ``model.postprocess(raw, batch)`` for evaluation).
        train_dataset, collate_fn: frames and the function batching them into a dict.
        config: see :class:`~lidarops.train.TrainConfig`.
        out_dir: ``log.csv``, ``train.log``, ``checkpoint_epoch_{e}.pth``, ``latest.pth``, ``final.pth``,
            ``eval_epoch_{e}.json``, ``tensorboard/``.
        val_dataset, evaluator: evaluation every ``config.eval_every`` epochs and after the last.
        resume: False starts a new run (refused if ``out_dir/latest.pth`` exists); True continues from
            ``out_dir/latest.pth`` when present; a path continues from that checkpoint.
        extra_checkpoint: entries added to every checkpoint (the model's resolved config, class names, the
            data recipe): dicts, lists, str, numbers, None and tensors.

    Returns:
        :class:`FitResult`. A run stopped by ``max_minutes`` or ``max_steps`` is continued by calling
        :func:`fit` again with ``resume=True``.
    """
    out = Path(out_dir)
    extra = dict(extra_checkpoint or {})
    check_plain(extra)
    clash = sorted(set(extra) & RESERVED_KEYS)
    if clash:
        raise ValueError(f"extra_checkpoint keys {clash} are reserved by the checkpoint format")
    ckpt_path = None
    if resume is True:
        ckpt_path = out / "latest.pth" if (out / "latest.pth").exists() else None
    elif resume:
        ckpt_path = Path(resume)
    elif (out / "latest.pth").exists():
        raise FileExistsError(f"{out} already holds a run (latest.pth): pass resume=True to continue it, "
                              f"or choose another out_dir")
    ctx = DistContext.from_env(config.device)
    log = run = None
    try:
        if ctx.is_main:
            out.mkdir(parents=True, exist_ok=True)
        ctx.barrier()
        run = _Run(model, train_dataset, collate_fn, config, out, val_dataset, evaluator, extra, ctx)
        _seed_all(config.seed + ctx.rank)
        if ckpt_path is not None:
            run.restore(load_checkpoint(ckpt_path))
        run.start(resumed=ckpt_path is not None)
        log = run.log
        start = (f"resuming {ckpt_path} at epoch {run.epoch + 1}, step {run.step_in_epoch} of "
                 f"{run.steps_per_epoch} (global step {run.global_step})" if ckpt_path is not None
                 else "new run" + (" (no latest.pth to resume)" if resume is True else ""))
        log.say(f"lidarops.train: {start}; {ctx.world_size} process(es) on {ctx.device}, batch {config.batch_size} "
                f"per process, {run.steps_per_epoch} steps per epoch, {config.epochs} epochs")
        if config.sync_bn and not (ctx.distributed and ctx.device.type == "cuda"):
            log.say("sync_bn has no effect: it needs several processes on CUDA")
        reason = run.run()
        if reason == "finished":
            run.checkpoint(["final.pth", "latest.pth"])
        if ctx.device.type == "cuda":
            torch.cuda.synchronize(ctx.device)
        fps, fps_total = run.throughput()
        checkpoint = out / ("final.pth" if reason == "finished" else "latest.pth")
        wall = _clock() - run.call_start
        ranks = ctx.gather_to_main({"rank": ctx.rank, "frames": run.frames, "steps": run.steps,
                                    "train_seconds": run.train_seconds, "data_seconds": run.data_seconds,
                                    "frames_per_s": fps})
        if ctx.is_main:
            _write_summary(out / "summary.json", run, reason, ctx, fps_total, wall, ranks)
        log.say(f"{reason} at epoch {run.epoch}, step {run.step_in_epoch} (global step {run.global_step}); "
                f"{run.steps} steps in {run.train_seconds:.1f} s ({_share(run.data_seconds, run.train_seconds)} "
                f"waiting for data), {fps:.1f} frames/s per process, {fps_total:.1f} in all; checkpoint {checkpoint}"
                + ("" if reason == "finished" else " (continue with resume=True)"))
        return FitResult(out_dir=out, checkpoint=checkpoint, finished=reason == "finished", stop_reason=reason,
                         epoch=run.epoch, step_in_epoch=run.step_in_epoch, global_step=run.global_step,
                         steps=run.steps, world_size=ctx.world_size, frames_per_s=fps, frames_per_s_total=fps_total,
                         train_seconds=run.train_seconds, data_seconds=run.data_seconds,
                         eval_seconds=run.eval_total, checkpoint_seconds=run.ckpt_total, wall_seconds=wall,
                         losses=run.losses, metrics=run.metrics)
    finally:
        if log is not None:
            log.close()
        if run is not None and ctx.distributed:
            # DDP's reducer holds the process group: dropped here, the group goes when close() destroys it (after
            # its barrier) instead of in some later garbage collection or Python's exit, where a gloo rank can
            # abort while its peer tears down
            run.ddp_model = run.module
            gc.collect()
        ctx.close()
