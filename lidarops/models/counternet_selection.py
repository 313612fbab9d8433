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
"""
from __future__ import annotations

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

    def parameters(self):
        for m in self.models:
            yield from m.parameters()

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
        the chosen model's per-frame output, with ``model`` (its index) added."""
        choice = self.choose(batch)
        out: list[dict | None] = [None] * len(choice)
        for m in torch.unique(choice).tolist():
            frames = self.models[m].predict(batch)
            for b in torch.nonzero(choice == m).flatten().tolist():
                out[b] = {**frames[b], "model": m}
        return out  # type: ignore[return-value]
