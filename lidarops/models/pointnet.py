"""PointNet, the classifier (Qi et al., CVPR 2017), by default in the vanilla form (no T-Nets) that the
learned-sampling line of work puts behind its samplers: S-NET (Dovrat et al. 2019) uses it; SampleNet (Lang
et al. 2020) trains both it and the full model (its release's default task network is the full one); CAS-Net
(Chen et al. 2023) follows SampleNet's classification protocol. Read it top to bottom:

- ``input_transform`` (optional, off by default): a T-Net predicting a 3 x 3 matrix applied to x, y, z;
- ``mlp``: the shared MLP ``in_channels -> 64 -> 64 -> 64 -> 128 -> 1024``, 1 x 1 convolutions with BatchNorm
  and ReLU (``conv1`` .. ``conv5``, the scopes of the reference code); the optional ``feature_transform``
  (a 64 x 64 T-Net, with the orthogonality loss ``|I - A A^T|_F^2`` weighted 0.001, averaged over the objects:
  the reference code's ``tf.nn.l2_loss`` sums over the batch and halves, which would tie the loss to the batch
  size; the trainer wants a mean) sits after ``conv2``;
- the global max pool over the points (the symmetric function);
- ``head``: ``fc1`` 1024 -> 512 and ``fc2`` 512 -> 256, each Linear + BatchNorm + ReLU, dropout 0.3 (keep
  probability 0.7), then ``fc3`` 256 -> num_classes (the logits).

This is ``pointnet_cls_basic.py`` of the PointNet release (also SampleNet's "PointNet vanilla"): one dropout,
after ``fc2``. Turning both transforms on gives ``pointnet_cls.py``'s network except that it keeps that one
dropout (the full model has a second one after ``fc1``).

Labels are 0-based into ``class_names`` (:mod:`lidarops.conventions`: classification targets are what
``torch.nn.CrossEntropyLoss`` wants), unlike the 1-based class ids of the detectors.

::

    model = PointNet(PointNetConfig(class_names=["Car", "Pedestrian"]))
    out = model({"points": points, "labels": labels})        # training: {"loss", "loss_cls", "accuracy", ...}
    preds = model.predict({"points": points})                 # [{"label", "score", "probs"}, ...]
    logits, _ = model.network(points)                         # (B, K), differentiable in the points
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops import checkpoint
from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError
from lidarops.models.base import model_from_checkpoint, DictConfig, PredictMixin, as_model_config, read_object_config
from lidarops.models.config import _check_value
from lidarops.ops.validation import describe, run_value_checks, value_checks_enabled

__all__ = ["PointNet", "PointNetConfig", "TNet", "SIM_CLASSES"]

#: The simulator's object classes (``lidarops.data.CLASSES``, written out: models do not import the data floor).
SIM_CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist", "Truck", "Bus", "Barrier", "TrafficCone", "Drone")

# field -> (the config key that sets it, kind, lo, hi, lo open, hi open)
_SPEC: dict[str, tuple] = {
    "in_channels": ("DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list (its length)", "int", 3, 1024, False, False),
    "mlp": ("MODEL.MLP", "ints", 1, 1 << 16, False, False),
    "fc": ("MODEL.FC", "ints", 1, 1 << 16, False, False),
    "dropout": ("MODEL.DROPOUT", "real", 0.0, 1.0, False, True),
    "input_transform": ("MODEL.INPUT_TRANSFORM", "bool", None, None, False, False),
    "feature_transform": ("MODEL.FEATURE_TRANSFORM", "bool", None, None, False, False),
    "feature_transform_weight": ("MODEL.FEATURE_TRANSFORM_WEIGHT", "real", 0.0, None, False, False),
    "label_smoothing": ("MODEL.LABEL_SMOOTHING", "real", 0.0, 1.0, False, True),
}
_MODEL_KEYS = {"NAME"} | {v[0].split(".", 1)[1] for v in _SPEC.values() if v[0].startswith("MODEL.")}


@dataclass
class PointNetConfig(DictConfig):
    """Everything :class:`PointNet` is built from.

    Attributes (the YAML key in brackets, OpenPCDet's schema; :meth:`from_openpcdet` reads a whole config):
        class_names (list[str]): [CLASS_NAMES] the classes, in label order (labels are 0-based into them).
        in_channels (int): [length of DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list] point columns
            read: x, y, z first, then extra channels (intensity ...); >= 3.
        mlp (list[int]): [MODEL.MLP] widths of the shared MLP (paper: 64, 64, 64, 128, 1024).
        fc (list[int]): [MODEL.FC] widths of the hidden fully connected layers (paper: 512, 256).
        dropout (float): [MODEL.DROPOUT] drop probability before the last layer (paper: keep 0.7, so 0.3).
        input_transform (bool): [MODEL.INPUT_TRANSFORM] the 3 x 3 T-Net on x, y, z (off: PointNet vanilla).
        feature_transform (bool): [MODEL.FEATURE_TRANSFORM] the T-Net on the features after the second
            layer (needs >= 3 MLP layers), with its orthogonality loss (off: PointNet vanilla).
        feature_transform_weight (float): [MODEL.FEATURE_TRANSFORM_WEIGHT] weight of that loss (paper 0.001).
        label_smoothing (float): [MODEL.LABEL_SMOOTHING] of the cross-entropy, in [0, 1) (paper: 0, off).
    """

    class_names: list[str] = field(default_factory=lambda: list(SIM_CLASSES))
    in_channels: int = 3
    mlp: list[int] = field(default_factory=lambda: [64, 64, 64, 128, 1024])
    fc: list[int] = field(default_factory=lambda: [512, 256])
    dropout: float = 0.3
    input_transform: bool = False
    feature_transform: bool = False
    feature_transform_weight: float = 0.001
    label_smoothing: float = 0.0

    def __post_init__(self) -> None:
        self.validate()
        self.class_names = list(self.class_names)
        self.mlp, self.fc = list(self.mlp), list(self.fc)
        self.dropout, self.label_smoothing = float(self.dropout), float(self.label_smoothing)
        self.feature_transform_weight = float(self.feature_transform_weight)

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def validate(self) -> None:
        """Every field's type and range (a ``ConfigError`` naming the YAML key), then their consistency."""
        names = self.class_names
        if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)) or not names \
                or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
            raise ConfigError(f"CLASS_NAMES must be a non-empty list of distinct names, got {names!r}")
        for name, (key, kind, lo, hi, lo_open, hi_open) in _SPEC.items():
            value = getattr(self, name)
            if kind == "ints":
                if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)) \
                        or (name == "mlp" and not value):
                    raise ConfigError(f"{key} must be a {'non-empty ' if name == 'mlp' else ''}list of ints, "
                                      f"got {value!r}")
                for i, v in enumerate(value):
                    _check_value(v, f"{key}[{i}]", "int", lo, hi, lo_open, hi_open)
            else:
                _check_value(value, key, kind, lo, hi, lo_open, hi_open)
        if self.feature_transform and len(self.mlp) < 3:
            raise ConfigError(f"MODEL.FEATURE_TRANSFORM needs at least 3 MLP layers (it acts after the second), "
                              f"got MODEL.MLP {list(self.mlp)}")

    @classmethod
    def from_openpcdet(cls, cfg: Mapping) -> "PointNetConfig":
        """From a whole config dict (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL`` with ``NAME: PointNet``), e.g.
        ``load_config("configs/casnet/pointnet_objects.yaml")``. Unknown ``MODEL`` keys and bad values raise
        ``ConfigError`` naming the key."""
        _, _, kwargs = read_object_config(cfg, "PointNet", _MODEL_KEYS, _SPEC)
        return cls(**kwargs)


