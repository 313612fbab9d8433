"""What every lidarops model shares: its config from any of the forms users hand it, and ``predict``."""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, Mapping

import torch

from lidarops.config import ConfigError, load_config

__all__ = ["as_model_config", "PredictMixin", "DictConfig", "read_object_config", "model_from_checkpoint",
           "load_weights_strict"]


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
        replayed = self._predict_replayed(batch)
        if replayed is not None:
            return replayed
        was_training = self.training
        self.eval()
        try:
            return self.postprocess(self(batch), batch)
        finally:
            self.train(was_training)

    def _predict_replayed(self, batch: Mapping[str, Any]) -> list[dict] | None:
        """``predict``'s result from a graph recorded in eval mode, or None where the eager call runs (a model's
        choice); it leaves the train/eval mode as it was."""
        return None


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


def read_object_config(cfg: Any, name: str, model_keys: set, spec: Mapping) -> tuple[Mapping, Mapping, dict]:
    """The common part of reading an object classifier's whole config (``CLASS_NAMES``, ``DATA_CONFIG``,
    ``MODEL`` with ``NAME: <name>``): checks the shapes and the ``MODEL`` keys (``ConfigError`` naming the
    key) and returns ``(MODEL, DATA_CONFIG, kwargs)``, ``kwargs`` holding ``class_names``, ``in_channels``
    (from ``used_feature_list``) and every ``MODEL.*`` entry of ``spec`` (field -> (key, ...)) present."""
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"a config must be a mapping (OpenPCDet's schema), got {type(cfg).__name__}")
    model = cfg.get("MODEL")
    if not isinstance(model, Mapping):
        raise ConfigError(f"MODEL must be a mapping of keys, got {model!r}")
    if model.get("NAME") != name:
        raise ConfigError(f"MODEL.NAME must be '{name}' for {name}Config, got {model.get('NAME')!r}")
    unknown = sorted(set(model) - set(model_keys))
    if unknown:
        raise ConfigError(f"unknown MODEL keys {unknown} for {name}; known: {sorted(model_keys)}")
    if "CLASS_NAMES" not in cfg:
        raise ConfigError("config key CLASS_NAMES is missing")
    kwargs: dict[str, Any] = {"class_names": cfg["CLASS_NAMES"]}
    data = cfg.get("DATA_CONFIG", {})
    data = data if isinstance(data, Mapping) else {}
    encoding = data.get("POINT_FEATURE_ENCODING", {})
    used = encoding.get("used_feature_list") if isinstance(encoding, Mapping) else None
    if used is not None:
        if not isinstance(used, list) or used[:3] != ["x", "y", "z"]:
            raise ConfigError("DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list must be a list starting "
                              f"with x, y, z, got {used!r}")
        kwargs["in_channels"] = len(used)
    for field_name, (key, *_rest) in spec.items():
        if key.startswith("MODEL.") and key[6:] in model:
            kwargs[field_name] = model[key[6:]]
    return model, data, kwargs


def model_from_checkpoint(cls: type, path: "str | Path", config: Any = None, map_location: Any = "cpu",
                          check_finite: bool = True, **build: Any):
    """The common ``from_checkpoint`` of the models: reads a lidarops checkpoint (refusing one of another model
    class), builds ``cls(config or the config it records, **build)`` and loads its weights with
    ``model.load_weights`` (strict; with ``check_finite`` NaN or infinite values are refused). Errors name
    ``path``."""
    from lidarops.checkpoint import CheckpointError, model_record, model_state, read_checkpoint

    ckpt = read_checkpoint(path, map_location)
    record = model_record(ckpt, str(path))
    if record.model_class not in (None, cls.__name__):
        raise CheckpointError(f"{path} holds a {record.model_class}, not a {cls.__name__}: load it with "
                              "lidarops.models.load_model(path)")
    config = record.config if config is None else config
    if config is None:
        raise ConfigError(f"{path} carries no model config: pass config=...")
    try:
        model = cls(config, **build)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    model.load_weights(model_state(ckpt, str(path)), source=str(path), check_finite=check_finite)
    return placed(model, map_location)


def placed(model, map_location: Any):
    """``model`` moved to ``map_location`` when that names a device (a str or ``torch.device``): loading copies the
    weights into the model's own tensors, so without this a model read with ``map_location="cuda"`` would stay
    on the CPU, its buffers too."""
    if isinstance(map_location, (str, torch.device)):
        model.to(map_location)
    return model


def load_weights_strict(model, state_dict: Mapping[str, Any], source: str = "state dict", check_finite: bool = True) -> None:
    """``model.load_state_dict(strict=True)`` after one check of every key and shape (a ``CheckpointError`` naming
    the missing, unexpected and differently shaped keys) and, with ``check_finite``, of NaN or infinite values;
    the values are cast to the model's dtypes (float16 shipped weights load into float32 models)."""
    from lidarops import checkpoint
    from lidarops.checkpoint import CheckpointError

    own = model.state_dict()
    missing = [k for k in own if k not in state_dict]
    unexpected = [k for k in state_dict if k not in own]
    shapes = [k for k in own if k in state_dict and tuple(state_dict[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        raise CheckpointError(f"{source} does not fit this {type(model).__name__} config: missing {missing[:6]}, "
                              f"unexpected {unexpected[:6]}, shape mismatch {shapes[:6]}")
    if check_finite:
        checkpoint.check_finite(state_dict, source)
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in state_dict.items()}, strict=True)
