"""OpenPCDet's own PointPillar as the peer of lidarops' PointPillars, timed in the same run.

    python benchmarks/openpcdet_peer.py --openpcdet .peers/openpcdet-src [--runs 50] [--out rows.json]

or from another benchmark::

    from benchmarks.openpcdet_peer import openpcdet_rows
    rows = openpcdet_rows(Path(".peers/openpcdet-src"), frame)     # frame: float32 (N, 4) on the CPU

The peer is OpenPCDet's code, unchanged: a checkout whose compiled ops ``tools/upstream/openpcdet/build_ops.py``
built, its ``PointPillar`` from its own ``tools/cfgs/kitti_models/pointpillar.yaml``, loaded with the lidarops
checkpoint (the shipped ``pointpillars_synth`` by default) with ``strict=True``, as
``tools/upstream/openpcdet/side_by_side.py`` loads it (whose helpers build it here). Its post-processing is
the same as the shipped model's (score threshold 0.1, NMS 0.01, 4096 / 500 boxes). On the GPU machine,
``tools/upstream/openpcdet/peer_setup.sh`` installs what OpenPCDet needs and builds its ops; README.md there
says what it needs. It runs on CUDA only: OpenPCDet's model code calls ``.cuda()``.

Rows (``"op": "pointpillars", "impl": "openpcdet"``, one per ``stage``), for one frame (batch size 1):

* ``forward``: ``model(batch_dict)`` in eval mode on a batch already on the GPU: the PFN, scatter, 2D
  backbone, anchor head and OpenPCDet's ``post_processing`` (decode, score threshold, NMS, whose host reads
  are part of it), returning its ``pred_dicts``. CUDA events, median and p90 of ``runs`` calls.
* ``prepare``: OpenPCDet's CPU data preparation of the frame, test mode: ``prepare_data`` (point feature
  encoder, range mask, spconv's ``Point2VoxelCPU3d``) and ``collate_batch``. ``time.perf_counter``.
* ``frame``: what OpenPCDet's ``tools/demo.py`` runs per frame, from points in host memory to
  ``pred_dicts``: ``prepare`` + ``load_data_to_gpu`` (its host-to-device copy) + ``forward``. CUDA events
  (the GPU idles while the host prepares, so they measure the wall time).

lidarops' eager row (``bm_detector.py``) starts from points in device memory and voxelizes on the GPU; the
``forward`` row leaves voxelization out, the ``frame`` row has it on the CPU with the copy: the two bracket it.
Every row names the peer (``peer_version``: OpenPCDet's commit, from ``COMMIT`` beside ``pcdet/`` or git,
and spconv's version), the number of boxes OpenPCDet returned and the pillars it made.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.common import Timing, env_meta, fmt_ms, print_table, time_cpu, time_cuda  # noqa: E402
from tools.upstream.openpcdet.build_ops import commit_of  # noqa: E402
from tools.upstream.openpcdet.side_by_side import (  # noqa: E402
    import_openpcdet, load_strict, read_config, scan_dataset)

__all__ = ["openpcdet_rows", "load_peer", "prepare_frame", "time_prepare", "peer_version", "OpenPCDetPeer"]

INCLUDES = {
    "forward": "model(batch_dict), eval: PFN, scatter, 2D backbone, anchor head, post_processing (decode, score "
               "threshold, NMS); batch already on the GPU",
    "prepare": "CPU: prepare_data (point feature encoder, range mask, spconv Point2VoxelCPU3d) + collate_batch",
    "frame": "prepare + load_data_to_gpu + forward: OpenPCDet's tools/demo.py per frame, host points to pred_dicts",
}


@dataclass
class OpenPCDetPeer:
    """OpenPCDet's side, built by its own code: its test-mode dataset (data preparation) and model."""

    src: Path
    dataset: Any  # pcdet DatasetTemplate over no scans: prepare_data is called on given points
    model: torch.nn.Module | None  # eval mode on CUDA; None when built without the model
    load_data_to_gpu: Any  # pcdet.models.load_data_to_gpu
    weights: Path | None
    version: str


