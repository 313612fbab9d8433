"""Checkpoint files: atomic writes, loading with clear errors, RNG states, pruning.

A checkpoint is one ``torch.save`` dict (loadable with ``weights_only=True``)::

    format            "lidarops.train.checkpoint"        format_version  1
    version           "lidarops+<version>"  (OpenPCDet's key)   lidarops_version "<version>"
    model_state       the model's state_dict (no DDP "module." prefix; OpenPCDet's key)
    optimizer_state   optimizer.state_dict()              scheduler_state  scheduler.state_dict()
    scaler_state      GradScaler.state_dict() or None (amp != "fp16")
    epoch             epochs completed (OpenPCDet's key)   step_in_epoch    steps done in the next epoch
    it                optimisation steps taken in all (OpenPCDet's accumulated_iter)
    steps_per_epoch, world_size, eval_pending (the epoch-end evaluation still to run on resume)
    elapsed_s, frames  training wall time and frames (per process) so far
    config            TrainConfig.to_dict()
    rng               per rank: {"torch", "numpy", "python", "cuda" (when on CUDA)}
    ... plus the caller's ``extra_checkpoint`` entries (model config, class names, data recipe).
"""
from __future__ import annotations

import os
import random
import re
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

__all__ = ["CHECKPOINT_FORMAT", "REQUIRED_KEYS", "load_checkpoint", "save_checkpoint", "capture_rng_state",
           "restore_rng_state", "prune_epoch_checkpoints", "check_plain"]

CHECKPOINT_FORMAT = "lidarops.train.checkpoint"
FORMAT_VERSION = 1
REQUIRED_KEYS = ("format_version", "version", "lidarops_version", "model_state", "optimizer_state",
                 "scheduler_state", "scaler_state", "epoch", "step_in_epoch", "it", "steps_per_epoch",
                 "world_size", "eval_pending", "elapsed_s", "frames", "config", "rng")
RESERVED_KEYS = frozenset(REQUIRED_KEYS) | {"format"}
_EPOCH_FILE = re.compile(r"^checkpoint_epoch_(\d+)\.pth$")


def save_checkpoint(state: Mapping[str, Any], paths: list[Path]) -> None:
    """Writes ``state`` to each path atomically: a temporary file in the same folder, then ``os.replace``,
    so a kill at any moment leaves either the previous file or the new one."""
    first = None
    for path in paths:
        path = Path(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                if first is None:
                    torch.save(dict(state), f)
                else:
                    with open(first, "rb") as src:
                        while chunk := src.read(1 << 24):
                            f.write(chunk)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        first = first or path


def load_checkpoint(path: str | os.PathLike, map_location: Any = "cpu", weights_only: bool = True) -> dict[str, Any]:
    """A lidarops checkpoint as a dict (see the module docstring for the keys).

    Args:
        path: a ``.pth`` file written by :func:`lidarops.train.fit`.
        map_location: as ``torch.load``.
        weights_only (bool): as ``torch.load``; lidarops checkpoints hold only plain values and tensors.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a lidarops checkpoint (e.g. an OpenPCDet one: load its
            ``model_state`` with ``model.load_state_dict``), or lacks keys of the format.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=weights_only)
    except Exception as e:
        raise ValueError(f"{path} is not a lidarops checkpoint: torch.load failed ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from e
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        what = f"a dict with keys {sorted(map(str, ckpt))[:12]}" if isinstance(ckpt, dict) else type(ckpt).__name__
        hint = (" (it looks like an OpenPCDet checkpoint: load ckpt['model_state'] with model.load_state_dict)"
                if isinstance(ckpt, dict) and "model_state" in ckpt else "")
        raise ValueError(f"{path} is not a lidarops checkpoint: expected format {CHECKPOINT_FORMAT!r}, "
                         f"found {what}{hint}")
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise ValueError(f"{path} is a damaged lidarops checkpoint: missing keys {missing}")
    if ckpt["format_version"] > FORMAT_VERSION:
        raise ValueError(f"{path} has checkpoint format {ckpt['format_version']}, newer than this lidarops "
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


_PLAIN = (str, int, float, bool, type(None), torch.Tensor)


def check_plain(value: Any, where: str = "extra_checkpoint") -> None:
    """Raises ``TypeError`` unless ``value`` is made of dicts (str keys), lists, tuples, str, numbers,
    None and tensors: what ``torch.load(weights_only=True)`` reads back."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: keys must be str, got {k!r}")
            check_plain(v, f"{where}[{k!r}]")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            check_plain(v, f"{where}[{i}]")
    elif not isinstance(value, _PLAIN):
        raise TypeError(f"{where} is a {type(value).__name__}; checkpoints hold only dicts, lists, str, numbers, "
                        f"None and tensors (convert dataclasses with dataclasses.asdict)")
