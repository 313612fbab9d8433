"""Per-frame model selection over several CounterNets (the seed's CN with model selection; issue 38).

Different models count different frames best (a partitioned model the crowded ones, a whole-map model the
sparse ones). :class:`SelectedCounter` holds the models and a
:class:`~lidarops.models.counting.ChernoffSelector`:

- :meth:`SelectedCounter.fit` runs every model over training frames, assigns each frame to the model whose
  counts are nearest the labels (the sum over classes of ``|count - true|``; ties: the lower model), and fits
  the selector on the frames' features;
- :meth:`SelectedCounter.predict` computes each frame's features, picks its model
  (``argmin_m ||f - omega_m|| * P_m``) and returns that model's counts, with ``model`` (the index) per frame.

The frame features are the global max-pool of the shared conv of one model, ``feature_model`` (default the
first): the models' own shared convs differ, so one of them must describe the frames for all.

::

    counter = SelectedCounter([cn, cn_pt, cn_pt_o]).fit(train_batches, epsilon=0.5)
    frames = counter.predict(batch)          # [{"counts", "centres", "model", ...}, ...]
    counter.save("selection.pth", ["cn.pth", "cn_pt.pth", "cn_pt_o.pth"])   # the members' checkpoints
    counter = lidarops.models.load_model("selection.pth")                  # or SelectedCounter.load(...)

The file :meth:`SelectedCounter.save` writes holds the fitted selector and where the members' checkpoints are
(paths relative to the file's folder, absolute paths, or names of shipped weights), not their weights, so
``lidarops index build --source counter --checkpoint selection.pth`` counts each frame with its model and records
the model's name per frame (the index's ``model`` column).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import torch
from torch import Tensor

from lidarops.models.counting import ChernoffSelector

__all__ = ["SelectedCounter"]


class SelectedCounter:
    """CounterNets behind a per-frame model choice; usable wherever one CounterNet is (``predict``,
    ``config.class_names``, ``parameters()``: e.g. :class:`lidarops.query.build.CounterSource`).

    Args:
        models (sequence of CounterNet): at least one, all counting the same classes, on one device.
        selector (ChernoffSelector, optional): a fitted selector (e.g. from :meth:`ChernoffSelector.from_state`);
            None: call :meth:`fit` first (with one model, none is needed).
        feature_model (int): whose shared-conv features describe the frames.
    """

    def __init__(self, models: Sequence[Any], selector: ChernoffSelector | None = None, feature_model: int = 0):
        models = list(models)
        if not models:
            raise ValueError("models is empty: give at least one CounterNet")
        names = [list(m.config.class_names) for m in models]
        if any(n != names[0] for n in names):
            raise ValueError(f"models must count the same classes, got {names}")
        devices = {next(m.parameters()).device for m in models}
        if len(devices) != 1:
            raise ValueError(f"models must be on one device, got {sorted(map(str, devices))}")
        if isinstance(feature_model, bool) or not isinstance(feature_model, int) \
                or not 0 <= feature_model < len(models):
            raise ValueError(f"feature_model must be an index into models [0, {len(models)}), got {feature_model!r}")
        self.models = models
        self.selector = selector
        self.feature_model = feature_model
        self.config = models[0].config
        self.names = [f"model{i}" for i in range(len(models))]  # each member's name (its file's, once loaded)

    def parameters(self):
        for m in self.models:
            yield from m.parameters()

    def eval(self) -> "SelectedCounter":
        for m in self.models:
            m.eval()
        return self

    def to(self, device) -> "SelectedCounter":
        """The members and the selector on ``device``."""
        self.models = [m.to(device) for m in self.models]
        return self

    def save(self, path: "str | Path", members: Sequence["str | Path"]) -> Path:
        """Writes the selection to ``path``: the fitted selector, ``feature_model`` and, for each member in order,
        where its checkpoint is (``members``: paths, written relative to ``path``'s folder when inside it, or
        names of shipped weights), not its weights."""
        from lidarops.checkpoint import format_fields, save_checkpoint

        if len(members) != len(self.models):
            raise ValueError(f"members must name the {len(self.models)} models' checkpoints, got {len(members)}")
        if self.selector is None and len(self.models) > 1:
            raise ValueError("no selector: call fit(batches, epsilon) before save")
        path = Path(path)
        refs = []
        for m in members:
            p = Path(m)
            if p.suffix in (".pth", ".xz", ".pt") or p.exists():
                p = p.resolve()
                try:
                    p = p.relative_to(path.resolve().parent)
                except ValueError:
                    pass
            refs.append(str(p))
        record = {**format_fields(), "model_class": "SelectedCounter", "class_names": list(self.config.class_names),
                  "model_config": {"members": refs, "feature_model": self.feature_model,
                                   "class_names": list(self.config.class_names)},
                  "selector": None if self.selector is None else self.selector.state_dict()}
        path.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(record, [path])
        return path

    @classmethod
    def load(cls, path: "str | Path", map_location: Any = "cpu") -> "SelectedCounter":
        """The selection :meth:`save` wrote, its members loaded from their checkpoints (``ValueError`` naming a
        member that cannot be found or is not a CounterNet)."""
        from lidarops.checkpoint import CheckpointError, read_checkpoint
        from lidarops.models import load_model, weights

        path = Path(path)
        ckpt = read_checkpoint(path, map_location)
        cfg = ckpt.get("model_config") or {}
        refs = cfg.get("members")
        if ckpt.get("model_class") != "SelectedCounter" or not isinstance(refs, list) or not refs:
            raise CheckpointError(f"{path}: not a SelectedCounter file (model_class {ckpt.get('model_class')!r})")
        models, names = [], []
        for ref in refs:
            p = Path(ref)
            p = p if p.is_absolute() else path.parent / p
            if not p.is_file():
                if str(ref) not in weights.available():
                    raise CheckpointError(f"{path}: member {ref!r} is neither a file (looked for {p}) nor a shipped "
                                          f"checkpoint ({', '.join(weights.available())})")
                p = weights.path(str(ref))
            model = load_model(p, map_location=map_location)
            if type(model).__name__ != "CounterNet":
                raise CheckpointError(f"{path}: member {ref!r} holds a {type(model).__name__}, not a CounterNet")
            models.append(model)
            names.append(Path(str(ref)).name.split(".pth")[0])
        selector = None if ckpt.get("selector") is None else ChernoffSelector.from_state(ckpt["selector"])
        out = cls(models, selector, int(cfg.get("feature_model", 0)))
        out.names = names
        return out

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: Any = None, map_location: Any = "cpu",
                        check_finite: bool = True) -> "SelectedCounter":
        """:meth:`load` under :func:`lidarops.models.load_model`'s signature (``config``: unused)."""
        return cls.load(path, map_location)

    @torch.no_grad()
    def features(self, batch: Mapping[str, Any]) -> Tensor:
        """``(B, S)``: the feature model's global max-pool of its shared conv, per frame."""
        model = self.models[self.feature_model]
        was = model.training
        model.eval()
        try:
            return model(batch)["features"]
        finally:
            model.train(was)

    @torch.no_grad()
    def fit(self, batches: Iterable[Mapping[str, Any]], epsilon: float) -> "SelectedCounter":
        """Assigns each training frame to its best model and fits the selector.

        Args:
            batches: OpenPCDet batches holding ``gt_boxes`` (the labels the counts are scored against), e.g.
                a DataLoader over a KITTI-format training split with ``collate_batch``.
            epsilon (float > 0): the Chernoff bound's epsilon, in the features' units.

        Returns:
            self (``self.best`` holds each frame's model, ``self.errors`` the (F, M) count errors).
        """
        feats, errors = [], []
        for batch in batches:
            if not isinstance(batch.get("gt_boxes"), Tensor):
                raise ValueError("each batch must hold gt_boxes: the frames are assigned by their labelled counts")
            per_model = []
            for m in self.models:
                frames = m.predict(batch)
                per_model.append(torch.stack([(f["counts"] - f["true_counts"]).abs().sum() for f in frames]))
            errors.append(torch.stack(per_model, dim=1))
            feats.append(self.features(batch))
        if not feats:
            raise ValueError("batches is empty: no frame to fit the selection on")
        self.errors = torch.cat(errors)
        self.best = torch.argmin(self.errors, dim=1)  # ties: the first minimum, the lower model
        self.selector = ChernoffSelector().fit(torch.cat(feats).double(), self.best, len(self.models), epsilon)
        return self

    @torch.no_grad()
    def choose(self, batch: Mapping[str, Any]) -> Tensor:
        """``(B,)`` int64: the model each frame of the batch is counted by."""
        if len(self.models) == 1:
            return torch.zeros(int(batch["batch_size"]), dtype=torch.int64)
        if self.selector is None:
            raise ValueError("no selector: call fit(batches, epsilon) first, or pass a fitted selector")
        return self.selector.select(self.features(batch).double().to(self.selector.centres.device)).cpu()

    @torch.no_grad()
    def predict(self, batch: Mapping[str, Any]) -> list[dict]:
        """Each frame counted by its chosen model (the models chosen by no frame of the batch are not run):
        the chosen model's per-frame output, with ``model`` (its index) and ``model_name`` added."""
        choice = self.choose(batch)
        out: list[dict | None] = [None] * len(choice)
        for m in torch.unique(choice).tolist():
            frames = self.models[m].predict(batch)
            for b in torch.nonzero(choice == m).flatten().tolist():
                out[b] = {**frames[b], "model": m, "model_name": self.names[m]}
        return out  # type: ignore[return-value]
