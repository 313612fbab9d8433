"""Training checkpoints: the training state in the one checkpoint format (:mod:`lidarops.checkpoint`),
read back for resuming, RNG states, pruning.

A training checkpoint is a :mod:`lidarops.checkpoint` file (``format``, ``model_class``, ``model_config``,
``class_names``, ``model_state`` ...) that also holds::

    optimizer_state   optimizer.state_dict()              scheduler_state  scheduler.state_dict()
    scaler_state      GradScaler.state_dict() or None (amp != "fp16")
    epoch             epochs completed (OpenPCDet's key)   step_in_epoch    steps done in the next epoch
    it                optimisation steps taken in all (OpenPCDet's accumulated_iter)
    steps_per_epoch, world_size, eval_pending (the epoch-end evaluation still to run on resume)
    elapsed_s, frames  training wall time and frames (per process) so far
    config            TrainConfig.to_dict()
    rng               per rank: {"torch", "numpy", "python", "cuda" (when on CUDA)}
    ... plus the caller's ``extra_checkpoint`` entries (config path, data recipe, training command).
"""
from __future__ import annotations

import os
import random
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from lidarops.checkpoint import FORMAT, FORMAT_VERSION, CheckpointError, check_plain, read_checkpoint, save_checkpoint

__all__ = ["CHECKPOINT_FORMAT", "REQUIRED_KEYS", "load_checkpoint", "save_checkpoint", "capture_rng_state",
           "restore_rng_state", "prune_epoch_checkpoints", "check_plain"]

CHECKPOINT_FORMAT = FORMAT
# the training checkpoints of lidarops 0.1 (format_version 1) resume too
_TRAIN_FORMATS = (FORMAT, "lidarops.train.checkpoint")
REQUIRED_KEYS = ("format_version", "version", "lidarops_version", "model_state", "optimizer_state",
                 "scheduler_state", "scaler_state", "epoch", "step_in_epoch", "it", "steps_per_epoch",
                 "world_size", "eval_pending", "elapsed_s", "frames", "config", "rng")
RESERVED_KEYS = frozenset(REQUIRED_KEYS) | {"format", "model_class", "model_config", "class_names"}
_EPOCH_FILE = re.compile(r"^checkpoint_epoch_(\d+)\.pth$")


def load_checkpoint(path: str | os.PathLike, map_location: Any = "cpu", weights_only: bool = True) -> dict[str, Any]:
    """A training checkpoint as a dict (see the module docstring for the keys), to resume from.

    Args:
        path: a ``.pth`` file written by :func:`lidarops.train.fit`.
        map_location: as ``torch.load``.
        weights_only (bool): kept for compatibility; checkpoints are always read with ``weights_only=True``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a lidarops training checkpoint (e.g. an OpenPCDet one: load its
            ``model_state`` with ``model.load_state_dict``; a shipped model: ``lidarops.models.load_model``),
            or lacks keys of the format.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = read_checkpoint(path, map_location)
    except CheckpointError as e:
        raise CheckpointError(f"{path} is not a lidarops checkpoint: torch.load failed ({e})") from None
    if ckpt.get("format") not in _TRAIN_FORMATS:
        what = f"a dict with keys {sorted(map(str, ckpt))[:12]}"
        if "model_state" in ckpt and "model_config" in ckpt:
            hint = (" (a model without training state, e.g. a shipped one: build it with "
                    "lidarops.models.load_model(path))")
        elif "model_state" in ckpt:
            hint = " (it looks like an OpenPCDet checkpoint: load ckpt['model_state'] with model.load_state_dict)"
        else:
            hint = ""
        raise CheckpointError(f"{path} is not a lidarops checkpoint: expected format {CHECKPOINT_FORMAT!r}, "
                              f"found {what}{hint}")
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if not any(k in ckpt for k in ("optimizer_state", "scheduler_state", "rng", "epoch", "it", "step_in_epoch")):
        raise CheckpointError(f"{path} holds a model without training state (a shipped or exported model), nothing "
                              "to resume: build it with lidarops.models.load_model(path)")
    if missing:
        raise CheckpointError(f"{path} is a damaged lidarops checkpoint: missing keys {missing}")
    if ckpt["format_version"] > FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {ckpt['format_version']}, newer than this lidarops "
                              f"reads ({FORMAT_VERSION}): upgrade lidarops")
    return ckpt


def capture_rng_state(device: torch.device | None = None) -> dict[str, Any]:
    """This process's RNG states: torch (CPU), numpy's global, python's ``random``, CUDA of ``device``."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state = {"torch": torch.get_rng_state(), "python": random.getstate(),
             "numpy": {"name": name, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                       "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}}
    if device is not None and device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def restore_rng_state(state: Mapping[str, Any], device: torch.device | None = None) -> None:
    """Inverse of :func:`capture_rng_state`."""
    torch.set_rng_state(state["torch"].cpu())
    random.setstate(_as_tuples(state["python"]))
    n = state["numpy"]
    np.random.set_state((n["name"], n["keys"].cpu().numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    if device is not None and device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"].cpu(), device)


def _as_tuples(x):
    return tuple(_as_tuples(v) for v in x) if isinstance(x, (list, tuple)) else x


def prune_epoch_checkpoints(out_dir: Path, keep_last: int | None) -> list[Path]:
    """Deletes all but the newest ``keep_last`` ``checkpoint_epoch_*.pth``; returns the deleted paths."""
    if keep_last is None:
        return []
    found = sorted((int(m.group(1)), p) for p in Path(out_dir).iterdir() if (m := _EPOCH_FILE.match(p.name)))
    doomed = [p for _, p in found[:max(len(found) - keep_last, 0)]]
    for p in doomed:
        p.unlink(missing_ok=True)
    return doomed