# ---------------------------------------------------------------------------------------------------- parts
class _ConvBN(nn.Sequential):
    """1 x 1 convolution (a shared per-point linear layer) + BatchNorm + ReLU on ``(B, C, N)``. No conv bias:
    BatchNorm's shift replaces it (the reference code has both; the functions are the same)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(OrderedDict(conv=nn.Conv1d(cin, cout, 1, bias=False), bn=nn.BatchNorm1d(cout),
                                     relu=nn.ReLU(inplace=True)))


class _LinearBN(nn.Sequential):
    """Linear + BatchNorm + ReLU on ``(B, C)``."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(OrderedDict(linear=nn.Linear(cin, cout, bias=False), bn=nn.BatchNorm1d(cout),
                                     relu=nn.ReLU(inplace=True)))


class TNet(nn.Module):
    """The alignment network of PointNet: per-point MLP 64 -> 128 -> 1024, max pool, FC 512 -> 256 -> k*k;
    the output starts as the identity (zero last weight, identity bias).

    Args:
        k (int): the matrix size (3 for x, y, z; 64 for features).

    Shapes: ``x (Tensor[B, k, N]) -> (Tensor[B, k, k])``.
    """

    def __init__(self, k: int) -> None:
        super().__init__()
        self.k = k
        self.conv1, self.conv2, self.conv3 = _ConvBN(k, 64), _ConvBN(64, 128), _ConvBN(128, 1024)
        self.fc1, self.fc2 = _LinearBN(1024, 512), _LinearBN(512, 256)
        self.transform = nn.Linear(256, k * k)
        nn.init.zeros_(self.transform.weight)
        with torch.no_grad():
            self.transform.bias.copy_(torch.eye(k).flatten())

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv3(self.conv2(self.conv1(x))).amax(dim=2)
        return self.transform(self.fc2(self.fc1(x))).view(-1, self.k, self.k)


