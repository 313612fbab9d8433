"""CAS-Net in front of a frozen PointPillars: CAS-Net's detection experiment (issue 37; the paper's Table I).
Read it top to bottom:

- each frame's points (the camera's field of view, as the KITTI dataset gives them) are cut into spatially
  coherent segments of at most ``SEGMENT_POINTS`` (8,192 in the paper: offset attention is O(N^2)), padded
  to ``SEGMENT_POINTS`` and masked;
- ``casnet``: a :class:`~lidarops.models.casnet.CASNet` (hard mode, the paper's AHSN) keeps
  ``m = SEGMENT_POINTS // RATIO`` points of each segment, every channel (x, y, z, intensity: real points);
  the kept rows of a frame's segments are its new cloud (repeats kept, as in the paper);
- ``task``: a :class:`~lidarops.models.pointpillars.PointPillars` trained on full clouds
  (``MODEL.TASK_CHECKPOINT``: a file or a shipped name, ``pointpillars_synth`` by default), frozen (eval
  mode, no gradient to its weights). The pillars are built from the kept points so that the detector's
  loss reaches them: the voxelizer picks each point's pillar and slot, and the pillars are filled from the
  points with an index copy, which carries the straight-through gradient back to CAS-Net's sampling matrix;
- the loss: :func:`~lidarops.models.casnet.casnet_loss`, the detector's loss on the kept points + alpha *
  Chamfer(kept, segment) + beta * the cosine loss of the selection matrices.

::

    model = CASNetPointPillars(load_config("configs/casnet/casnet_pointpillars_synth.yaml"))
    out = model(batch)              # training: {"loss", "loss_task", "loss_chamfer", "loss_cosine", "duplicates", ...}
    boxes = model.predict(batch)    # the detector's boxes on the kept points
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops.checkpoint import CheckpointError
from lidarops.config import ConfigError
from lidarops.models.base import (DictConfig, PredictMixin, as_model_config, load_weights_strict,
                                  model_from_checkpoint)
from lidarops.models.casnet import CASNet, casnet_loss
from lidarops.models.casnet_pointnet import CASNET_CHOICES, CASNET_SPEC, FrozenTaskMixin, casnet_of
from lidarops.models.config import PointPillarsConfig, _check_value
from lidarops.models.pointpillars import PointPillars, _check_batch
from lidarops.models.samplers import spatial_segments

__all__ = ["CASNetPointPillars", "CASNetPointPillarsConfig", "sample_frames"]

_SPEC: dict[str, tuple] = {  # field -> (the config key, kind, lo, hi, lo open, hi open)
    "ratio": ("MODEL.RATIO", "int", 2, 1 << 16, False, False),
    "segment_points": ("MODEL.SEGMENT_POINTS", "int", 2, 1 << 20, False, False),
    **CASNET_SPEC,
}
_CHOICES = CASNET_CHOICES
_MODEL_KEYS = {"NAME", "TASK_CHECKPOINT", "TASK", "DEDUP"} | {key.split(".", 1)[1] for key, *_ in
                                                      [*_SPEC.values(), *_CHOICES.values()]}


@dataclass
class CASNetPointPillarsConfig(DictConfig):
    """Everything :class:`CASNetPointPillars` is built from.

    Attributes (the YAML key in brackets):
        ratio (int): [MODEL.RATIO] ``D`` >= 2: each segment of ``segment_points`` keeps ``m = segment_points // D``.
        segment_points (int): [MODEL.SEGMENT_POINTS] the segment size ``m * D`` (8,192 in the paper).
        variant (str): [MODEL.VARIANT] ``"full"`` (3 offset-attention layers, ``k`` neighbours) or ``"fast"``.
        k, radius, neighbors: [MODEL.K, MODEL.RADIUS, MODEL.NEIGHBORS] the neighbourhoods (32, 2 m, ball query).
        temperature (float): [MODEL.TEMPERATURE] of the sampling softmax.
        alpha, beta (float): [MODEL.ALPHA, MODEL.BETA] the Chamfer and cosine weights (1, 1).
        cosine_form (str): [MODEL.COSINE_FORM] ``"paper"`` or ``"frobenius"``.
        head (str), candidates (int): [MODEL.HEAD, MODEL.CANDIDATES] the sampling matrix: ``"matrix"`` (the
            paper's) or ``"anchored"`` (ours, :class:`~lidarops.models.casnet.AnchoredHead`, ``candidates`` per row).
        dedup (bool): [MODEL.DEDUP] in training, reassign repeated picks so that the detector sees ``m``
            distinct points per segment, and in inference keep distinct points (:meth:`CASNetPointPillars.keep`)
            (ours; off in the paper, whose rows may pick one point many times).
        task_checkpoint (str | None): [MODEL.TASK_CHECKPOINT] the trained detector: a file or a shipped name
            (``lidarops.models.weights``); None builds the detector from ``task`` with fresh weights (tests).
        task (dict | None): [MODEL.TASK] the detector's :class:`PointPillarsConfig` as a dict (filled in from the
            task checkpoint, so that this model's checkpoints carry it); None: PointPillars' defaults.
    """

    ratio: int = 8
    segment_points: int = 8192
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
    dedup: bool = False
    task_checkpoint: Optional[str] = "pointpillars_synth"
    task: Optional[dict] = None

    def __post_init__(self) -> None:
        self.validate()
        for name in ("radius", "temperature", "alpha", "beta"):
            setattr(self, name, float(getattr(self, name)))

    @property
    def num_out(self) -> int:
        """``m``: the points CAS-Net keeps of each segment."""
        return self.segment_points // self.ratio

    @property
    def class_names(self) -> list[str]:
        return list(self.task_config().class_names)

    def task_config(self) -> PointPillarsConfig:
        if self.task is None:
            return PointPillarsConfig()
        try:
            return PointPillarsConfig.from_dict(self.task)
        except ConfigError as e:
            raise ConfigError(f"MODEL.TASK: {e}") from None

    def validate(self) -> None:
        """Every field's type and range (a ``ConfigError`` naming the YAML key)."""
        for name, (key, kind, lo, hi, lo_open, hi_open) in _SPEC.items():
            _check_value(getattr(self, name), key, kind, lo, hi, lo_open, hi_open)
        for name, (key, choices) in _CHOICES.items():
            if not isinstance(getattr(self, name), str) or getattr(self, name) not in choices:
                raise ConfigError(f"{key} must be one of {list(choices)}, got {getattr(self, name)!r}")
        if not isinstance(self.dedup, bool):
            raise ConfigError(f"MODEL.DEDUP must be true or false, got {self.dedup!r}")
        if self.segment_points // self.ratio < 1:
            raise ConfigError(f"MODEL.RATIO {self.ratio} keeps no point of MODEL.SEGMENT_POINTS {self.segment_points}")
        ckpt = self.task_checkpoint
        if ckpt is not None and (not isinstance(ckpt, (str, Path)) or not str(ckpt)):
            raise ConfigError(f"MODEL.TASK_CHECKPOINT must be a file path, a shipped name or null, got {ckpt!r}")
        if ckpt is not None:
            self.task_checkpoint = str(ckpt)
        if self.task is not None and not isinstance(self.task, Mapping):
            raise ConfigError(f"MODEL.TASK must be a PointPillars config dict or null, got {self.task!r}")
        self.task_config()

    @classmethod
    def from_openpcdet(cls, cfg: Mapping) -> "CASNetPointPillarsConfig":
        """From a whole config dict (``MODEL`` with ``NAME: CASNetPointPillars``; ``CLASS_NAMES`` and
        ``DATA_CONFIG`` are the dataset's and must agree with the detector's classes)."""
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"a config must be a mapping (OpenPCDet's schema), got {type(cfg).__name__}")
        model = cfg.get("MODEL")
        if not isinstance(model, Mapping) or model.get("NAME") != "CASNetPointPillars":
            raise ConfigError("MODEL.NAME must be 'CASNetPointPillars' for CASNetPointPillarsConfig, got "
                              f"{model.get('NAME') if isinstance(model, Mapping) else model!r}")
        unknown = sorted(set(model) - _MODEL_KEYS)
        if unknown:
            raise ConfigError(f"unknown MODEL keys {unknown} for CASNetPointPillars; known: {sorted(_MODEL_KEYS)}")
        kwargs = {name: model[key[6:]] for name, (key, *_r) in {**_SPEC, **_CHOICES}.items() if key[6:] in model}
        if "DEDUP" in model:
            kwargs["dedup"] = model["DEDUP"]
        if "TASK_CHECKPOINT" in model:
            kwargs["task_checkpoint"] = model["TASK_CHECKPOINT"]
        if model.get("TASK") is not None:
            kwargs["task"] = model["TASK"]
        out = cls(**kwargs)
        names = cfg.get("CLASS_NAMES")
        if out.task is not None and names is not None and list(names) != out.class_names:
            raise ConfigError(f"CLASS_NAMES {list(names)} differ from the detector's {out.class_names} (MODEL.TASK)")
        return out