def peer_version(src: Path) -> tuple[str, str | None]:
    """(OpenPCDet's commit, spconv's version): the commit from ``src/COMMIT`` (a ``git archive`` copy), else
    from ``src``'s own git; "unknown" when neither says."""
    commit = commit_of(src) or "unknown"
    try:
        import spconv

        spconv_version = getattr(spconv, "__version__", None)
    except ImportError:
        spconv_version = None
    return commit, spconv_version


def load_peer(src: Path, weights_path: Path | None = None, faces: bool = False, model: bool = True) -> OpenPCDetPeer:
    """OpenPCDet's dataset and PointPillar from the checkout ``src``, the checkpoint loaded strictly.

    Args:
        src: OpenPCDet source tree (``pcdet/``, ``tools/``) with its ops built, unless ``faces``.
        weights_path: lidarops checkpoint (default: the shipped ``pointpillars_synth``).
        faces: lidarops.compat.pcdet in place of OpenPCDet's compiled ops (the data side then runs on a
            CPU-only machine).
        model: build the model (needs CUDA: OpenPCDet's model code calls ``.cuda()``); False: the data side
            only.
    """
    src = Path(src).resolve()
    if not (src / "pcdet").is_dir():
        raise FileNotFoundError(f"{src}: no pcdet/ (an OpenPCDet source tree; tools/upstream/openpcdet/README.md)")
    _, cfg, cfg_from_yaml_file, DatasetTemplate, build_network, _ = import_openpcdet(src, faces)
    from pcdet.models import load_data_to_gpu

    read_config(src, cfg, cfg_from_yaml_file)
    dataset = scan_dataset(DatasetTemplate, cfg, [], logger=logging.getLogger("openpcdet_peer"))
    net = None
    if model:
        from lidarops.models import weights

        weights_path = Path(weights_path or weights.path()).resolve()
        net = build_network(model_cfg=cfg.MODEL, num_class=len(cfg.CLASS_NAMES), dataset=dataset)
        load_strict(net, weights_path)
        net.cuda().eval()
    commit, spconv_version = peer_version(src)
    return OpenPCDetPeer(src, dataset, net, load_data_to_gpu, weights_path if model else None,
                         f"OpenPCDet {commit[:7]}, spconv {spconv_version}")


def prepare_frame(peer: OpenPCDetPeer, points: np.ndarray) -> dict:
    """One frame through OpenPCDet's data preparation and collation: its batch dict of NumPy arrays."""
    item = peer.dataset.prepare_data(data_dict={"points": points, "frame_id": 0})
    return peer.dataset.collate_batch([item])


