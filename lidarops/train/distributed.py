"""The process group of a run: torchrun's environment, the device, and small collectives on a CPU group.

Launch::

    torchrun --standalone --nproc_per_node=G train_script.py ...

``torchrun`` sets ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK``; :meth:`DistContext.from_env` then joins the
default group with NCCL on CUDA, gloo on CPU (or uses a group the caller already made). Decisions taken from
rank 0's clock (stop, checkpoint now) and Python objects (RNG states, predictions) travel on a separate
gloo group, so they neither touch the GPU nor wait for its queue. Without those variables everything runs
in one process with no group at all.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist

__all__ = ["DistContext", "resolve_device"]


def resolve_device(device: str | torch.device, local_rank: int = 0) -> torch.device:
    """``"auto"`` -> ``cuda:LOCAL_RANK`` when CUDA is available, else ``cpu``; ``"cuda"`` -> ``cuda:LOCAL_RANK``."""
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise RuntimeError(f"device {device!r} asked for but torch sees no CUDA device")
        if dev.index is None:
            dev = torch.device("cuda", local_rank)
    return dev


@dataclass
class DistContext:
    """Rank, world size and device of this process, and the collectives the trainer needs."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    owns_group: bool = False
    control_group: Any = None

    @classmethod
    def from_env(cls, device: str | torch.device = "auto") -> "DistContext":
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if dist.is_available() and dist.is_initialized():
            rank, world, owns = dist.get_rank(), dist.get_world_size(), False
        else:
            rank, world, owns = int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1")), False
        dev = resolve_device(device, local_rank)
        if dev.type == "cuda":
            torch.cuda.set_device(dev)
        ctx = cls(rank=rank, world_size=world, local_rank=local_rank, device=dev)
        if world > 1:
            if not dist.is_initialized():
                # device_id binds this rank's GPU: NCCL need not guess it from the rank, and barriers use it
                dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo",
                                        device_id=dev if dev.type == "cuda" else None)
                owns = True
            ctx.owns_group = owns
            ctx.control_group = (dist.new_group(backend="gloo") if dist.get_backend() != "gloo"
                                 else dist.group.WORLD)
        return ctx

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier(group=self.control_group)

    def from_main(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every rank."""
        if not self.distributed:
            return obj
        box = [obj]
        dist.broadcast_object_list(box, src=0, group=self.control_group)
        return box[0]

    def agree(self, flags: list[bool]) -> list[bool]:
        """Rank 0's flags on every rank (decisions that must be the same everywhere)."""
        if not self.distributed:
            return flags
        t = torch.tensor([int(f) for f in flags], dtype=torch.uint8)
        dist.broadcast(t, src=0, group=self.control_group)
        return [bool(v) for v in t.tolist()]

    def gather_to_main(self, obj: Any) -> list[Any] | None:
        """Every rank's ``obj`` as a list on rank 0 (rank order); None elsewhere."""
        if not self.distributed:
            return [obj]
        out = [None] * self.world_size if self.is_main else None
        dist.gather_object(obj, out, dst=0, group=self.control_group)
        return out

    def sum(self, value: float) -> float:
        """The sum of ``value`` over ranks, on every rank."""
        if not self.distributed:
            return value
        t = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(t, group=self.control_group)
        return float(t.item())

    def close(self) -> None:
        """Leaves the group if this context made it (else only its control group)."""
        if not self.distributed or not dist.is_initialized():
            return
        # a rank that tears gloo down while another still sends aborts the process at exit; bounded, so that
        # a rank that died (an error path) cannot hang the others here
        try:
            dist.monitored_barrier(group=self.control_group, timeout=timedelta(seconds=60))
        except RuntimeError:
            pass
        if self.owns_group:
            dist.destroy_process_group()
        elif self.control_group is not dist.group.WORLD:
            dist.destroy_process_group(self.control_group)