# ---------------------------------------------------------------------------------------------------- model
class PointNet(PredictMixin, nn.Module):
    """The PointNet classifier (a :class:`lidarops.train.TrainableModel`).

    Args:
        config (PointNetConfig | Mapping | str | Path | None): a typed config, a dict of its fields, a whole
            config dict (with ``MODEL``), or a YAML path; None: the defaults (the simulator's 8 classes, x, y, z).

    Batch: ``points (Tensor[B, N, C])`` with ``C >= in_channels`` (x, y, z, then the extra channels; the
    first ``in_channels`` columns are read), ``N >= 1`` points per object; in training ``labels (Tensor[B])``
    int64 in ``[0, num_classes)`` and ``B >= 2`` (BatchNorm of the fully connected layers needs two objects).
    A batch that breaks this is refused with a ``ValueError`` naming ``batch['points']`` or ``batch['labels']``:
    shapes and dtypes first (points, then labels), then the values (finite points, labels in range; one sync).

    ``forward(batch)`` returns in training ``{"loss", "loss_cls", "accuracy", "logits"}`` (``loss_reg`` too
    with the feature transform): ``loss`` the mean over the batch, ``accuracy`` the batch's share of correct
    argmaxes (logged, no gradient); in eval mode the raw logits ``(Tensor[B, num_classes])``.
    :meth:`postprocess` turns those into per-object predictions, :meth:`predict` does both.
    """

    def __init__(self, config: "PointNetConfig | Mapping | str | Path | None" = None) -> None:
        super().__init__()
        cfg = self.config = as_model_config(config, PointNetConfig)
        if cfg.input_transform:
            self.input_transform = TNet(3)
        widths = [cfg.in_channels, *cfg.mlp]
        self.mlp = nn.Sequential(OrderedDict((f"conv{i + 1}", _ConvBN(widths[i], widths[i + 1]))
                                             for i in range(len(cfg.mlp))))
        if cfg.feature_transform:
            self.feature_transform = TNet(cfg.mlp[1])
        head: list[tuple[str, nn.Module]] = []
        widths = [cfg.mlp[-1], *cfg.fc]
        head += [(f"fc{i + 1}", _LinearBN(widths[i], widths[i + 1])) for i in range(len(cfg.fc))]
        head += [("dp1", nn.Dropout(cfg.dropout)), (f"fc{len(cfg.fc) + 1}", nn.Linear(widths[-1], cfg.num_classes))]
        self.head = nn.Sequential(OrderedDict(head))

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config: "PointNetConfig | Mapping | str | Path") -> "PointNet":
        """A model with freshly initialised weights from a config (see the class docstring)."""
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: "PointNetConfig | Mapping | str | Path | None" = None,
                        map_location: "str | torch.device" = "cpu", check_finite: bool = True) -> "PointNet":
        """A model with weights from a lidarops checkpoint (a training run's ``final.pth`` or a file of
        :meth:`save`; it carries its config), or a bare state dict file given ``config``. A state dict that
        does not fit, or (with ``check_finite``) holds NaN or infinite values, raises
        :class:`~lidarops.checkpoint.CheckpointError` naming the keys."""
        return model_from_checkpoint(cls, path, config, map_location, check_finite)

    def load_weights(self, state_dict: Mapping[str, Tensor], source: str = "state dict",
                     check_finite: bool = True) -> None:
        """``load_state_dict(strict=True)`` after one check of keys and shapes whose error names every missing,
        unexpected or differently shaped key; with ``check_finite`` NaN or infinite values are refused."""
        own = self.state_dict()
        missing = [k for k in own if k not in state_dict]
        unexpected = [k for k in state_dict if k not in own]
        shapes = [f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(own[k].shape)}"
                  for k in own if k in state_dict and tuple(state_dict[k].shape) != tuple(own[k].shape)]
        parts = [f"{title} ({len(items)}): " + ", ".join(items[:8]) + (" ..." if len(items) > 8 else "")
                 for title, items in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", shapes))
                 if items]
        if parts:
            raise CheckpointError(f"{source} does not fit this {type(self).__name__} config (classes "
                                  f"{self.config.class_names}, in_channels {self.config.in_channels}): "
                                  + "; ".join(parts))
        if check_finite:
            checkpoint.check_finite(state_dict, source)
        self.load_state_dict({k: v.to(own[k].dtype) for k, v in state_dict.items()}, strict=True)

    def save(self, path: "str | Path", **extra: Any) -> Path:
        """Writes the model as a :mod:`lidarops.checkpoint` file (format fields, ``model_class``,
        ``model_config``, ``class_names``, ``model_state``) plus ``extra`` entries (``data_recipe``,
        ``evaluation`` ...), atomically; :meth:`from_checkpoint` and ``lidarops.models.load_model`` read it."""
        checkpoint.check_plain(extra, "extra")
        state = {**checkpoint.format_fields(), **checkpoint.model_fields(self), "model_state": self.state_dict(),
                 **extra}
        path = Path(path)
        checkpoint.save_checkpoint(state, [path])
        return path

    # ---------------------------------------------------------------- the network
    def network(self, points: Tensor) -> tuple[Tensor, Tensor | None]:
        """Points -> ``(logits (Tensor[B, num_classes]), feature transform (Tensor[B, 64, 64]) or None)``,
        without checks: differentiable in ``points`` (a learned sampler trains through it).

        Args:
            points (Tensor[B, N, in_channels]): x, y, z, then the extra channels.
        """
        x = points.transpose(1, 2)  # (B, C, N): channels first for the 1 x 1 convolutions
        if self.config.input_transform:
            xyz = torch.bmm(self.input_transform(x[:, :3]).transpose(1, 2), x[:, :3])
            x = torch.cat([xyz, x[:, 3:]], dim=1)
        transform = None
        for i, layer in enumerate(self.mlp):
            x = layer(x)
            if i == 1 and self.config.feature_transform:
                transform = self.feature_transform(x)
                x = torch.bmm(transform.transpose(1, 2), x)
        return self.head(x.amax(dim=2)), transform

    def forward(self, batch: Mapping[str, Any]) -> "dict[str, Tensor] | Tensor":
        dtype = self.head[-1].weight.dtype
        points, labels = _check_batch(batch, self.config, self.training, dtype)
        logits, transform = self.network(points)
        if not self.training:
            return logits
        loss_cls = F.cross_entropy(logits, labels, label_smoothing=self.config.label_smoothing)
        out = {"loss": loss_cls, "loss_cls": loss_cls,
               "accuracy": (logits.detach().argmax(1) == labels).float().mean(), "logits": logits}
        if transform is not None:
            eye = torch.eye(transform.shape[1], dtype=transform.dtype, device=transform.device)
            diff = eye - torch.bmm(transform, transform.transpose(1, 2))
            loss_reg = self.config.feature_transform_weight * diff.square().sum(dim=(1, 2)).mean()
            out["loss_reg"] = loss_reg
            out["loss"] = loss_cls + loss_reg
        return out

    def postprocess(self, raw: Tensor, batch: Mapping[str, Any] | None = None) -> list[dict[str, Tensor]]:
        """Per-object predictions from the eval-mode logits ``(Tensor[B, K])``: ``label`` (int64, 0-based into
        ``class_names``, the argmax; ties to the lower id), ``score`` (its probability) and ``probs``
        (Tensor[K], the softmax)."""
        if not isinstance(raw, Tensor) or raw.dim() != 2 or raw.shape[1] != self.config.num_classes:
            raise ValueError(f"raw must be the eval-mode logits (B, {self.config.num_classes}), got {describe(raw)}")
        probs = raw.detach().float().softmax(dim=1)
        score, label = probs.max(dim=1)
        return [{"label": label[i], "score": score[i], "probs": probs[i]} for i in range(raw.shape[0])]





