"""The training configuration: :class:`TrainConfig`, readable from OpenPCDet's ``OPTIMIZATION`` block."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from lidarops._checks import integer, real

__all__ = ["TrainConfig", "OPTIMIZERS", "AMP_MODES"]

OPTIMIZERS = ("adam_onecycle", "adam", "adamw")
AMP_MODES = ("none", "bf16", "fp16")

# Fields that may change when a run is resumed: they do not change what the optimisation computes.
RESUMABLE_CHANGES = frozenset({
    "num_workers", "eval_every", "ckpt_every_min", "keep_last", "max_minutes", "max_steps", "log_every",
    "tensorboard", "progress", "device",
})

# OpenPCDet key -> TrainConfig field. MOMENTUM (SGD only) and WARMUP_EPOCH (read only when LR_WARMUP is
# on) appear in OpenPCDet's shipped configs and are accepted without effect.
_OPENPCDET_KEYS = {
    "BATCH_SIZE_PER_GPU": "batch_size",
    "NUM_EPOCHS": "epochs",
    "OPTIMIZER": "optimizer",
    "LR": "lr",
    "WEIGHT_DECAY": "weight_decay",
    "MOMS": "moms",
    "PCT_START": "pct_start",
    "DIV_FACTOR": "div_factor",
    "DECAY_STEP_LIST": "decay_epochs",
    "LR_DECAY": "lr_decay",
    "LR_CLIP": "lr_clip",
    "GRAD_NORM_CLIP": "grad_norm_clip",
}
_OPENPCDET_IGNORED = ("MOMENTUM", "WARMUP_EPOCH", "LR_WARMUP")


@dataclass
class TrainConfig:
    """What :func:`lidarops.train.fit` does, with OpenPCDet's optimisation semantics.

    Optimisation (OpenPCDet's ``OPTIMIZATION`` keys in brackets):
        epochs (int): [NUM_EPOCHS].
        batch_size (int): frames per step and per process [BATCH_SIZE_PER_GPU]; the global batch is
            ``batch_size * world_size``.
        optimizer (str): [OPTIMIZER]
            ``"adam_onecycle"``: ``torch.optim.AdamW`` (betas (0.9, 0.99), decoupled weight decay on every
            parameter, as OpenPCDet's ``OptimWrapper(true_wd=True, bn_wd=True)``) with
            ``torch.optim.lr_scheduler.OneCycleLR``: lr cosine from ``lr / div_factor`` up to ``lr`` over
            ``pct_start`` of the steps, then down to ``lr / div_factor / 1e4``; beta1 cosine from
            ``moms[0]`` to ``moms[1]`` and back. The scheduler advances once per optimisation step.
            ``"adam"``: ``torch.optim.Adam`` with L2 ``weight_decay`` (coupled, as OpenPCDet's ``adam``);
            ``"adamw"``: ``torch.optim.AdamW``. Both keep ``lr`` and multiply it by ``lr_decay`` at each
            epoch in ``decay_epochs``, never below ``lr_clip`` (OpenPCDet's step schedule).
        lr (float): the peak learning rate [LR].
        weight_decay (float): [WEIGHT_DECAY].
        moms (tuple): beta1 at the ends and at the peak of the one cycle [MOMS].
        pct_start (float): fraction of the steps spent raising the lr [PCT_START].
        div_factor (float): the starting lr is ``lr / div_factor`` [DIV_FACTOR].
        decay_epochs, lr_decay, lr_clip: the step schedule of ``adam``/``adamw``
            [DECAY_STEP_LIST, LR_DECAY, LR_CLIP].
        grad_norm_clip (float or None): clip the global gradient norm to this [GRAD_NORM_CLIP];
            None or 0 does not clip.
        amp (str): ``"none"``, ``"bf16"`` (autocast to bfloat16) or ``"fp16"`` (autocast to float16 with
            a ``GradScaler``). Evaluation always runs in float32.
        sync_bn (bool): convert BatchNorm layers to ``SyncBatchNorm`` under multi-GPU DDP. Without it each
            rank normalises with the statistics of its own ``batch_size`` frames.
        find_unused_parameters (bool): passed to ``DistributedDataParallel``, for models whose loss does not
            reach every parameter.

    Running:
        seed (int): seeds the processes (``seed + rank``) and the sample order, a function of
            ``(seed, epoch)`` only.
        num_workers (int): DataLoader workers per process.
        device (str): ``"auto"`` (``cuda:LOCAL_RANK`` if available, else ``cpu``), ``"cpu"``, ``"cuda"``,
            ``"cuda:N"``.
        eval_every (int): evaluate every this many epochs (and after the last) when a validation set and
            an evaluator are given; 0 evaluates only after the last epoch.
        ckpt_every_min (float or None): write ``latest.pth`` at least this often; it is also written at
            every epoch end and when the run stops.
        keep_last (int or None): epoch checkpoints kept (the newest); None keeps all.
        max_minutes (float or None): wall-clock budget of one :func:`fit` call. The run stops at a step
            boundary, with a checkpoint, before a step that would end past it.
        max_steps (int or None): stop (with a checkpoint) once this many optimisation steps have been taken
            in total; the schedule still spans ``epochs``.
        log_every (int): steps between rows of ``log.csv`` (and progress lines when tqdm is absent).
        tensorboard (bool): also write TensorBoard scalars when ``torch.utils.tensorboard`` imports.
        progress (bool): show a progress bar (tqdm when installed, else log lines) on rank 0.
    """

    epochs: int = 80
    batch_size: int = 4
    optimizer: str = "adam_onecycle"
    lr: float = 0.003
    weight_decay: float = 0.01
    moms: tuple[float, float] = (0.95, 0.85)
    pct_start: float = 0.4
    div_factor: float = 10.0
    decay_epochs: tuple[int, ...] = (35, 45)
    lr_decay: float = 0.1
    lr_clip: float = 1e-7
    grad_norm_clip: float | None = 10.0
    amp: str = "none"
    sync_bn: bool = False
    find_unused_parameters: bool = False
    seed: int = 0
    num_workers: int = 4
    device: str = "auto"
    eval_every: int = 1
    ckpt_every_min: float | None = 5.0
    keep_last: int | None = 5
    max_minutes: float | None = None
    max_steps: int | None = None
    log_every: int = 10
    tensorboard: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        problems = []

        def check(fn, name, *args, **kwargs):
            try:
                return fn(getattr(self, name), name, *args, **kwargs)
            except ValueError as e:
                problems.append(str(e))
                return getattr(self, name)

        if self.optimizer not in OPTIMIZERS:
            problems.append(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.amp not in AMP_MODES:
            problems.append(f"amp must be one of {AMP_MODES}, got {self.amp!r}")
        for name in ("epochs", "batch_size", "log_every"):
            setattr(self, name, check(integer, name, 1))
        for name in ("num_workers", "eval_every", "seed"):
            setattr(self, name, check(integer, name, 0))
        self.lr = check(real, "lr", 0, None, lo_open=True)
        for name in ("weight_decay", "lr_decay", "lr_clip"):
            setattr(self, name, check(real, name, 0))
        self.pct_start = check(real, "pct_start", 0, 1, lo_open=True, hi_open=True)
        self.div_factor = check(real, "div_factor", 0, None, lo_open=True)
        try:
            self.moms = tuple(real(m, f"moms[{i}]", 0, 1, hi_open=True) for i, m in enumerate(self.moms))
            if len(self.moms) != 2:
                raise ValueError(f"moms must be two values in [0, 1), got {self.moms!r}")
        except (TypeError, ValueError) as e:
            problems.append(str(e) if isinstance(e, ValueError) else f"moms must be two values, got {self.moms!r}")
        try:
            self.decay_epochs = tuple(integer(e, f"decay_epochs[{i}]", 0) for i, e in enumerate(self.decay_epochs))
        except TypeError:
            problems.append(f"decay_epochs must be a list of ints, got {self.decay_epochs!r}")
        except ValueError as e:
            problems.append(str(e))
        # None turns each of these off; a value must mean something (NaN minutes would never stop the run)
        for name, fn, lo, lo_open in (("grad_norm_clip", real, 0, True), ("ckpt_every_min", real, 0, False),
                                      ("max_minutes", real, 0, True), ("max_steps", integer, 1, False),
                                      ("keep_last", integer, 0, False)):
            if getattr(self, name) is not None:
                extra = {"lo_open": lo_open} if fn is real else {}
                setattr(self, name, check(fn, name, lo, None, **extra))
        for name in ("sync_bn", "find_unused_parameters", "tensorboard", "progress"):
            if not isinstance(getattr(self, name), bool):
                problems.append(f"{name} must be True or False, got {getattr(self, name)!r}")
        if problems:
            raise ValueError("TrainConfig: " + "; ".join(problems))

    def to_dict(self) -> dict[str, Any]:
        """Plain values (tuples as lists), as stored in checkpoints."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TrainConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"TrainConfig has no fields {unknown}; known: {sorted(names)}")
        return cls(**dict(d))

    @classmethod
    def from_openpcdet(cls, optimization: Mapping[str, Any], **overrides: Any) -> "TrainConfig":
        """A config from OpenPCDet's ``OPTIMIZATION`` block (or a whole config holding one).

        Args:
            optimization: e.g. ``{"BATCH_SIZE_PER_GPU": 4, "NUM_EPOCHS": 80, "OPTIMIZER": "adam_onecycle",
                "LR": 0.003, "WEIGHT_DECAY": 0.01, "MOMENTUM": 0.9, "MOMS": [0.95, 0.85], "PCT_START": 0.4,
                "DIV_FACTOR": 10, "DECAY_STEP_LIST": [35, 45], "LR_DECAY": 0.1, "LR_CLIP": 1e-7,
                "LR_WARMUP": False, "WARMUP_EPOCH": 1, "GRAD_NORM_CLIP": 10}`` (pointpillar.yaml).
            **overrides: other :class:`TrainConfig` fields (``amp``, ``num_workers`` ...); they win.

        Raises:
            ValueError: an unknown key, an optimizer other than ``adam_onecycle``/``adam``/``adamw``
                (OpenPCDet's ``sgd`` and ``adam_cosineanneal`` are not implemented), or ``LR_WARMUP: True``.
        """
        if "OPTIMIZATION" in optimization:
            optimization = optimization["OPTIMIZATION"]
        unknown = sorted(k for k in optimization if k not in _OPENPCDET_KEYS and k not in _OPENPCDET_IGNORED)
        if unknown:
            raise ValueError(f"unsupported OPTIMIZATION keys {unknown}; lidarops.train reads "
                             f"{sorted(_OPENPCDET_KEYS)} and accepts {list(_OPENPCDET_IGNORED)}")
        opt = str(optimization.get("OPTIMIZER", "adam_onecycle")).lower()
        if opt not in OPTIMIZERS:
            raise ValueError(f"OPTIMIZER {optimization['OPTIMIZER']!r} is not supported; lidarops.train "
                             f"implements {list(OPTIMIZERS)} (OpenPCDet's sgd and adam_cosineanneal are not)")
        if optimization.get("LR_WARMUP", False):
            raise ValueError("LR_WARMUP: True is not supported (adam_onecycle warms up by itself); "
                             "set LR_WARMUP: False")
        kwargs: dict[str, Any] = {field: optimization[key] for key, field in _OPENPCDET_KEYS.items()
                                  if key in optimization}
        kwargs["optimizer"] = opt
        kwargs.update(overrides)
        return cls.from_dict(kwargs)