def _points(points: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (N, 4) x, y, z, intensity, got {tuple(points.shape)}")
    return np.ascontiguousarray(points, dtype=np.float32)


@contextlib.contextmanager
def _tf32(on: bool):
    """bm_detector's "tf32" / "fp32" (lidarops.models.cuda_graph.precision_mode), without importing lidarops'
    models: the peer needs no lidarops build."""
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = on
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def _stats(t: Timing, timer: str) -> dict:
    times = t.times_ms
    p90 = statistics.quantiles(times, n=10)[-1] if len(times) > 1 else times[0]
    return {**t.as_dict(), "p90_ms": round(p90, 6), "timer": timer}


def time_prepare(peer: OpenPCDetPeer, points: torch.Tensor | np.ndarray, runs: int = 50) -> dict:
    """``prepare``'s timing (median and p90 of ``runs`` warm calls, ``time.perf_counter``) and the pillars made."""
    pts = _points(points)
    batch = prepare_frame(peer, pts)
    t = time_cpu(prepare_frame, (peer, pts), min_runs=runs, max_runs=runs, slow_single_s=float("inf"))
    return {"stage": "prepare", "includes": INCLUDES["prepare"], "pillars": int(batch["voxels"].shape[0]),
            **_stats(t, "perf_counter")}


def openpcdet_rows(src: Path, points: torch.Tensor, weights_path: Path | None = None, runs: int = 50,
                   tf32: bool = True) -> list[dict]:
    """OpenPCDet's PointPillar on one frame: the ``forward``, ``prepare`` and ``frame`` rows (module docstring).

    Args:
        src: OpenPCDet source tree whose ops ``tools/upstream/openpcdet/build_ops.py`` built.
        points (Tensor[N, 4]): float32 x, y, z, intensity on the CPU.
        weights_path: lidarops checkpoint loaded into OpenPCDet's model (default: the shipped
            ``pointpillars_synth``).
        runs: timed calls per row, after the warm-up calls.
        tf32: TF32 matmuls and convolutions (``"precision": "tf32"``), else float32 (``"fp32"``).

    Returns:
        rows: dicts with ``op``, ``impl``, ``stage``, ``includes``, ``precision``, ``median_ms``, ``p90_ms``,
        ``iqr_ms``, ``runs``, ``timer``, ``points``, ``pillars``, ``boxes``, ``peer_version``, ``status``.

    Raises:
        RuntimeError: no CUDA device. FileNotFoundError: ``src`` is no OpenPCDet tree. ImportError: OpenPCDet's
        needs (spconv, easydict, ...) or its built ops are missing.
    """
    if not torch.cuda.is_available():
        raise RuntimeError("OpenPCDet's PointPillar runs on CUDA only (its model code calls .cuda())")
    precision = "tf32" if tf32 else "fp32"
    peer = load_peer(src, weights_path)
    pts = _points(points)
    on_gpu = prepare_frame(peer, pts)
    peer.load_data_to_gpu(on_gpu)

    def forward(batch: dict):
        return peer.model(dict(batch))  # a copy: the model adds its intermediate tensors to the dict

    def frame(p: np.ndarray):
        batch = prepare_frame(peer, p)
        peer.load_data_to_gpu(batch)
        return peer.model(batch)

    with torch.no_grad(), _tf32(tf32):
        preds, _ = forward(on_gpu)
        t_forward = time_cuda(forward, (on_gpu,), min_runs=runs, max_runs=runs, rotate=False,
                              slow_single_s=float("inf"))
        t_frame = time_cuda(frame, (pts,), min_runs=runs, max_runs=runs, rotate=False, slow_single_s=float("inf"))
    prepare = time_prepare(peer, pts, runs)
    common = {"op": "pointpillars", "impl": "openpcdet", "backbone": "dense", "precision": precision,
              "memory_format": "contiguous", "points": int(pts.shape[0]), "pillars": prepare["pillars"],
              "boxes": int(preds[0]["pred_boxes"].shape[0]), "peer_version": peer.version,
              "weights": peer.weights.name, "status": "ok", "device": "cuda"}
    return [{**common, "stage": "forward", "includes": INCLUDES["forward"], **_stats(t_forward, "cuda events")},
            {**common, **prepare},
            {**common, "stage": "frame", "includes": INCLUDES["frame"], **_stats(t_frame, "cuda events")}]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--openpcdet", type=Path, default=Path(ROOT) / ".peers/openpcdet-src",
                    help="OpenPCDet source tree with its ops built (default .peers/openpcdet-src)")
    ap.add_argument("--weights", type=Path, default=None, help="lidarops checkpoint (default: the shipped model)")
    ap.add_argument("--frame", type=Path, default=None,
                    help="a KITTI velodyne .bin scan (default: bm_detector.py's driving_city frame)")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--precision", nargs="+", choices=("tf32", "fp32"), default=["tf32", "fp32"])
    ap.add_argument("--out", type=Path, default=None, help="write the rows and the environment as JSON")
    args = ap.parse_args(argv)
    if args.frame is not None:
        points = torch.from_numpy(np.fromfile(args.frame, dtype=np.float32).reshape(-1, 4))
    else:
        from benchmarks.bm_detector import kitti_like_frame

        points = kitti_like_frame()
    rows = [r for p in args.precision
            for r in openpcdet_rows(args.openpcdet, points, args.weights, args.runs, tf32=p == "tf32")]
    print_table(f"OpenPCDet PointPillar ({rows[0]['peer_version']}), {rows[0]['points']} points, "
                f"{rows[0]['pillars']} pillars, on {env_meta('cuda')['device']}",
                ["precision", "stage", "median ms", "p90 ms", "boxes", "timer"],
                [[r["precision"], r["stage"], fmt_ms(r["median_ms"]), fmt_ms(r["p90_ms"]), r["boxes"], r["timer"]]
                 for r in rows], right=(2, 3, 4))
    if args.out:
        args.out.write_text(json.dumps({"meta": env_meta("cuda"), "rows": rows}, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