def _check_batch(batch: Mapping[str, Any], cfg: PointNetConfig, training: bool,
                 dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
    """The points (first ``in_channels`` columns, in the weights' dtype) and, in training, the labels; a
    ``ValueError`` naming the key otherwise."""
    if not isinstance(batch, Mapping) or "points" not in batch:
        got = f"a dict with keys {sorted(map(str, batch))}" if isinstance(batch, Mapping) else type(batch).__name__
        raise ValueError(f"batch must be a dict with 'points' (B, N, C) and, in training, 'labels' (B,); got {got}")
    points = batch["points"]
    c = cfg.in_channels
    if not isinstance(points, Tensor) or points.dim() != 3 or points.shape[2] < c or not points.is_floating_point() \
            or points.shape[0] < 1 or points.shape[1] < 1:
        raise ValueError(f"batch['points'] must be a floating (B, N, C) tensor with B >= 1 objects, N >= 1 points "
                         f"and C >= in_channels = {c} columns (x, y, z first), got {describe(points)}")
    points = points[..., :c]
    if points.dtype != dtype:
        points = points.to(dtype)
    b = points.shape[0]
    checks = []
    if value_checks_enabled():
        bad = ~torch.isfinite(points).all(dim=(1, 2))
        checks.append((bad.any(), lambda: f"batch['points'] must be finite; object(s) "
                       f"{torch.nonzero(bad).flatten()[:8].tolist()} hold NaN or infinite values"))
    labels = None
    if training:
        labels = batch.get("labels")
        if not isinstance(labels, Tensor) or labels.shape != (b,) or labels.is_floating_point() \
                or labels.is_complex() or labels.dtype == torch.bool:
            raise ValueError(f"batch['labels'] must be an integer (B,) = ({b},) tensor of class ids in training, "
                             f"got {describe(labels) if labels is not None else 'no labels'}")
        if b < 2:
            raise ValueError("batch['points'] holds 1 object: training needs B >= 2 (BatchNorm of the fully "
                             "connected layers has no statistics for one object); batch size and dataset size "
                             "must not leave a batch of one")
        labels = labels.long()
        if labels.device != points.device:
            raise ValueError(f"batch['labels'] is on {labels.device} but batch['points'] is on {points.device}")
        if value_checks_enabled():
            k = cfg.num_classes
            bad_label = (labels < 0) | (labels >= k)
            checks.append((bad_label.any(), lambda: f"batch['labels'] must be class ids in [0, {k}) (0-based into "
                           f"class_names); got {labels[bad_label][:8].tolist()}"))
    run_value_checks(checks)
    return points, labels

