"""What every lidarops model shares: its config from any of the forms users hand it, and ``predict``."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import torch

from lidarops.config import ConfigError, load_config

__all__ = ["as_model_config", "PredictMixin"]


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
