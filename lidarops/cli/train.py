"""``lidarops train``: trains a model from a config (OpenPCDet's schema) with the one training loop,
:func:`lidarops.train.fit`.

The config's ``MODEL.NAME`` picks, through :data:`TRAINABLE`, the model class, the datasets with their
collate function, and the evaluator run on the validation frames. Under ``torchrun`` the same command runs
DistributedDataParallel, one process per GPU. Every checkpoint names the model, its config and classes
(written by the trainer), the config file, the data recipe and this command line.

Examples::

    lidarops data synth --scenario driving_city driving_highway --frames 2000 1000 --workers 16 --out data/synth
    lidarops train --config configs/pointpillars/pointpillars_synth.yaml --data data/synth --out runs/pp --amp bf16
    lidarops train --config configs/pointpillars/pointpillars_synth.yaml --data data/synth --out runs/pp --resume
    lidarops train --config configs/casnet/casnet_pointnet_objects.yaml --out runs/cas_d4 --set MODEL.RATIO 4
    torchrun --standalone --nproc_per_node=2 -m lidarops train --config ... --out runs/pp2   # 2 GPUs
"""
from __future__ import annotations

import argparse
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from lidarops.cli.errors import CliError, guarded

__all__ = ["register", "train", "Trainable", "TRAINABLE"]


@dataclass(frozen=True)
class Trainable:
    """What ``lidarops train`` needs to train one kind of model (the functions import on call, so that
    building the parser imports no model, dataset or trainer).

    Attributes:
        model: the class's name in :data:`lidarops.models.MODELS`; the class is built from the whole config.
        datasets: ``(data folder, class names, config, args) -> (training set, validation set, collate_fn)``.
        evaluator: ``(class names, config) -> `` the evaluator :func:`lidarops.train.fit` runs on the validation set.
        summary: ``(metrics, class names) -> `` the line printed after an evaluation, or ``""``.
    """

    model: str
    datasets: Callable[[Path, Sequence[str], Mapping, argparse.Namespace], tuple]
    evaluator: Callable[[Sequence[str], Mapping], Any]
    summary: Callable[[Mapping[str, float], Sequence[str]], str]
    creates_data: Callable[[Mapping], bool] = lambda cfg: False  # the data folder is a cache the run fills


def _kitti_detection_datasets(root: Path, class_names: Sequence[str], cfg: Mapping, args: argparse.Namespace):
    """A KITTI-format folder's ``ImageSets/train.txt`` (augmented as ``DATA_CONFIG`` says, with gt sampling)
    and ``ImageSets/val.txt``, batched by OpenPCDet's collate."""
    from lidarops.data.detection import (DetectionConfig, KittiDetectionDataset, build_gt_database, collate_batch,
                                         train_val_datasets)

    data_cfg = DetectionConfig.from_openpcdet(cfg.get("DATA_CONFIG", {}))
    gt_database = None
    if args.gt_database_frames:  # OpenPCDet builds it from every training frame; a subset is quicker
        # training=False: the ids alone (a training dataset would first build the database from every frame)
        ids = KittiDetectionDataset(root, "train", class_names, data_cfg, training=False).ids[:args.gt_database_frames]
        gt_database = build_gt_database(root, ids, class_names)
    train_set, val_set = train_val_datasets(root, class_names, data_cfg, seed=args.seed or 0, gt_database=gt_database)
    if args.max_train_frames:
        train_set.ids = train_set.ids[:args.max_train_frames]
    if args.max_val_frames and val_set is not None:
        val_set.ids = val_set.ids[:args.max_val_frames]
    return train_set, val_set, collate_batch


def _kitti_evaluator(class_names: Sequence[str], cfg: Mapping):
    """KITTI's protocol on the camera's view; on the sensor's whole view (BEV and 3D, ground truths in the
    range) for models that see every point (``FOV_POINTS_ONLY: False``, e.g. the Aerial-PointPillars)."""
    from lidarops.eval.kitti import KittiEvaluator

    data = cfg.get("DATA_CONFIG", {})
    if data.get("FOV_POINTS_ONLY", True):
        return KittiEvaluator(class_names)
    return KittiEvaluator(class_names, camera=False, point_cloud_range=data.get("POINT_CLOUD_RANGE"))