def _load_task(cfg: CASNetPointPillarsConfig) -> PointPillars:
    """The detector of ``task_checkpoint``: a file, or the name of a shipped checkpoint."""
    from lidarops.models import weights

    source = cfg.task_checkpoint
    path = Path(source)
    if not path.is_file() and source in weights.available():
        path = weights.path(source)
    try:
        task = PointPillars.from_checkpoint(path)
    except (OSError, CheckpointError, ConfigError) as e:
        raise ConfigError(f"MODEL.TASK_CHECKPOINT {source}: {e}") from None
    if cfg.task is not None and PointPillarsConfig.from_dict(cfg.task).to_dict() != task.config.to_dict():
        raise ConfigError(f"MODEL.TASK disagrees with the detector of MODEL.TASK_CHECKPOINT {source}: leave it out "
                          "(the checkpoint carries its config)")
    return task


def sample_frames(casnet: CASNet, points: Tensor, batch_size: int, segment_points: int,
                  mode: str = "hard", dedup: bool = False, ratio: Optional[int] = None) -> tuple[Tensor, Any, Tensor]:
    """Every frame of an OpenPCDet batch sampled by ``casnet``, segment by segment.

    Args:
        casnet (CASNet): keeps ``casnet.num_out`` rows of each segment.
        points (Tensor[P, 1 + C]): frame index in column 0, then x, y, z, ... (OpenPCDet's batch).
        batch_size (int): frames.
        segment_points (int): segment size (each frame's points cut by
            :func:`~lidarops.models.samplers.spatial_segments`, padded to it, masked).
        mode (str), dedup (bool): passed to the model.
        ratio (int, optional): the anchored head only: each segment of ``n`` points keeps ``max(1, n // ratio)``
            rows (its first, anchored at its first farthest point samples), as inference does; without it
            (and with the paper's head) every segment keeps ``casnet.num_out``.

    Returns:
        ``(kept (Tensor[P', 1 + C]), out (CASNetOutput of the segments), segments (Tensor[S, segment_points, C]))``:
        the kept rows with their frame index (differentiable through the straight-through matrix in hard
        mode), the model's output and the padded segments it saw (for the Chamfer loss).
    """
    frame = points[:, 0].long()
    segs, owners = [], []
    for b in range(batch_size):
        pts = points[frame == b, 1:]
        for idx in spatial_segments(pts[:, :3], segment_points):
            segs.append(pts[idx])
            owners.append(b)
    lengths = torch.tensor([s.shape[0] for s in segs], dtype=torch.int64, device=points.device)
    batch = points.new_zeros(len(segs), segment_points, points.shape[1] - 1)
    for i, s in enumerate(segs):
        batch[i, :s.shape[0]] = s
    owner = torch.tensor(owners, dtype=points.dtype, device=points.device)
    if ratio is not None and casnet.head_kind == "anchored":
        shares = [max(1, s.shape[0] // ratio) for s in segs]
        out = casnet(batch, lengths, mode=mode, dedup=dedup, num_out=max(shares))
        kept = torch.cat([torch.cat([owner[i].view(1, 1).expand(share, 1), out.sampled[i, :share]], dim=1)
                          for i, share in enumerate(shares)])
        return kept, out, batch
    out = casnet(batch, lengths, mode=mode, dedup=dedup)
    kept = torch.cat([owner.view(-1, 1, 1).expand(-1, out.sampled.shape[1], 1), out.sampled], dim=2)
    # frames in order: segments were appended frame by frame
    return kept.reshape(-1, kept.shape[-1]), out, batch


class CASNetPointPillars(FrozenTaskMixin, PredictMixin, nn.Module):
    """CAS-Net keeping ``1/D`` of each frame's points for a frozen PointPillars (a
    :class:`lidarops.train.TrainableModel`; OpenPCDet's batch: ``points (P, 1 + C)``, ``batch_size``, in
    training ``gt_boxes``).

    ``forward(batch)`` returns in training ``{"loss", "loss_task", "loss_chamfer", "loss_cosine", "loss_cls",
    "loss_box", "loss_dir", "duplicates", "kept_points"}`` (``loss_task`` the detector's loss on the kept
    points; ``duplicates`` the mean repeated picks per segment, ``kept_points`` the mean points per frame,
    both logged without gradient); in eval mode the detector's raw outputs on the kept points, which
    :meth:`postprocess` (the detector's) turns into boxes.

    Attributes: ``casnet`` (:class:`CASNet`), ``task`` (:class:`PointPillars`, frozen), ``config``.
    """

    def __init__(self, config: "CASNetPointPillarsConfig | Mapping | str | Path | None" = None,
                 load_task: bool = True) -> None:
        super().__init__()
        cfg = as_model_config(config, CASNetPointPillarsConfig)
        if load_task and cfg.task_checkpoint is not None:
            task = _load_task(cfg)
        else:
            task = PointPillars(cfg.task_config())
        cfg = dataclasses.replace(cfg, task=task.config.to_dict())
        self.config = cfg
        self.casnet = casnet_of(cfg)
        self.task = task.eval().requires_grad_(False)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config) -> "CASNetPointPillars":
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config=None, map_location: Any = "cpu",
                        check_finite: bool = True) -> "CASNetPointPillars":
        """A model with the weights (CAS-Net's and the detector's) of a ``lidarops train`` checkpoint."""
        return model_from_checkpoint(cls, path, config, map_location, check_finite, load_task=False)

    @classmethod
    def casnet_of_checkpoint(cls, path: "str | Path") -> CASNet:
        """The CAS-Net of a checkpoint of this model (what :func:`lidarops.models.casnet.load_casnet` reads)."""
        return cls.from_checkpoint(path).casnet

    def load_weights(self, state_dict: Mapping[str, Tensor], source: str = "state dict",
                     check_finite: bool = True) -> None:
        """Strict loading with one error naming the keys that differ (and, with ``check_finite``, NaN or inf)."""
        load_weights_strict(self, state_dict, source, check_finite)

    def save(self, path: "str | Path", **extra: Any) -> Path:
        """Writes a lidarops checkpoint of the whole model (CAS-Net and detector) with its config."""
        from lidarops.checkpoint import format_fields, save_checkpoint

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint({**format_fields(), "model_class": type(self).__name__, "model_config": self.config.to_dict(),
                         "class_names": self.config.class_names,
                         "model_state": {k: v.detach().cpu() for k, v in self.state_dict().items()}, **extra}, [path])
        return path

    # ---------------------------------------------------------------- the network
    def pillars(self, points: Tensor, batch_size: int) -> tuple[Tensor, Tensor, Tensor]:
        """The detector's pillars of ``points`` (as :meth:`PointPillars.voxelize` builds them, test-time
        capacities), filled by an index copy so that gradients reach the points."""
        from lidarops.ops.voxelize import voxelize

        cfg = self.task.config
        c = cfg.num_point_features
        frame = points[:, 0].long()
        voxels, nums, coords = [], [], []
        for b in range(batch_size):
            pts = points[frame == b, 1:1 + c]
            res = voxelize(pts.detach(), cfg.voxel_size, cfg.point_cloud_range, cfg.max_points_per_voxel,
                           cfg.max_voxels_test, overflow="drop")
            pv, ps = res.info.point_voxel.long(), res.info.point_slot.long()
            keep = (pv >= 0) & (ps >= 0)
            v = pts.new_zeros(res.voxels.shape)
            v = v.index_put((pv[keep], ps[keep]), pts[keep])
            voxels.append(v)
            nums.append(res.num_points)
            coords.append(F.pad(res.coords, (1, 0), value=b))
        return torch.cat(voxels), torch.cat(nums), torch.cat(coords)

    def sample(self, points: Tensor, batch_size: int) -> tuple[Tensor, Any, Tensor]:
        """``(kept points (P', 1 + C), CASNetOutput, padded segments)``: :func:`sample_frames` with this
        model's CAS-Net and segment size."""
        return sample_frames(self.casnet, points, batch_size, self.config.segment_points, dedup=self.config.dedup,
                             ratio=self.config.ratio)

    def forward(self, batch: Mapping[str, Any]) -> "dict[str, Tensor]":
        dtype = self.task.vfe.pfn_layers[0].linear.weight.dtype
        points, batch_size = _check_batch(batch, self.task.config, self.training, dtype)
        c = self.task.config.num_point_features
        points = points[:, :1 + c]
        if not self.training:
            return self.task.network(*self.pillars(self.keep(points, batch_size), batch_size), batch_size)
        if points.shape[0] == 0:
            raise ValueError("batch['points'] holds no point: CAS-Net has nothing to sample in training")
        kept, out, segments = self.sample(points, batch_size)
        raw = self.task.network(*self.pillars(kept, batch_size), batch_size)
        det = self.task.dense_head.loss(raw, batch["gt_boxes"])
        losses = casnet_loss(out, segments, det["loss"], self.config.alpha, self.config.beta, self.config.cosine_form)
        losses.update({k: v.detach() for k, v in det.items() if k != "loss"})
        losses["duplicates"] = out.num_duplicates.float().mean()
        losses["kept_points"] = torch.tensor(kept.shape[0] / batch_size, device=kept.device)
        return losses

    @torch.no_grad()
    def keep(self, points: Tensor, batch_size: int) -> Tensor:
        """Inference: ``n // ratio`` rows of each frame of ``n`` (at least one), chosen by
        :class:`~lidarops.models.casnet.CASNetSampler` at this model's ratio and segment size, the budget
        random sampling and FPS get; rows of ``points`` (frame index first). Distinct points with
        ``dedup``; otherwise the most confident picks, repeats last (the paper's raw picks)."""
        from lidarops.models.casnet import CASNetSampler

        sampler = CASNetSampler(self.casnet, ratio=self.config.ratio, max_points=self.config.segment_points,
                                dedup=self.config.dedup)
        frame = points[:, 0].long()
        kept = []
        for b in range(batch_size):
            rows = torch.nonzero(frame == b).flatten()
            if rows.numel():
                idx = sampler(points[rows, 1:].unsqueeze(0), max(1, rows.numel() // self.config.ratio))[0]
                kept.append(points[rows[idx[idx >= 0]]])
        return torch.cat(kept) if kept else points

    def postprocess(self, raw: Mapping[str, Tensor], batch: Mapping[str, Any] | None = None) -> list[dict]:
        """The detector's boxes per frame (:meth:`PointPillars.postprocess`)."""
        return self.task.postprocess(raw, batch)
