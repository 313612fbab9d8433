"""Optimizers and learning-rate schedules with OpenPCDet's semantics, built from torch's own classes.

``adam_onecycle`` (OpenPCDet ``tools/train_utils/optimization``): OpenPCDet wraps ``optim.Adam(betas=(0.9,
0.99))`` in fastai's ``OptimWrapper(true_wd=True, bn_wd=True)``, which multiplies every parameter by
``1 - lr * wd`` before the Adam step -- exactly ``torch.optim.AdamW``'s decoupled decay, over one parameter
group. Its ``OneCycle`` anneals lr with ``annealing_cos`` from ``lr / div_factor`` to ``lr`` over
``pct_start`` of the steps, then to ``lr / div_factor / 1e4``, and beta1 from ``moms[0]`` to ``moms[1]`` and
back -- ``torch.optim.lr_scheduler.OneCycleLR`` with ``max_momentum, base_momentum = moms`` and
``final_div_factor=1e4`` (it cycles ``betas[0]`` for Adam-type optimizers, with the same cosine).
One difference of indexing: torch places the peak at step ``pct_start * total - 1`` and ends exactly at the
floor lr at step ``total - 1``; OpenPCDet peaks at step ``int(pct_start * total)`` and stops one step
short of the floor.
"""
from __future__ import annotations

from typing import Iterable

import torch
from torch import nn

from lidarops.train.config import TrainConfig

__all__ = ["build_optimizer"]

ONECYCLE_FINAL_DIV = 1e4


def build_optimizer(params: nn.Module | Iterable[torch.Tensor], config: TrainConfig, total_steps: int,
                    steps_per_epoch: int) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    """The optimizer and its per-step scheduler (call ``scheduler.step()`` after every ``optimizer.step()``).

    Args:
        params: a module or its parameters (one group, as OpenPCDet).
        config: ``optimizer``, ``lr``, ``weight_decay``, ``moms``, ``pct_start``, ``div_factor``,
            ``decay_epochs``, ``lr_decay``, ``lr_clip``.
        total_steps (int): optimisation steps of the whole run (``epochs * steps_per_epoch``).
        steps_per_epoch (int): for the epoch-based decay of ``adam``/``adamw``.
    """
    if isinstance(params, nn.Module):
        params = params.parameters()
    params = [p for p in params if p.requires_grad]
    if total_steps < 1:
        raise ValueError(f"total_steps must be >= 1, got {total_steps}")
    if config.optimizer == "adam_onecycle":
        # OneCycleLR's first phase ends at step pct_start * total - 1; it must lie after step 0
        if config.pct_start * total_steps <= 1:
            raise ValueError(f"adam_onecycle needs pct_start * total_steps > 1, got {config.pct_start} * "
                             f"{total_steps}: train longer or raise pct_start")
        optimizer = torch.optim.AdamW(params, lr=config.lr, betas=(config.moms[0], 0.99),
                                      weight_decay=config.weight_decay)
        scheduler = torch.optim.lr_scheduler.OneCycleLR(
            optimizer, max_lr=config.lr, total_steps=total_steps, pct_start=config.pct_start,
            anneal_strategy="cos", cycle_momentum=True, max_momentum=config.moms[0],
            base_momentum=config.moms[1], div_factor=config.div_factor, final_div_factor=ONECYCLE_FINAL_DIV)
        return optimizer, scheduler
    cls = torch.optim.Adam if config.optimizer == "adam" else torch.optim.AdamW
    optimizer = cls(params, lr=config.lr, weight_decay=config.weight_decay)
    decay_steps = [e * steps_per_epoch for e in config.decay_epochs]
    floor = config.lr_clip / config.lr

    def factor(step: int) -> float:
        f = 1.0
        for s in decay_steps:
            if step >= s:
                f *= config.lr_decay
        return max(f, floor)

    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