def _kitti_summary(metrics: Mapping[str, float], class_names: Sequence[str]) -> str:
    keys = [f"{n}_3d_moderate_R40" for n in class_names] + [f"{n}_bev_moderate_R40" for n in class_names]
    shown = [f"{k.replace('_moderate_R40', '')} {metrics[k]:.1f}" for k in keys if k in metrics]
    return "moderate AP (R40): " + ", ".join(shown) if shown else ""


def _object_datasets(root: Path, class_names: Sequence[str], cfg: Mapping, args: argparse.Namespace):
    """Objects cut from simulated scenes (cached in the data folder) or ModelNet40, resampled to a fixed
    number of points, batched as ``points (B, N, C)``, ``labels (B,)``."""
    import os

    from lidarops.data.object_sets import datasets_from_config, without_single_object_batches

    train_set, test_set, collate = datasets_from_config(cfg, data_path=root, workers=args.workers or 0, log=print)
    if args.max_train_frames:
        train_set = train_set.subset(range(min(args.max_train_frames, len(train_set))))
    if args.max_val_frames:
        test_set = test_set.subset(range(min(args.max_val_frames, len(test_set))))
    batch = args.batch_size or cfg.get("OPTIMIZATION", {}).get("BATCH_SIZE_PER_GPU", 32)
    return without_single_object_batches(train_set, batch, int(os.environ.get("WORLD_SIZE", 1))), test_set, collate


def _classification_evaluator(class_names: Sequence[str], cfg: Mapping):
    from lidarops.eval.classification import ClassificationEvaluator

    return ClassificationEvaluator(class_names)


def _classification_summary(metrics: Mapping[str, float], class_names: Sequence[str]) -> str:
    if "accuracy" not in metrics:
        return ""
    return f"accuracy {metrics['accuracy']:.1f} %, mean class accuracy {metrics['mean_class_accuracy']:.1f} %"


def _counting_evaluator(class_names: Sequence[str], cfg: Mapping):
    from lidarops.eval.counting import CountingEvaluator

    return CountingEvaluator(class_names)


def _counting_summary(metrics: Mapping[str, float], class_names: Sequence[str]) -> str:
    if "counting_accuracy" not in metrics:
        return ""
    return (f"counting accuracy {metrics['counting_accuracy']:.1f} % (exact counts), mean absolute error "
            f"{metrics['count_mae']:.2f} objects per class and frame")


def _simulated_objects(cfg: Mapping) -> bool:
    """Whether the data folder is the object-set cache a first run simulates (rather than data to read)."""
    return cfg.get("DATA_CONFIG", {}).get("DATASET", "SimObjects") == "SimObjects"


_POINTPILLARS = Trainable(model="PointPillars", datasets=_kitti_detection_datasets, evaluator=_kitti_evaluator,
                          summary=_kitti_summary)

#: ``MODEL.NAME`` -> how to train it: the one table of what ``lidarops train`` trains. OpenPCDet's configs
#: name PointPillars ``PointPillar``; lidarops' checkpoints name the class.
TRAINABLE: dict[str, Trainable] = {
    "PointPillar": _POINTPILLARS,
    "PointPillars": _POINTPILLARS,
    "PointNet": Trainable(model="PointNet", datasets=_object_datasets, evaluator=_classification_evaluator,
                          summary=_classification_summary, creates_data=_simulated_objects),
    "CASNetPointNet": Trainable(model="CASNetPointNet", datasets=_object_datasets,
                                evaluator=_classification_evaluator, summary=_classification_summary,
                                creates_data=_simulated_objects),
    "CASNetPointPillars": Trainable(model="CASNetPointPillars", datasets=_kitti_detection_datasets,
                                    evaluator=_kitti_evaluator, summary=_kitti_summary),
    "CounterNet": Trainable(model="CounterNet", datasets=_kitti_detection_datasets, evaluator=_counting_evaluator,
                            summary=_counting_summary),
}


def _trainable(cfg: Mapping, config_path: str) -> Trainable:
    model = cfg.get("MODEL")
    name = model.get("NAME") if isinstance(model, Mapping) else None
    if name is None:
        raise CliError(f"{config_path} names no model (MODEL.NAME); lidarops trains {', '.join(sorted(TRAINABLE))}")
    if name not in TRAINABLE:
        raise CliError(f"{config_path}: MODEL.NAME {name!r} is not a model lidarops trains; known: "
                       f"{', '.join(sorted(TRAINABLE))}")
    return TRAINABLE[name]


