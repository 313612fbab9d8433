"""The one checkpoint format: every file lidarops writes (a training run's checkpoints, a shipped model,
an exported one) is one ``torch.save`` dict, read back with ``weights_only=True`` by :func:`read_checkpoint`.

Keys (OpenPCDet's names where it has one, so its tools read ours)::

    format            "lidarops.checkpoint"           format_version   2
    lidarops_version  "<version>"                      version          "lidarops+<version>" (OpenPCDet's key)
    model_class       the model's class name (the key of lidarops.models.MODELS)
    model_config      the model's resolved config (its config dataclass as a dict)
    class_names       the model's classes, in label order (labels are 1-based into them)
    model_state       the model's state_dict (OpenPCDet's key)
    training state    optimizer_state, scheduler_state, scaler_state, epoch, it, rng, ... (lidarops.train)
    provenance        config_path, data_recipe, train_command, evaluation (optional)

Files older than this format still load: a shipped model or a training checkpoint of lidarops 0.1
(``model_config`` without ``model_class``: a PointPillars), and OpenPCDet's own checkpoints
(``model_state`` only: the caller gives the config). :func:`model_record` says which model a file holds.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

__all__ = ["FORMAT", "FORMAT_VERSION", "CheckpointError", "ModelRecord", "read_checkpoint", "save_checkpoint",
           "model_record", "model_state", "model_fields", "format_fields", "check_plain", "check_finite"]

FORMAT = "lidarops.checkpoint"
FORMAT_VERSION = 2
# format names earlier versions wrote: a training checkpoint of lidarops 0.1
_OLD_FORMATS = ("lidarops.train.checkpoint",)
# what a lidarops 0.1 file holding model_config (and no model_class) holds: the only model it had
_OLD_MODEL_CLASS = "PointPillars"


class CheckpointError(ValueError):
    """A file that is not a readable checkpoint, or whose weights do not fit the model; the message names
    the file and, for a mismatch, every key that differs."""


@dataclass(frozen=True)
class ModelRecord:
    """Which model a checkpoint holds.

    Attributes:
        model_class (str | None): the class name (None for an OpenPCDet checkpoint, which does not say).
        config (dict | None): the resolved model config (None for an OpenPCDet checkpoint).
        class_names (tuple[str, ...] | None): the classes, in label order.
        format_version (int): 0 for files without a ``format`` key (lidarops 0.1's shipped models,
            OpenPCDet's checkpoints), else the file's version.
    """

    model_class: "str | None"
    config: "dict | None"
    class_names: "tuple[str, ...] | None"
    format_version: int


def _numpy_scalar_globals() -> list:
    """What unpickling NumPy scalars needs: OpenPCDet's ``train.py`` saves its one-cycle schedule's learning
    rates and betas as ``numpy.float64`` in ``optimizer_state``. Data constructors only (no code runs)."""
    import numpy as np

    try:
        from numpy._core.multiarray import scalar
    except ImportError:  # NumPy < 2
        from numpy.core.multiarray import scalar
    return [scalar, np.dtype] + [type(np.dtype(t)) for t in ("float64", "float32", "float16", "int64", "int32",
                                                              "int16", "int8", "uint8", "bool")]


def read_checkpoint(path: "str | os.PathLike", map_location: Any = "cpu") -> dict:
    """The dict a checkpoint file holds, loaded with ``weights_only=True`` (a pickle can run code; lidarops'
    and OpenPCDet's checkpoints hold only tensors and plain values, and NumPy scalars, which are allowed).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: not a readable checkpoint (truncated, not a torch file, not a dict, holding objects
            ``weights_only`` refuses, or written by a newer lidarops); the message names the file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    try:
        with torch.serialization.safe_globals(_numpy_scalar_globals()):
            ckpt = torch.load(str(path), map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001  (torch.load raises many types for a damaged or foreign file)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        # a torch file (a zip archive: "PK", or a legacy pickle: 0x80) holding objects beyond tensors; anything
        # else is not a checkpoint at all, and the advice to unpickle it must not be given
        with open(path, "rb") as f:
            head = f.read(2)
        if "weights only load failed" in first.lower() and (head == b"PK" or head[:1] == b"\x80"):
            raise CheckpointError(
                f"{path}: a torch file holding objects that safe loading refuses (it could run code); only if "
                "you trust where it came from, load it with torch.load(..., weights_only=False) and pass its "
                "state dict to model.load_weights") from None
        if not (head == b"PK" or head[:1] == b"\x80"):
            raise CheckpointError(f"{path}: not a checkpoint (neither a torch zip archive nor a pickle: it starts "
                                  f"with {head!r}); give a .pth file that lidarops or OpenPCDet wrote") from None
        raise CheckpointError(f"{path}: a damaged or truncated checkpoint (torch cannot read it: "
                              f"{type(e).__name__}: {first[:160]})") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path}: not a checkpoint (a {type(ckpt).__name__}, not a dict)")
    version = ckpt.get("format_version", 0)
    if ckpt.get("format") == FORMAT and isinstance(version, int) and version > FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {version}, newer than this lidarops reads "
                              f"({FORMAT_VERSION}): upgrade lidarops")
    return ckpt


