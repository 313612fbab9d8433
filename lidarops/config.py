"""Configs: YAML files with OpenPCDet's schema (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``,
``OPTIMIZATION``) read into plain dicts, with ``_BASE_CONFIG_`` merging. The ground floor: models,
datasets and the trainer each read their part of the same dict into their own dataclass.

lidarops' own configs (``lidarops/configs/<model>/*.yaml``, over ``datasets/``; ``configs/`` at the
repository's root) ship inside the package and load by name from any directory. They use the same
schema, so an OpenPCDet ``pointpillar.yaml`` and a lidarops config load the same way::

    from lidarops.config import load_config
    cfg = load_config("pointpillars_synth")          # or "configs/pointpillars/pointpillars_synth.yaml", or any path
    model_cfg = PointPillarsConfig.from_openpcdet(cfg)                   # typed, validated (lidarops.models)

``_BASE_CONFIG_`` may appear at any level (OpenPCDet puts it under ``DATA_CONFIG``); the base file's
keys are loaded first and the including file's keys merged over them, recursively. Its path is tried
as given, relative to the including file and to each folder above it (OpenPCDet's paths are relative
to its ``tools/`` folder, e.g. ``cfgs/dataset_configs/kitti_dataset.yaml``), relative to the working
directory, and among the shipped configs (so a copy of ``pointpillars_demo.yaml`` loads anywhere).
"""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Mapping

__all__ = ["load_config", "merge_config", "ConfigError", "packaged_configs", "resolve_config", "PACKAGED_CONFIGS"]


class ConfigError(ValueError):
    """A config file or dict that lidarops cannot build a model from; the message says which key."""


def _yaml():
    try:
        import yaml
    except ImportError:  # pyyaml is what reads configs; it is in lidarops' requirements
        raise ConfigError("reading YAML configs needs pyyaml: pip install pyyaml") from None
    return yaml


#: The configs lidarops ships (``lidarops/configs``, also ``configs/`` at the repository's root).
PACKAGED_CONFIGS = Path(__file__).resolve().parent / "configs"


def _find_base(name: str, including: Path) -> Path:
    tried = []
    # a copy of a shipped config keeps working outside the repository: its base is found among the shipped ones
    candidates = [Path(name)] if Path(name).is_absolute() else (
        [d / name for d in [including.parent, *including.parent.parents]] + [Path.cwd() / name,
                                                                              PACKAGED_CONFIGS / name])
    for c in candidates:
        tried.append(str(c))
        if c.is_file():
            return c
    raise ConfigError(f"{including}: _BASE_CONFIG_ {name!r} not found (tried {', '.join(tried[:4])}"
                      f"{', ...' if len(tried) > 4 else ''})")


def merge_config(base: dict, new: Mapping, source: Path | None = None, _chain: tuple = ()) -> dict:
    """Merges ``new`` into ``base`` in place (OpenPCDet's ``merge_new_config``): a ``_BASE_CONFIG_`` key
    loads that file into ``base`` first; dict values merge recursively, others replace."""
    if "_BASE_CONFIG_" in new:
        if source is None:
            raise ConfigError("_BASE_CONFIG_ needs the path of the including file to resolve it")
        if not isinstance(new["_BASE_CONFIG_"], str):
            raise ConfigError(f"{source}: _BASE_CONFIG_ must be a file name, got {new['_BASE_CONFIG_']!r}")
        base.update(_load(_find_base(new["_BASE_CONFIG_"], source), _chain))
    for key, value in new.items():
        if key == "_BASE_CONFIG_":
            continue
        if isinstance(value, Mapping):
            if not isinstance(base.get(key), dict):
                base[key] = {}
            merge_config(base[key], value, source, _chain)
        else:
            base[key] = copy.deepcopy(value)
    return base


def packaged_configs() -> dict[str, Path]:
    """The shipped configs by name (the file's stem, e.g. ``"pointpillars_synth"``): what
    :func:`load_config` finds by name from any directory. Base files (``datasets/``) are left out."""
    return {p.stem: p for p in sorted(PACKAGED_CONFIGS.rglob("*.yaml")) if p.parent.name != "datasets"}


