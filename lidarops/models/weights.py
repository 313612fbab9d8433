"""Shipped checkpoints (``lidarops/weights/*.pth``): models trained on the simulator's data, loaded
without any download.

    from lidarops.models import weights
    model = weights.load("pointpillars_synth")          # PointPillars, Car / Pedestrian / Cyclist
    weights.available()                                  # names of the shipped checkpoints

Each file holds ``model_state`` (float16 weights), ``model_config`` (the resolved
:class:`~lidarops.models.config.PointPillarsConfig`), ``class_names``, the lidarops version, the data
recipe, the training command and the evaluation of the model; ``docs/detector.md`` gives the same in prose.
"""
from __future__ import annotations

from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
DEFAULT = "pointpillars_synth"

__all__ = ["WEIGHTS_DIR", "DEFAULT", "available", "path", "info", "load"]


def available() -> list[str]:
    """Names of the shipped checkpoints."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.pth"))


def path(name: str = DEFAULT) -> Path:
    """The file of a shipped checkpoint (``FileNotFoundError`` naming the available ones)."""
    p = WEIGHTS_DIR / f"{name}.pth"
    if not p.is_file():
        raise FileNotFoundError(f"no shipped checkpoint {name!r} in {WEIGHTS_DIR} (available: {available() or 'none'})")
    return p


def info(name: str = DEFAULT) -> dict:
    """Everything a shipped checkpoint says about itself except the weights."""
    import torch

    ckpt = torch.load(str(path(name)), map_location="cpu", weights_only=False)
    return {k: v for k, v in ckpt.items() if k != "model_state"}


def load(name: str = DEFAULT, map_location="cpu"):
    """The shipped model ``name`` in eval mode (float32 weights)."""
    from lidarops.models.detector import PointPillars

    return PointPillars.from_checkpoint(path(name), map_location=map_location).eval()