def model_record(ckpt: Mapping[str, Any], source: str = "checkpoint") -> ModelRecord:
    """Which model ``ckpt`` (a dict from :func:`read_checkpoint`) holds; ``CheckpointError`` naming
    ``source`` when its model entries are malformed."""
    fmt = ckpt.get("format")
    version = int(ckpt.get("format_version", 0)) if fmt in (FORMAT, *_OLD_FORMATS) else 0
    config = ckpt.get("model_config")
    model_class = ckpt.get("model_class")
    if model_class is None and config is not None:
        model_class = _OLD_MODEL_CLASS
    if model_class is not None and not isinstance(model_class, str):
        raise CheckpointError(f"{source}: model_class must be a class name, got {model_class!r}")
    if config is not None and not isinstance(config, Mapping):
        raise CheckpointError(f"{source}: model_config must be a dict, got a {type(config).__name__}")
    names = ckpt.get("class_names")
    if names is None and isinstance(config, Mapping):
        names = config.get("class_names")
    if names is not None and (isinstance(names, str) or not all(isinstance(n, str) for n in names)):
        raise CheckpointError(f"{source}: class_names must be a list of names, got {names!r}")
    return ModelRecord(model_class, dict(config) if config is not None else None,
                       tuple(names) if names is not None else None, version)


def model_state(ckpt: Mapping[str, Any], source: str = "checkpoint") -> Mapping[str, Any]:
    """The state dict a checkpoint holds: ``model_state`` (lidarops', OpenPCDet's), ``state_dict`` or
    ``model``; ``CheckpointError`` naming ``source`` when there is none."""
    for key in ("model_state", "state_dict", "model"):
        state = ckpt.get(key)
        if isinstance(state, Mapping):
            return state
    raise CheckpointError(f"{source}: no model_state / state_dict in the checkpoint (keys: {sorted(map(str, ckpt))[:8]})")


def check_finite(state: Mapping[str, Any], source: str = "state dict") -> None:
    """Refuses a state dict holding NaN or infinite values (``CheckpointError`` naming the tensors and how
    many values each): one damaged weight would otherwise turn every output into NaN, and a detector
    would silently find nothing. One reduction per floating tensor."""
    import torch

    bad = []
    for name, value in state.items():
        if isinstance(value, torch.Tensor) and (value.is_floating_point() or value.is_complex()) and value.numel():
            n = int((~torch.isfinite(value)).sum())
            if n:
                bad.append(f"{name} ({n} of {value.numel()})")
    if bad:
        raise CheckpointError(f"{source} holds non-finite values (NaN or inf) in {len(bad)} tensor(s): "
                              f"{', '.join(bad[:8])}{' ...' if len(bad) > 8 else ''}; the model would output NaN. "
                              "Load it anyway with check_finite=False")


def model_fields(model: Any) -> dict[str, Any]:
    """The entries that say which model a file holds: ``model_class`` always; ``model_config`` and
    ``class_names`` when the model has a ``config`` with ``to_dict()`` (and ``class_names``)."""
    out: dict[str, Any] = {"model_class": type(model).__name__}
    config = getattr(model, "config", None)
    if config is not None and hasattr(config, "to_dict"):
        out["model_config"] = config.to_dict()
        names = getattr(config, "class_names", None)
        if names is not None:
            out["class_names"] = list(names)
    return out


def format_fields() -> dict[str, Any]:
    """``format``, ``format_version``, ``lidarops_version`` and OpenPCDet's ``version``."""
    from lidarops import __version__

    return {"format": FORMAT, "format_version": FORMAT_VERSION, "lidarops_version": __version__,
            "version": f"lidarops+{__version__}"}


def save_checkpoint(state: Mapping[str, Any], paths: "list[Path] | Path") -> None:
    """Writes ``state`` to each path atomically: a temporary file in the same folder, then ``os.replace``,
    so a kill at any moment leaves either the previous file or the new one."""
    import torch

    first = None
    for path in [paths] if isinstance(paths, (str, Path)) else paths:
        path = Path(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                if first is None:
                    torch.save(dict(state), f)
                else:
                    with open(first, "rb") as src:
                        while chunk := src.read(1 << 24):
                            f.write(chunk)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        first = first or path


def check_plain(value: Any, where: str = "extra_checkpoint") -> None:
    """Raises ``TypeError`` unless ``value`` is made of dicts (str keys), lists, tuples, str, numbers,
    None and tensors: what ``torch.load(weights_only=True)`` reads back."""
    import torch

    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: keys must be str, got {k!r}")
            check_plain(v, f"{where}[{k!r}]")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            check_plain(v, f"{where}[{i}]")
    elif not isinstance(value, (str, int, float, bool, type(None), torch.Tensor)):
        raise TypeError(f"{where} is a {type(value).__name__}; checkpoints hold only dicts, lists, str, numbers, "
                        f"None and tensors (convert dataclasses with dataclasses.asdict)")
