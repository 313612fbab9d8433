"""Shipped checkpoints (``lidarops/weights/*.pth``, or ``*.pth.xz``): models trained on the simulator's
data, loaded without any download.

    from lidarops.models import weights
    model = weights.load("pointpillars_synth")          # PointPillars, Car / Pedestrian / Cyclist
    counter = weights.load("counternet_road7")           # CounterNet, seven road classes
    weights.available()                                  # names of the shipped checkpoints

A checkpoint too large for the 10 MB a shipped file may take is stored xz-compressed (``<name>.pth.xz``):
:func:`path` unpacks it once into a cache folder (``$LIDAROPS_CACHE``, default ``~/.cache/lidarops``, a
temporary folder where that cannot be written), named by the compressed file's SHA-256 so a changed file is
unpacked again.

Each file is a :mod:`lidarops.checkpoint` file: ``model_state`` (float16 weights), the model's class and
resolved config, ``class_names``, the lidarops version, the data recipe, the training command and the
evaluation of the model; :func:`load` builds the model the file names (:func:`lidarops.models.load_model`).
``docs/train.md`` lists the shipped files with their recipes.
"""
from __future__ import annotations

from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
DEFAULT = "pointpillars_synth"

__all__ = ["WEIGHTS_DIR", "DEFAULT", "available", "path", "info", "trained_scenarios", "load", "export"]


def available() -> list[str]:
    """Names of the shipped checkpoints."""
    return sorted({p.stem for p in WEIGHTS_DIR.glob("*.pth")} | {p.name[:-len(".pth.xz")]
                                                                 for p in WEIGHTS_DIR.glob("*.pth.xz")})


def path(name: str = DEFAULT) -> Path:
    """The file of a shipped checkpoint (``FileNotFoundError`` naming the available ones); a compressed one
    unpacked into the cache."""
    p = WEIGHTS_DIR / f"{name}.pth"
    if p.is_file():
        return p
    packed = WEIGHTS_DIR / f"{name}.pth.xz"
    if not packed.is_file():
        raise FileNotFoundError(f"no shipped checkpoint {name!r} in {WEIGHTS_DIR} (available: {available() or 'none'})")
    return _unpacked(packed)


def _unpacked(packed: Path) -> Path:
    """``packed`` (``<name>.pth.xz``) unpacked into the cache, once per content."""
    import hashlib
    import lzma
    import os
    import tempfile

    digest = hashlib.sha256(packed.read_bytes()).hexdigest()[:16]
    name = f"{packed.name[:-len('.pth.xz')]}-{digest}.pth"
    roots = [Path(os.environ.get("LIDAROPS_CACHE") or Path.home() / ".cache" / "lidarops") / "weights",
             Path(tempfile.gettempdir()) / "lidarops-weights"]
    for root in roots:
        out = root / name
        if out.is_file():
            return out
        try:
            root.mkdir(parents=True, exist_ok=True)
            # written beside and renamed: a reader never sees half a file, two writers never clash
            fd, tmp = tempfile.mkstemp(dir=root, suffix=".part")
            with os.fdopen(fd, "wb") as f:
                f.write(lzma.decompress(packed.read_bytes()))
            os.replace(tmp, out)
            return out
        except OSError:
            continue
    raise OSError(f"cannot unpack {packed}: neither {roots[0]} nor {roots[1]} can be written (set LIDAROPS_CACHE)")


def info(name: str = DEFAULT) -> dict:
    """Everything a shipped checkpoint says about itself except the weights."""
    from lidarops.checkpoint import read_checkpoint

    ckpt = read_checkpoint(path(name))
    return {k: v for k, v in ckpt.items() if k != "model_state"}


def _recipe_entries(checkpoint: "str | Path") -> tuple[dict, list]:
    """A checkpoint's data recipe and its list of scenario entries (a shipped name or a file); empty when it has
    none or cannot be read."""
    from lidarops.checkpoint import read_checkpoint

    file = Path(checkpoint)
    try:
        recipe = read_checkpoint(file if file.is_file() else path(str(checkpoint))).get("data_recipe") or {}
    except (OSError, ValueError):
        return {}, []
    if not isinstance(recipe, dict):
        return {}, []
    entries = recipe.get("scenarios")
    return recipe, [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


def trained_scenarios(checkpoint: "str | Path") -> list[str]:
    """The simulator scenarios a checkpoint's data recipe names, in order (a shipped name or a file); ``[]``
    when it names none or cannot be read."""
    return [e["scenario"] for e in _recipe_entries(checkpoint)[1] if isinstance(e.get("scenario"), str)]


def trained_realism(checkpoint: "str | Path", scenario: str) -> "str | None":
    """The simulator's realism profile of the first frames of ``scenario`` in a checkpoint's data recipe (a
    ``data synth --realism`` per scenario, or the one profile of older recipes); None: ray-cast, not named, or
    unreadable."""
    recipe, entries = _recipe_entries(checkpoint)
    for entry in entries:
        if entry.get("scenario") == scenario:
            profile = entry["realism"] if "realism" in entry else recipe.get("realism")
            return profile if isinstance(profile, str) else None
    return None


def load(name: str = DEFAULT, map_location="cpu"):
    """The shipped model ``name`` in eval mode (float32 weights), of the class its file records."""
    from lidarops.models import load_model

    return load_model(path(name), map_location=map_location)


def export(checkpoint: "str | Path", out: "str | Path", **extra) -> Path:
    """Writes a shippable file from a training checkpoint (``lidarops train``'s ``final.pth``): the model's
    weights in float16, its config, class names, data recipe, training command and evaluation, without
    the optimizer state. ``extra`` entries (e.g. ``evaluation=...``) are added."""
    from lidarops.checkpoint import format_fields, model_record, read_checkpoint, save_checkpoint

    ckpt = read_checkpoint(checkpoint)
    record = model_record(ckpt, str(checkpoint))
    if "model_state" not in ckpt or record.config is None:
        raise ValueError(f"{checkpoint}: not a lidarops checkpoint of a model (needs model_state and model_config)")
    state = {k: (v.half() if v.is_floating_point() else v) for k, v in ckpt["model_state"].items()}
    keep = ("config_path", "data_recipe", "train_command", "epoch", "it", "elapsed_s", "frames", "config")
    shipped = {**format_fields(), "model_class": record.model_class, "model_config": record.config,
               "class_names": list(record.class_names or ()), "model_state": state,
               **{k: ckpt[k] for k in keep if k in ckpt}, **extra}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(shipped, [out])
    return out


if __name__ == "__main__":  # python -m lidarops.models.weights CHECKPOINT OUT [EVAL_JSON]
    import json
    import sys

    evaluation = json.loads(Path(sys.argv[3]).read_text()) if len(sys.argv) > 3 else None
    print(export(sys.argv[1], sys.argv[2], **({"evaluation": evaluation} if evaluation else {})))
