"""CAS-Net in front of a frozen PointNet: the classification experiment of CAS-Net (issue 37; SampleNet's
protocol, which Chen et al. 2023 follow). Read it top to bottom:

- ``casnet``: a :class:`~lidarops.models.casnet.CASNet` (hard mode, the paper's AHSN; the full or the fast
  variant) keeps ``m = NUM_POINTS // RATIO`` points of each object;
- ``task``: a :class:`~lidarops.models.pointnet.PointNet` trained on the full clouds
  (``MODEL.TASK_CHECKPOINT``), frozen: no gradient reaches its weights and it stays in eval mode while the
  wrapper trains (dropout off, BatchNorm on its running statistics, which do not move), so that only the
  sampler learns; it classifies the sampled points;
- the loss: :func:`~lidarops.models.casnet.casnet_loss`, the task's cross-entropy on the sampled points +
  alpha * Chamfer(sampled, input) + beta * the cosine loss of the selection matrix.

::

    model = CASNetPointNet(load_config("configs/casnet/casnet_pointnet_objects.yaml"))
    out = model({"points": points, "labels": labels})   # training: {"loss", "loss_task", "loss_chamfer", ...}
    preds = model.predict({"points": points})            # [{"label", "score", "probs"}, ...] from m points each
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError
from lidarops.models.base import model_from_checkpoint, DictConfig, PredictMixin, as_model_config, read_object_config
from lidarops.models.casnet import CASNet, casnet_loss
from lidarops.models.casnet_losses import COSINE_FORMS
from lidarops.models.config import _check_value
from lidarops.models.pointnet import SIM_CLASSES, PointNet, PointNetConfig, _check_batch

__all__ = ["CASNetPointNet", "CASNetPointNetConfig"]

# CAS-Net's own MODEL keys, shared by the models that put it in front of a task network:
# field -> (the config key that sets it, kind, lo, hi, lo open, hi open)
CASNET_SPEC: dict[str, tuple] = {
    "k": ("MODEL.K", "int", 1, 1 << 16, False, False),
    "radius": ("MODEL.RADIUS", "real", 0.0, None, True, False),
    "temperature": ("MODEL.TEMPERATURE", "real", 0.0, None, True, False),
    "alpha": ("MODEL.ALPHA", "real", 0.0, None, False, False),
    "beta": ("MODEL.BETA", "real", 0.0, None, False, False),
    "candidates": ("MODEL.CANDIDATES", "int", 1, 1 << 16, False, False),
}
# field -> (the config key, the values it may take)
CASNET_CHOICES: dict[str, tuple] = {
    "variant": ("MODEL.VARIANT", ("full", "fast")),
    "neighbors": ("MODEL.NEIGHBORS", ("ball", "knn")),
    "cosine_form": ("MODEL.COSINE_FORM", COSINE_FORMS),
    "head": ("MODEL.HEAD", ("matrix", "anchored")),
}
_SPEC: dict[str, tuple] = {
    "in_channels": ("DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list (its length)", "int", 3, 1024, False, False),
    "num_points": ("DATA_CONFIG.NUM_POINTS", "int", 1, 1 << 20, False, False),
    "ratio": ("MODEL.RATIO", "int", 1, 1 << 20, False, False),
    **CASNET_SPEC,
}
_CHOICES = CASNET_CHOICES
_OTHER_KEYS = {"task_checkpoint": "MODEL.TASK_CHECKPOINT", "task": "MODEL.TASK"}
_MODEL_KEYS = {"NAME"} | {key.split(".", 1)[1] for key, *_ in [*_SPEC.values(), *_CHOICES.values()]
                          if key.startswith("MODEL.")} | {k.split(".", 1)[1] for k in _OTHER_KEYS.values()}


@dataclass
class CASNetPointNetConfig(DictConfig):
    """Everything :class:`CASNetPointNet` is built from.

    Attributes (the YAML key in brackets, OpenPCDet's schema; :meth:`from_openpcdet` reads a whole config):
        class_names (list[str]): [CLASS_NAMES] the classes, in label order (0-based labels, as PointNet's).
        in_channels (int): [length of DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list] point columns read
            (x, y, z first); CAS-Net samples them all, PointNet reads them all.
        num_points (int): [DATA_CONFIG.NUM_POINTS] ``N``, the points of each object (what the data resamples to).
        ratio (int): [MODEL.RATIO] ``D``: CAS-Net keeps ``m = num_points // ratio`` points (>= 1).
        variant (str): [MODEL.VARIANT] ``"full"`` (3 offset-attention layers, ``k`` neighbours) or ``"fast"``
            (:meth:`CASNet.fast`: one layer, each point's nearest neighbour; ``k`` and ``neighbors`` unused).
        k (int), radius (float), neighbors (str): [MODEL.K, MODEL.RADIUS, MODEL.NEIGHBORS] the full variant's
            neighbourhoods (:class:`~lidarops.models.casnet.FeatureEmbedding`).
        temperature (float): [MODEL.TEMPERATURE] of the sampling softmax, > 0.
        alpha, beta (float): [MODEL.ALPHA, MODEL.BETA] weights of the Chamfer and cosine losses (paper 1, 1).
        cosine_form (str): [MODEL.COSINE_FORM] ``"paper"`` or ``"frobenius"``
            (:func:`~lidarops.models.casnet_losses.selection_cosine_loss`).
        head (str): [MODEL.HEAD] ``"matrix"`` (the paper's sampling matrix) or ``"anchored"`` (ours: rows
            anchored at farthest point samples, :class:`~lidarops.models.casnet.AnchoredHead`).
        candidates (int): [MODEL.CANDIDATES] the anchored head's candidates per row (16).
        task_checkpoint (str | None): [MODEL.TASK_CHECKPOINT] the trained PointNet (a ``lidarops train`` run's
            ``final.pth``, a path as given, i.e. relative to the working directory); None: a fresh PointNet
            (tests, or weights that come from a CASNetPointNet checkpoint).
        task (dict | None): [MODEL.TASK: PointNet's MODEL keys, e.g. ``{MLP: [...], FC: [...]}``] the PointNet's
            config as :meth:`PointNetConfig.to_dict` gives it; None: PointNet's defaults for these classes and
            channels. Filled in from the task checkpoint when the model is built, so that the model's own
            checkpoints carry the PointNet's architecture.
    """

    class_names: list[str] = field(default_factory=lambda: list(SIM_CLASSES))
    in_channels: int = 3
    num_points: int = 1024
    ratio: int = 8
    variant: str = "full"
    k: int = 32
    radius: float = 2.0
    neighbors: str = "ball"
    temperature: float = 1.0
    alpha: float = 1.0
    beta: float = 1.0
    cosine_form: str = "paper"
    head: str = "matrix"
    candidates: int = 16
    task_checkpoint: Optional[str] = None
    task: Optional[dict] = None

    def __post_init__(self) -> None:
        self.validate()
        self.class_names = list(self.class_names)
        for name in ("radius", "temperature", "alpha", "beta"):
            setattr(self, name, float(getattr(self, name)))
        if self.task is not None:
            self.task = self.task_config().to_dict()

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def num_out(self) -> int:
        """``m``: the points CAS-Net keeps of each object."""
        return self.num_points // self.ratio

    def task_config(self) -> PointNetConfig:
        """The PointNet's config: ``task``, or PointNet's defaults for these classes and channels."""
        if self.task is None:
            return PointNetConfig(class_names=list(self.class_names), in_channels=self.in_channels)
        try:
            return PointNetConfig.from_dict(self.task)
        except ConfigError as e:
            raise ConfigError(f"MODEL.TASK: {e}") from None

    def validate(self) -> None:
        """Every field's type and range (a ``ConfigError`` naming the YAML key), then their consistency."""
        names = self.class_names
        if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)) or not names \
                or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
            raise ConfigError(f"CLASS_NAMES must be a non-empty list of distinct names, got {names!r}")
        for name, (key, kind, lo, hi, lo_open, hi_open) in _SPEC.items():
            _check_value(getattr(self, name), key, kind, lo, hi, lo_open, hi_open)
        for name, (key, choices) in _CHOICES.items():
            if not isinstance(getattr(self, name), str) or getattr(self, name) not in choices:
                raise ConfigError(f"{key} must be one of {list(choices)}, got {getattr(self, name)!r}")
        if self.num_points // self.ratio < 1:
            raise ConfigError(f"MODEL.RATIO {self.ratio} leaves no point of DATA_CONFIG.NUM_POINTS {self.num_points}: "
                              f"it must be at most {self.num_points}")
        ckpt = self.task_checkpoint
        if ckpt is not None and (not isinstance(ckpt, (str, Path)) or not str(ckpt)):
            raise ConfigError(f"MODEL.TASK_CHECKPOINT must be a file path or null, got {ckpt!r}")
        if ckpt is not None:
            self.task_checkpoint = str(ckpt)
        if self.task is not None and not isinstance(self.task, Mapping):
            raise ConfigError(f"MODEL.TASK must be a mapping of PointNet's MODEL keys or null, got {self.task!r}")
        task = self.task_config()
        if list(task.class_names) != list(names) or task.in_channels != self.in_channels:
            raise ConfigError(f"MODEL.TASK: the PointNet classifies {list(task.class_names)} from {task.in_channels} "
                              f"channels, the config {list(names)} from {self.in_channels}")

    @classmethod
    def from_openpcdet(cls, cfg: Mapping) -> "CASNetPointNetConfig":
        """From a whole config dict (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL`` with ``NAME: CASNetPointNet``),
        e.g. ``load_config("configs/casnet/casnet_pointnet_objects.yaml")``. Unknown ``MODEL`` keys and bad
        values raise ``ConfigError`` naming the key."""
        model, data, kwargs = read_object_config(cfg, "CASNetPointNet", _MODEL_KEYS, {**_SPEC, **_CHOICES})
        if "NUM_POINTS" in data:
            kwargs["num_points"] = data["NUM_POINTS"]
        kwargs["task_checkpoint"] = model.get("TASK_CHECKPOINT")
        task = model.get("TASK")
        if task is not None:
            if not isinstance(task, Mapping):
                raise ConfigError(f"MODEL.TASK must be a mapping of PointNet's MODEL keys or null, got {task!r}")
            try:  # PointNet's own reader: its keys, checks and defaults
                kwargs["task"] = PointNetConfig.from_openpcdet(
                    {"CLASS_NAMES": cfg["CLASS_NAMES"], "DATA_CONFIG": data,
                     "MODEL": {**task, "NAME": "PointNet"}}).to_dict()
            except ConfigError as e:
                raise ConfigError(f"MODEL.TASK: {e}".replace("MODEL.TASK: MODEL.", "MODEL.TASK.")) from None
        return cls(**kwargs)


def casnet_of(cfg) -> CASNet:
    """The hard-sampling CAS-Net a wrapper's config describes (``num_out``, ``variant``, ``k``, ``radius``,
    ``neighbors``, ``temperature``, ``head``, ``candidates``): the full model or :meth:`CASNet.fast`."""
    common = dict(temperature=cfg.temperature, mode="hard", head=cfg.head, candidates=cfg.candidates)
    if cfg.variant == "fast":
        return CASNet.fast(cfg.num_out, radius=cfg.radius, **common)
    return CASNet(cfg.num_out, k=cfg.k, radius=cfg.radius, neighbors=cfg.neighbors, **common)


class FrozenTaskMixin:
    """``train(mode)`` of a CAS-Net in front of a frozen task network ``self.task``: CAS-Net takes the mode, the
    task stays in eval mode (its BatchNorm statistics are the trained network's and must not move)."""

    def train(self, mode: bool = True):
        super().train(mode)
        self.task.eval()
        return self


class CASNetPointNet(FrozenTaskMixin, PredictMixin, nn.Module):
    """CAS-Net sampling ``m`` points of each object for a frozen PointNet (a
    :class:`lidarops.train.TrainableModel`).

    Args:
        config (CASNetPointNetConfig | Mapping | str | Path | None): a typed config, a dict of its fields, a
            whole config dict (with ``MODEL``), or a YAML path; None: the defaults (a fresh PointNet).
        load_task (bool): read ``task_checkpoint`` (when the config names one); False builds the PointNet
            fresh from ``config.task`` (what :meth:`from_checkpoint` does: the weights come from the file).

    Batch: as :class:`PointNet`'s: ``points (Tensor[B, N, C])`` with ``C >= in_channels`` and ``N`` the
    config's ``num_points`` (CAS-Net's head has ``m = num_points // ratio`` outputs; another ``N`` runs, at
    another ratio); in training ``labels (Tensor[B])`` int64 in ``[0, num_classes)`` and ``B >= 2``.

    ``forward(batch)`` returns in training ``{"loss", "loss_task", "loss_chamfer", "loss_cosine", "accuracy",
    "duplicates"}``: ``loss = loss_task + alpha * loss_chamfer + beta * loss_cosine`` (``loss_task`` the
    PointNet's cross-entropy on the sampled points, with its label smoothing), ``accuracy`` the batch's share
    of correct argmaxes and ``duplicates`` the mean number of repeated picks per object (both logged, no
    gradient); in eval mode the PointNet's logits ``(Tensor[B, num_classes])`` on the sampled points.

    Attributes: ``casnet`` (:class:`CASNet`), ``task`` (:class:`PointNet`, frozen), ``config``.
    """

    def __init__(self, config: "CASNetPointNetConfig | Mapping | str | Path | None" = None,
                 load_task: bool = True) -> None:
        super().__init__()
        cfg = as_model_config(config, CASNetPointNetConfig)
        if load_task and cfg.task_checkpoint is not None:
            task = _load_task(cfg)
            cfg = dataclasses.replace(cfg, task=task.config.to_dict())
        else:
            task = PointNet(cfg.task_config())
            cfg = dataclasses.replace(cfg, task=task.config.to_dict())
        self.config = cfg
        self.casnet = casnet_of(cfg)
        self.task = task.eval().requires_grad_(False)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config: "CASNetPointNetConfig | Mapping | str | Path") -> "CASNetPointNet":
        """A model with a fresh CAS-Net and the PointNet of ``MODEL.TASK_CHECKPOINT`` (fresh without one)."""
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: "CASNetPointNetConfig | Mapping | str | Path | None" = None,
                        map_location: "str | torch.device" = "cpu", check_finite: bool = True) -> "CASNetPointNet":
        """A model with weights (CAS-Net's and the PointNet's) from a lidarops checkpoint (a training run's
        ``final.pth`` or a file of :meth:`save`; it carries its config), or a bare state dict file given
        ``config``. The task checkpoint is not read. A state dict that does not fit, or (with
        ``check_finite``) holds NaN or infinite values, raises :class:`~lidarops.checkpoint.CheckpointError`."""
        return model_from_checkpoint(cls, path, config, map_location, check_finite, load_task=False)

    @classmethod
    def casnet_of_checkpoint(cls, path: "str | Path") -> CASNet:
        """The CAS-Net of a checkpoint of this model (what :func:`lidarops.models.casnet.load_casnet` reads)."""
        return cls.from_checkpoint(path).casnet

    # PointNet's: they read only state_dict(), config.class_names / in_channels / num_classes
    load_weights = PointNet.load_weights
    save = PointNet.save
    postprocess = PointNet.postprocess

    # ---------------------------------------------------------------- the network
    def forward(self, batch: Mapping[str, Any]) -> "dict[str, Tensor] | Tensor":
        dtype = self.task.head[-1].weight.dtype
        points, labels = _check_batch(batch, self.task.config, self.training, dtype)
        sampled = self.casnet(points)
        logits, _ = self.task.network(sampled.sampled)
        if not self.training:
            return logits
        loss_task = F.cross_entropy(logits, labels, label_smoothing=self.task.config.label_smoothing)
        out = casnet_loss(sampled, points, loss_task, self.config.alpha, self.config.beta, self.config.cosine_form)
        out["accuracy"] = (logits.detach().argmax(1) == labels).float().mean()
        out["duplicates"] = sampled.num_duplicates.float().mean()
        return out


def _load_task(cfg: CASNetPointNetConfig) -> PointNet:
    """The PointNet of ``MODEL.TASK_CHECKPOINT``, checked against the config's classes, channels and ``TASK``."""
    path = cfg.task_checkpoint
    try:
        task = PointNet.from_checkpoint(path)
    except (OSError, CheckpointError, ConfigError) as e:
        raise ConfigError(f"MODEL.TASK_CHECKPOINT {path}: {e}") from None
    if list(task.config.class_names) != list(cfg.class_names) or task.config.in_channels != cfg.in_channels:
        raise ConfigError(f"MODEL.TASK_CHECKPOINT {path} classifies {task.config.class_names} from "
                          f"{task.config.in_channels} channels, the config {cfg.class_names} from {cfg.in_channels}")
    if cfg.task is not None and cfg.task != task.config.to_dict():
        raise ConfigError(f"MODEL.TASK disagrees with the PointNet of MODEL.TASK_CHECKPOINT {path}: leave it out "
                          f"(the checkpoint carries its config) or make it {task.config.to_dict()}")
    return task
