"""``lidarops sample``: keeps 1/D of a LiDAR scan's points with one of the samplers of issue 37 (random, FPS,
chunked FPS, a trained CAS-Net) and writes the sampled scans in the input's format, with a before/after
bird's-eye picture of each.

The input is a KITTI velodyne ``.bin`` (float32 ``x, y, z, reflectance``) or a KITTI folder (``velodyne/``,
``training/velodyne/`` or ``object/training/velodyne/`` inside: every scan, in name order, the first
``--frames``). Each scan of ``N`` points keeps ``N // D`` of them (``D = --ratio``); a scan with fewer than
``D`` points keeps one, an empty scan stays empty. Every channel is kept: the output rows are rows of the
input. Output: ``OUT/<stem>_<method>_d<D>.bin`` (and ``.png``) for a file; ``OUT/velodyne/<id>.bin`` (and
``OUT/pictures/<id>_<method>_d<D>.png``) for a folder. One line per scan: points in -> out and the time of
the sampling call (the first scan's includes one-time start-up costs).

``--method casnet`` uses the shipped detection CAS-Net (``casnet_pointpillars_d8``, trained on the simulator's
driving scans) unless ``--checkpoint`` names another: a file of ``CASNet.save``, a checkpoint of ``lidarops
train`` holding a ``CASNetPointNet`` or ``CASNetPointPillars`` (its CAS-Net is used), a torch file
``{"model_config": {CASNet's keyword arguments}, "state_dict": ...}``, or a shipped name. A CAS-Net with the
anchored head samples each scan whole; one with the paper's head cuts it into segments of at most 8,192 points.

Examples::

    lidarops sample data/synth/training/velodyne/000000.bin --method fps --ratio 8 --out sampled/
    lidarops sample data/synth --method chunked-fps --ratio 4 --frames 10 --out synth_d4/
    lidarops sample data/synth --method casnet --checkpoint runs/casnet/final.pth --ratio 8 --out synth_cas/
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from lidarops.cli.errors import guarded

__all__ = ["register", "sample", "METHODS", "sample_count", "save_before_after"]

#: ``--method`` values, in the order of the help
METHODS = ("random", "fps", "chunked-fps", "casnet")
#: the CAS-Net ``--method casnet`` reads without ``--checkpoint``
SHIPPED_CASNET = "casnet_pointpillars_d8"


def sample_count(n: int, ratio: int) -> int:
    """Points kept of a scan of ``n``: ``n // ratio``; ``ceil(n / ratio)`` (one point) when ``0 < n < ratio``;
    0 for an empty scan."""
    return n // ratio if n >= ratio else math.ceil(n / ratio)


def _positive(text: str, flag: str) -> int:
    """``text`` as an int >= 1, or a ValueError naming ``flag`` (one line, unlike argparse's usage + error)."""
    try:
        value = int(text, 10)
    except (TypeError, ValueError):
        raise ValueError(f"{flag} must be an int >= 1, got {text!r}") from None
    if value < 1:
        raise ValueError(f"{flag} must be an int >= 1, got {value}")
    return value


def _scans(path: Path, frames: "int | None") -> "tuple[list[Path], Path | None]":
    """(the scans to sample, the KITTI split folder holding ``velodyne/``, or None for a single file)."""
    if not path.exists():
        raise FileNotFoundError(f"path {path} not found: give a KITTI velodyne .bin or a KITTI folder")
    if path.is_file():
        if path.suffix != ".bin":
            raise ValueError(f"path {path}: not a KITTI velodyne .bin (float32 x, y, z, reflectance) nor a KITTI "
                             "folder")
        return [path], None
    for split in (path, path / "training", path / "object" / "training"):
        if (split / "velodyne").is_dir():
            scans = sorted((split / "velodyne").glob("*.bin"))
            if not scans:
                raise ValueError(f"path {path}: {split / 'velodyne'} holds no .bin scans")
            return scans[:frames] if frames is not None else scans, split
    raise ValueError(f"path {path} is not a KITTI folder: no velodyne/ or training/velodyne/ inside")


def _load_casnet(path: Path, device):
    """The CAS-Net of ``--checkpoint`` (a file or a shipped name), in eval mode on ``device``."""
    from lidarops.checkpoint import CheckpointError
    from lidarops.models.casnet import load_casnet

    try:
        return load_casnet(str(path), device)
    except (CheckpointError, FileNotFoundError) as e:
        raise CheckpointError(f"--checkpoint {e}") from None


def _sampler(method: str, seed: int, checkpoint: "str | None", device):
    from lidarops.models.samplers import ChunkedFPSSampler, FPSSampler, RandomSampler

    if method == "random":
        return RandomSampler(seed)
    if method == "fps":
        return FPSSampler()
    if method == "chunked-fps":
        return ChunkedFPSSampler()
    from lidarops.models.casnet import CASNetSampler

    model = _load_casnet(Path(checkpoint), device)
    # the anchored head takes any number of rows: the whole cloud at once (better than segments, docs/casnet.md);
    # the paper's head: segments, the ratio per cloud the sampler's (n // m, lowered until the picks are distinct)
    return CASNetSampler(model, whole=model.head_kind == "anchored")


def _timed_sample(sampler, points, m: int, device, fp16: bool = False) -> "tuple[object, float]":
    """(the kept rows' indices, int64 numpy, ascending in selection order; milliseconds of the call); ``fp16``:
    under float16 autocast."""
    import contextlib

    import torch

    x = torch.from_numpy(points).to(device).unsqueeze(0)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    with torch.no_grad(), (torch.autocast("cuda", dtype=torch.float16) if fp16 else contextlib.nullcontext()):
        idx = sampler(x, m)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    ms = (time.perf_counter() - t0) * 1000.0
    idx = idx[0].cpu().numpy()
    return idx[idx >= 0], ms


def save_before_after(points, kept, path: Path, title: str, method: str, ratio: int) -> Path:
    """Writes a PNG of two bird's-eye views side by side: the scan and what the sampler kept, over the same area.

    Args:
        points (ndarray[N, 4]): the scan.
        kept (ndarray[M, 4]): the sampled scan.
        path (Path): output ``.png``.
        title (str): the figure's title (the scan's name).
        method (str), ratio (int): named in the right panel's title.
    """
    from lidarops.data.viz import new_figure, plot_bev

    fig = new_figure(16, 8)
    left = fig.add_subplot(1, 2, 1)
    shade = plot_bev(left, points, legend=False)
    extent = (*left.get_xlim(), *left.get_ylim())
    left.set_title(f"input: {points.shape[0]:,} points", fontsize=9)
    right = fig.add_subplot(1, 2, 2)
    kept_shade = plot_bev(right, kept, extent=extent, legend=False, point_size=min(0.3 * math.sqrt(ratio), 3.0))
    kept_shade.set_clim(*shade.get_clim())  # one colour scale for both panels (plot_bev fits it to its points)
    right.set_title(f"{method}, 1/{ratio}: {kept.shape[0]:,} points", fontsize=9)
    fig.set_layout_engine("constrained")
    fig.colorbar(shade, ax=[left, right], fraction=0.02, pad=0.01, label=shade.key_label)
    (x0, x1), (y0, y1) = extent[:2], extent[2:]
    fig.set_size_inches(16.0, min(max(7.0 * (y1 - y0) / max(x1 - x0, 1e-9) + 1.0, 3.5), 10.0))
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def sample(args: argparse.Namespace) -> int:
    """Samples the scans and writes them (and their pictures)."""
    from lidarops.cli._device import resolve_device
    from lidarops.data.formats.kitti import read_velodyne, write_velodyne

    if args.method not in METHODS:
        raise ValueError(f"--method must be one of {', '.join(METHODS)}, got {args.method!r}")
    ratio = _positive(args.ratio, "--ratio")
    frames = None if args.frames is None else _positive(args.frames, "--frames")
    if args.checkpoint and args.method != "casnet":
        raise ValueError(f"--checkpoint is a CAS-Net's, for --method casnet only (got --method {args.method})")
    checkpoint = args.checkpoint
    if args.method == "casnet":
        from lidarops.models import weights

        checkpoint = checkpoint or SHIPPED_CASNET
        if not Path(checkpoint).is_file() and checkpoint not in weights.available():
            raise FileNotFoundError(f"--checkpoint {checkpoint} not found" +
                                    (" (a directory)" if Path(checkpoint).is_dir() else "") +
                                    f": give a CAS-Net file or a shipped name ({', '.join(weights.available())})")
    path = Path(args.path)
    scans, split = _scans(path, frames)
    tag = f"{args.method}_d{ratio}"
    out = Path(args.out) if args.out is not None else (Path(".") if split is None else Path(f"{path.name}_{tag}"))
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is an existing file; give a directory")
    if split is not None and out.resolve() == split.resolve():
        raise ValueError(f"--out {out} is the input folder: its velodyne/ scans would be overwritten")
    device = resolve_device(args.device)
    if args.fp16 and (args.method != "casnet" or device.type != "cuda"):
        raise ValueError(f"--fp16 is for --method casnet on CUDA (got --method {args.method} on {device})")
    sampler = _sampler(args.method, args.seed, checkpoint, device)
    if not args.no_picture:
        from lidarops.data.viz import new_figure

        new_figure()  # matplotlib missing: one error before anything is written
    points = read_velodyne(scans[0])  # a bad first scan: one error before anything is written
    written = []
    for k, scan in enumerate(scans):
        if k:
            points = read_velodyne(scan)
        n = points.shape[0]
        m = sample_count(n, ratio)
        idx, ms = _timed_sample(sampler, points, m, device, args.fp16) if m else ([], 0.0)
        kept = points[idx]
        if split is None:
            target, picture = out / f"{scan.stem}_{tag}.bin", out / f"{scan.stem}_{tag}.png"
        else:
            target, picture = out / "velodyne" / scan.name, out / "pictures" / f"{scan.stem}_{tag}.png"
        write_velodyne(target, kept)
        written.append(target)
        note = "" if n >= ratio else (" (empty scan)" if n == 0 else f" (fewer points than --ratio {ratio}: one kept)")
        line = f"{scan.stem}: {n:,} -> {kept.shape[0]:,} points ({args.method}, 1/{ratio}) in {ms:.1f} ms{note}: {target}"
        if not args.no_picture:
            save_before_after(points, kept, picture, f"{scan}", args.method, ratio)
            line += f", {picture}"
        print(line, flush=True)
    if split is not None:
        print(f"wrote {len(written)} sampled scan{'' if len(written) == 1 else 's'} to {out / 'velodyne'}")
    return 0


def register(subparsers) -> None:
    """Adds ``sample`` to the ``lidarops`` parser."""
    p = subparsers.add_parser(
        "sample", help="keep 1/D of a scan's points (random, FPS, chunked FPS, CAS-Net); files and pictures",
        description="Sample a KITTI velodyne .bin or every scan of a KITTI folder: N // D points per scan (one "
                    "when N < D), every channel kept, written in the input's format with a before/after "
                    "bird's-eye picture per scan.")
    p.add_argument("path", help="a KITTI velodyne .bin or a KITTI folder (velodyne/ or training/velodyne/ inside)")
    p.add_argument("--method", default="random", metavar="METHOD",
                   help=f"one of {', '.join(METHODS)} (default random)")
    p.add_argument("--ratio", default="8", metavar="D", help="keep N // D points of a scan of N (default 8)")
    p.add_argument("--checkpoint", default=None,
                   help=f"--method casnet: a CAS-Net file or a shipped name (default {SHIPPED_CASNET})")
    p.add_argument("--seed", type=int, default=0, help="--method random: the generator's seed (default 0)")
    p.add_argument("--out", default=None,
                   help="output folder (default: . for a file, ./<folder>_<method>_d<D> for a folder)")
    p.add_argument("--frames", default=None, metavar="N", help="a folder: the first N scans (default all)")
    p.add_argument("--device", default="auto", help="auto (default: cuda when available), cpu or cuda")
    p.add_argument("--no-picture", action="store_true", help="no before/after PNG")
    p.add_argument("--fp16", action="store_true",
                   help="--method casnet on CUDA: float16 autocast, about twice as fast (docs/casnet.md); a few "
                        "near-tied picks may differ from float32's")
    p.set_defaults(func=guarded("sample", sample))