def resolve_config(path: str | Path) -> Path:
    """The file ``path`` names: the path itself when it is a file; else a shipped config by name
    (``pointpillars_demo``), or by its path in the repository (``configs/pointpillars/pointpillars_demo.yaml``),
    so that the docs' commands work from any directory.

    Raises:
        FileNotFoundError: neither a file nor a shipped config; the message lists the shipped names.
    """
    given = Path(path)
    if given.is_file():
        return given
    parts = given.parts[1:] if given.parts[:1] == ("configs",) else given.parts
    candidates = []
    if parts and not given.is_absolute():
        rel = Path(*parts)
        candidates += [PACKAGED_CONFIGS / rel, PACKAGED_CONFIGS / rel.with_name(rel.name + ".yaml")]
    shipped = packaged_configs()
    if given.suffix in ("", ".yaml") and given.stem in shipped and len(given.parts) == 1:
        candidates.append(shipped[given.stem])
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(f"config file not found: {path} (nor a shipped config of that name; shipped: "
                            f"{', '.join(shipped)})")


def load_config(path: str | Path) -> dict:
    """Reads a YAML config with its ``_BASE_CONFIG_`` files merged in; returns a plain dict.

    Args:
        path: a YAML file, or the name of a shipped config (:func:`packaged_configs`, e.g.
            ``"pointpillars_synth"``, or ``"configs/pointpillars/pointpillars_synth.yaml"`` from any directory).

    Raises:
        FileNotFoundError: no such file and no shipped config of that name.
        ConfigError: not YAML, not a mapping, or a base file that cannot be found.
    """
    return _load(resolve_config(path), ())


def _load(path: Path, chain: tuple) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    if path.resolve() in chain:  # a file that is its own base, directly or not, would never finish
        raise ConfigError(f"{path}: _BASE_CONFIG_ includes itself ({' -> '.join(str(p) for p in chain + (path,))})")
    yaml = _yaml()
    try:
        text = path.read_bytes().decode("utf-8-sig")  # a byte-order mark is not part of the first key
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a YAML text file (byte {e.start} is not UTF-8 text)") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(e).split())})") from None  # one line
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: a config must be a YAML mapping, got {type(data).__name__}")
    return merge_config({}, data, path.resolve(), chain + (path.resolve(),))


def apply_overrides(cfg: dict, pairs: "list[str] | tuple[str, ...]") -> dict:
    """OpenPCDet's ``--set KEY VALUE [KEY VALUE ...]`` (``cfg_from_list``): each dotted ``KEY`` (e.g.
    ``MODEL.RATIO``) must already be in ``cfg`` (a typo would otherwise change nothing); each ``VALUE`` is
    read as YAML (``4``, ``0.5``, ``5e-5``, ``[1, 2]``, ``null``, ``fast``). Returns ``cfg``, changed in place.

    Raises:
        ConfigError: an odd number of items, or a key that is not in the config (naming it and the keys
            beside it).
    """
    pairs = list(pairs)
    if len(pairs) % 2:
        raise ConfigError(f"--set takes KEY VALUE pairs, got {len(pairs)} item(s): {' '.join(pairs)}")
    yaml = _yaml()
    for key, text in zip(pairs[::2], pairs[1::2]):
        node, parts = cfg, key.split(".")
        for i, part in enumerate(parts):
            if not isinstance(node, dict) or part not in node:
                where = ".".join(parts[:i]) or "the config"
                known = sorted(node) if isinstance(node, dict) else []
                raise ConfigError(f"--set {key}: {where} has no key {part!r}"
                                  + (f" (it has {', '.join(map(str, known))})" if known else ""))
            if i < len(parts) - 1:
                node = node[part]
        try:  # YAML, except that 5e-5 is a number (YAML 1.1 reads it as a string; OpenPCDet's literal_eval not)
            value = yaml.safe_load(text)
            if isinstance(value, str):
                try:
                    value = float(value)
                except ValueError:
                    pass
            node[parts[-1]] = value
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {key} {text}: not a YAML value ({' '.join(str(e).split())})") from None
    return cfg