def _load_pretrained(model, source: str, cfg: Mapping) -> None:
    """Starts ``model`` from the weights of ``source`` (a checkpoint file, lidarops' or OpenPCDet's, or a shipped
    model's name), as OpenPCDet's ``--pretrained_model``: every key and shape must fit."""
    from lidarops.checkpoint import CheckpointError, model_record, read_checkpoint
    from lidarops.models import load_model, weights

    path = weights.path(source) if source in weights.available() else source
    if not Path(path).is_file():
        raise CliError(f"--pretrained-model {source}: no such file, nor a shipped model "
                       f"({', '.join(sorted(weights.available()))})")
    try:  # the model the file records; an OpenPCDet file records none and is read with the training config
        own = model_record(read_checkpoint(path), str(path)).model_class is not None
        pretrained = load_model(path) if own else load_model(path, config=cfg)
    except (CheckpointError, ValueError, OSError) as e:
        raise CliError(f"--pretrained-model {source}: {e}") from None
    if type(pretrained) is not type(model):
        raise CliError(f"--pretrained-model {source} holds a {type(pretrained).__name__}; the config trains a "
                       f"{type(model).__name__}")
    had, wants = (list(getattr(getattr(m, "config", None), "class_names", None) or []) for m in (pretrained, model))
    if had != wants:  # the same shapes in another order would load, and mean other classes
        raise CliError(f"--pretrained-model {source} detects {had}; the config's model {wants}")
    try:
        model.load_state_dict(pretrained.state_dict(), strict=True)
    except RuntimeError as e:  # torch names the missing and unexpected keys and the shapes that differ
        raise CliError(f"--pretrained-model {source} does not fit the config's model: "
                       + " ".join(str(e).split())) from None


def train(args: argparse.Namespace) -> int:
    """Trains the model a config names on its data folder; prints the evaluation and where the checkpoint is."""
    from lidarops.cli._device import resolve_device
    from lidarops.config import load_config
    from lidarops.models import model_class
    from lidarops.train import TrainConfig, fit

    for flag, lo in (("max_train_frames", 1), ("max_val_frames", 1), ("gt_database_frames", 1)):
        if getattr(args, flag) is not None and getattr(args, flag) < lo:
            raise CliError(f"--{flag.replace('_', '-')} must be >= {lo}, got {getattr(args, flag)}")
    cfg = load_config(args.config)
    if args.set_cfgs:
        from lidarops.config import ConfigError, apply_overrides

        try:
            apply_overrides(cfg, args.set_cfgs)
        except ConfigError as e:
            raise CliError(str(e)) from None
    entry = _trainable(cfg, args.config)
    if args.device not in (None, "auto"):  # checked now; the trainer maps "cuda" to each process's GPU
        resolve_device(args.device)
    overrides = {k: v for k, v in dict(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, amp=args.amp,
                                       num_workers=args.workers, seed=args.seed, eval_every=args.eval_every,
                                       max_minutes=args.max_minutes, max_steps=args.max_steps, device=args.device,
                                       sync_bn=args.sync_bn or None,
                                       progress=False if args.no_progress else None).items()
                 if v is not None}
    config = TrainConfig.from_openpcdet(cfg.get("OPTIMIZATION", {}), **overrides)
    data_path = args.data or cfg.get("DATA_CONFIG", {}).get("DATA_PATH")
    if data_path and entry.creates_data(cfg):
        Path(data_path).mkdir(parents=True, exist_ok=True)
    if not data_path or not Path(data_path).is_dir():
        where = f"data folder {data_path} not found" if data_path else "no data folder"
        raise CliError(f"{where} (give --data, or DATA_CONFIG.DATA_PATH in the config); make one with: "
                       "lidarops data synth --out DIR ...")
    data_root = Path(data_path)
    model = model_class(entry.model)(cfg)
    if args.pretrained_model is not None:
        _load_pretrained(model, args.pretrained_model, cfg)
    names = list(model.config.class_names)
    train_set, val_set, collate_fn = entry.datasets(data_root, names, cfg, args)
    # model_class, model_config and class_names are the trainer's to write (from the model)
    extra = {"config_path": str(args.config), "pretrained_model": args.pretrained_model and str(args.pretrained_model),
             "data_recipe": getattr(train_set, "recipe", None) or {"root": str(data_root)},
             "train_command": "lidarops " + shlex.join(sys.argv[1:])}
    result = fit(model, train_set, collate_fn, config, args.out, val_dataset=val_set if len(val_set or []) else None,
                 evaluator=entry.evaluator(names, cfg), resume=args.resume, extra_checkpoint=extra)
    line = entry.summary(result.metrics, names) if result.metrics else ""
    if line:
        print(line)
    state = "finished" if result.finished else f"stopped ({result.stop_reason}); continue with --resume"
    print(f"{state}: {result.global_step} steps, {result.frames_per_s_total:.1f} frames/s; {result.checkpoint}")
    return 0


