"""What every lidarops model shares: its config from any of the forms users hand it, and ``predict``."""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, Mapping

import torch

from lidarops.config import ConfigError, load_config

__all__ = ["as_model_config", "PredictMixin", "DictConfig"]


def as_model_config(config: Any, cls: type):
    """``config`` as ``cls``: None (the defaults), a ``cls``, a YAML path (OpenPCDet's schema), an
    OpenPCDet-schema dict (with ``MODEL``) or a flat dict of ``cls``'s fields."""
    if config is None:
        return cls()
    if isinstance(config, cls):
        return config
    if isinstance(config, (str, Path)):
        return cls.from_openpcdet(load_config(config))
    if isinstance(config, Mapping):
        return cls.from_openpcdet(config) if "MODEL" in config else cls.from_dict(config)
    raise ConfigError(f"config must be a {cls.__name__}, a dict or a YAML path, got {type(config).__name__}")


class PredictMixin:
    """``predict(batch)``: the eval-mode forward and ``postprocess``, leaving the train/eval mode as it was."""

    @torch.no_grad()
    def predict(self, batch: Mapping[str, Any]) -> list[dict]:
        """Eval-mode forward and post-processing: one dict per frame (detectors: ``boxes``, ``scores``,
        ``labels``) or per object (classifiers: ``label``, ``score``, ``probs``)."""
        was_training = self.training
        self.eval()
        try:
            return self.postprocess(self(batch), batch)
        finally:
            self.train(was_training)


class DictConfig:
    """``to_dict`` / ``from_dict`` of a model's config dataclass: the plain values a checkpoint stores."""

    def to_dict(self) -> dict:
        """Plain values, as checkpoints store them."""
        return copy.deepcopy(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, d: Mapping):
        """Inverse of :meth:`to_dict`; unknown keys raise ``ConfigError``."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"a {cls.__name__} dict must be a mapping, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown {cls.__name__} keys {unknown}; known: {sorted(known)}")
        return cls(**copy.deepcopy(dict(d)))
