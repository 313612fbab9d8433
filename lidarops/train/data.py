"""Data loading for the trainer: per-epoch sample order, resumable loaders, batches on the device.

The order of an epoch is ``DistributedSampler(shuffle=True, seed=seed)`` after ``set_epoch(epoch)``: a
permutation drawn from ``seed + epoch`` alone, padded to a multiple of the world size and dealt out
rank by rank. A resumed epoch takes the same order and drops the batches already done, so no sample is
loaded twice. Worker processes are seeded from ``(seed, epoch, rank)``; datasets whose augmentation must
be bit-identical across a mid-epoch resume with workers should draw it from a generator seeded by
``(epoch, index)`` (set through ``set_epoch``), since a resumed epoch deals its batches to workers in a
different rotation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler

__all__ = ["move_to_device", "frame_meta", "EpochLoader", "shard_indices", "batch_lengths", "make_loader"]


def move_to_device(obj: Any, device: torch.device, non_blocking: bool = False) -> Any:
    """Tensors moved to ``device``, recursively through dicts, lists and tuples; anything else as is."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device, non_blocking=non_blocking)
    if isinstance(obj, dict):
        return {k: move_to_device(v, device, non_blocking) for k, v in obj.items()}
    if isinstance(obj, list):
        return [move_to_device(v, device, non_blocking) for v in obj]
    if isinstance(obj, tuple):
        moved = [move_to_device(v, device, non_blocking) for v in obj]
        return type(obj)(*moved) if hasattr(obj, "_fields") else tuple(moved)
    return obj


def frame_meta(batch: dict[str, Any], num_frames: int) -> list[dict[str, Any]]:
    """Per-frame metadata of a batch: its list- or tuple-valued keys of length ``num_frames``
    (``frame_id``, ``annos``, ``calib`` ...), split by frame, tensors moved to the CPU."""
    keys = [k for k, v in batch.items() if isinstance(v, (list, tuple)) and len(v) == num_frames]
    return [{k: move_to_device(batch[k][i], torch.device("cpu")) for k in keys} for i in range(num_frames)]


def batch_lengths(num_indices: int, batch_size: int) -> list[int]:
    """Frames in each batch when ``num_indices`` samples are cut into batches (the last one short)."""
    full, rest = divmod(num_indices, batch_size)
    return [batch_size] * full + ([rest] if rest else [])


def shard_indices(n: int, rank: int, world_size: int) -> list[int]:
    """Evaluation shard of a rank: ``rank, rank + world, ...`` -- every index exactly once over the ranks
    (no padding, unlike ``DistributedSampler``)."""
    return list(range(rank, n, world_size))


def _seed_worker(worker_id: int) -> None:
    # torch already seeds python's random and numpy in workers from the loader generator; made explicit
    # so that a dataset seeing np.random in a worker gets the documented (seed, epoch, rank, worker) stream
    import random

    import numpy as np

    seed = torch.initial_seed() % 2**32
    random.seed(seed)
    np.random.seed(seed)


def make_loader(dataset: Dataset, indices: Sequence[int], batch_size: int, collate_fn: Callable | None,
                num_workers: int, pin_memory: bool, seed: int) -> DataLoader:
    """A loader over ``indices`` in that order, in batches of ``batch_size`` (the last one short)."""
    g = torch.Generator()
    g.manual_seed(seed)
    return DataLoader(dataset, batch_size=batch_size, sampler=list(indices), collate_fn=collate_fn,
                      num_workers=num_workers, pin_memory=pin_memory, drop_last=False, generator=g,
                      worker_init_fn=_seed_worker if num_workers > 0 else None)


@dataclass
class EpochLoader:
    """The training batches of each epoch for one rank, restartable at any batch."""

    dataset: Dataset
    batch_size: int
    collate_fn: Callable | None
    num_workers: int
    seed: int
    rank: int
    world_size: int
    pin_memory: bool = False

    def __post_init__(self) -> None:
        if len(self.dataset) == 0:
            raise ValueError("the training dataset is empty")
        self.sampler = DistributedSampler(self.dataset, num_replicas=self.world_size, rank=self.rank, shuffle=True,
                                          seed=self.seed, drop_last=False)

    @property
    def steps_per_epoch(self) -> int:
        return math.ceil(len(self.sampler) / self.batch_size)

    def epoch(self, epoch: int, skip_batches: int = 0) -> tuple[DataLoader, list[int]]:
        """The loader of ``epoch`` starting at batch ``skip_batches``, and the frame count of each batch it
        yields. Calls ``dataset.set_epoch(epoch)`` first (before workers copy the dataset)."""
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)
        self.sampler.set_epoch(epoch)
        indices = list(self.sampler)[skip_batches * self.batch_size:]
        worker_seed = ((self.seed * 1_000_003 + epoch) * 65_537 + self.rank) % 2**63
        loader = make_loader(self.dataset, indices, self.batch_size, self.collate_fn, self.num_workers,
                             self.pin_memory, worker_seed)
        return loader, batch_lengths(len(indices), self.batch_size)
