"""One training loop for every lidarops model (PointPillars, CounterNet, CAS-Net ...), model-agnostic: it
imports no model, dataset or metric (those come in through :class:`TrainableModel`, the dataset, the
collate function and the :class:`Evaluator`).

::

    from lidarops.train import TrainConfig, fit, load_checkpoint

    config = TrainConfig.from_openpcdet(yaml_cfg["OPTIMIZATION"], num_workers=4, amp="bf16", max_minutes=9)
    result = fit(model, train_set, collate_fn, config, "runs/pp", val_dataset=val_set, evaluator=kitti_eval,
                 resume=True, extra_checkpoint={"data_recipe": {...}, "train_command": "..."})
    ckpt = load_checkpoint("runs/pp/final.pth")       # model.load_state_dict(ckpt["model_state"])
    model = lidarops.models.load_model("runs/pp/final.pth")   # or build the model the file names

Every checkpoint is a :mod:`lidarops.checkpoint` file: it records the model's class, config and class names
(from ``model.config``), so the model can be rebuilt from the file alone.

Multi-GPU: the same script under ``torchrun --standalone --nproc_per_node=G script.py`` (DDP, one process per
GPU, ``batch_size`` frames per process). The model contract is :class:`TrainableModel`; the optimisation
follows OpenPCDet (:mod:`lidarops.train.optim`); the checkpoint format is in :mod:`lidarops.train.checkpoint`.
"""
from __future__ import annotations

from lidarops.train.checkpoint import CHECKPOINT_FORMAT, load_checkpoint
from lidarops.train.config import TrainConfig
from lidarops.train.data import move_to_device
from lidarops.train.distributed import DistContext
from lidarops.train.loop import FitResult, evaluate, fit
from lidarops.train.optim import build_optimizer
from lidarops.train.protocol import Evaluator, TrainableModel

__all__ = ["TrainConfig", "fit", "evaluate", "FitResult", "load_checkpoint", "CHECKPOINT_FORMAT",
           "build_optimizer", "move_to_device", "DistContext", "TrainableModel", "Evaluator"]