def register(subparsers) -> None:
    """Adds ``train`` to the ``lidarops`` parser."""
    t = subparsers.add_parser("train", help="train a model (PointPillars, PointNet, CAS-Net) from a config on its data",
                              description="Train the model a config names (MODEL.NAME: "
                                          f"{', '.join(sorted(TRAINABLE))}) from an OpenPCDet-schema config (e.g. "
                                          "configs/pointpillars/pointpillars_synth.yaml) on a KITTI-format folder, or a PointNet "
                                          "classifier (configs/casnet/pointnet_objects.yaml) or CAS-Net in front of a trained one "
                                          "(configs/casnet/casnet_pointnet_objects.yaml) on objects cut from "
                                          "simulated scenes. Under "
                                          "torchrun it runs DistributedDataParallel, one process per GPU.")
    t.add_argument("--config", required=True,
                   help="YAML config (OpenPCDet schema): a path, or a shipped config by name (pointpillars_synth, "
                        "pointpillars_demo, pointpillars_kitti, pointpillars_synth_all)")
    t.add_argument("--data", default=None, help="KITTI-format folder, or the object-set cache folder (default: the "
                                                "config's DATA_PATH)")
    t.add_argument("--out", required=True, help="run folder: checkpoints, log.csv, evaluations")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from latest.pth")
    t.add_argument("--pretrained-model", default=None,
                   help="start from these weights (fine-tuning; OpenPCDet's --pretrained_model): a checkpoint "
                        "(lidarops' or OpenPCDet's) or a shipped model's name; every key and shape must fit the "
                        "config's model. A run continued with --resume takes its own checkpoint's weights")
    t.add_argument("--epochs", type=int, default=None, help="epochs (default: the config's OPTIMIZATION.NUM_EPOCHS)")
    t.add_argument("--batch-size", type=int, default=None, help="frames per step and per process")
    t.add_argument("--lr", type=float, default=None, help="peak learning rate (default: the config's OPTIMIZATION.LR)")
    t.add_argument("--amp", choices=("none", "bf16", "fp16"), default=None, help="mixed precision")
    t.add_argument("--workers", type=int, default=None, help="DataLoader workers per process")
    t.add_argument("--eval-every", type=int, default=None, help="epochs between evaluations (0: only at the end)")
    t.add_argument("--max-minutes", type=float, default=None, help="stop with a checkpoint after this long")
    t.add_argument("--max-steps", type=int, default=None, help="stop with a checkpoint after this many steps")
    t.add_argument("--max-train-frames", type=int, default=None, help="use only the first N training frames")
    t.add_argument("--max-val-frames", type=int, default=None, help="evaluate on the first N validation frames")
    t.add_argument("--gt-database-frames", type=int, default=None,
                   help="build the gt-sampling database from the first N training frames (default: all)")
    t.add_argument("--seed", type=int, default=None, help="seed of the augmentations and the initial weights (default 0)")
    t.add_argument("--device", default=None, help="auto (default), cpu, cuda")
    t.add_argument("--sync-bn", action="store_true", help="SyncBatchNorm under multi-GPU DDP")
    t.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    t.add_argument("--set", dest="set_cfgs", nargs="+", default=None, metavar="KEY VALUE",
                   help="change config keys, OpenPCDet's --set: e.g. --set MODEL.RATIO 4 MODEL.VARIANT fast (each "
                        "key must exist in the config; values are read as YAML)")
    t.set_defaults(func=guarded("train", train))
