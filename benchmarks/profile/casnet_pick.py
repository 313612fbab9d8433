"""Where the time of a CAS-Net sampling call goes: the shipped ``casnet_pointpillars_d8`` picking one point in 8 of a
20,000-point field-of-view cloud (``CASNet.pick``, the anchored head, distinct picks), stage by stage.

    python benchmarks/profile/casnet_pick.py --device cuda            # float32 and float16 autocast
    python benchmarks/profile/casnet_pick.py --device cpu --points 4000

The stages are the pick's own calls, run one after the other with a synchronisation between them (so each
stage's time includes its launches and host reads): input checks, the neighbour embedding, the offset attention,
farthest point sampling of the anchors, the anchors' candidates (kNN), the head's logits on them, and the
distinct picks (a ranking on the device, the greedy scan on the host). The sum is checked against the whole
call timed alone. Medians of ``--runs`` after two warm-up calls.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402


def _stages(model, points: torch.Tensor, m: int) -> dict:
    """One pick, stage by stage: {stage: seconds}."""
    from lidarops.models.casnet import _greedy_candidates
    from lidarops.ops.neighbors import fps, gather, knn
    from lidarops.ops.validation import validation

    dev = points.device
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    times, t = {}, time.perf_counter()

    def lap(name):
        nonlocal t
        sync()
        now = time.perf_counter()
        times[name] = now - t
        t = now

    head = model.head
    with torch.no_grad():
        sync()
        t = time.perf_counter()
        lengths = model._check_input(points, None)
        lap("input checks")
        xyz = points[..., :3].float()
        x = model.embedding(xyz, lengths)
        lap("embedding (neighbours, MLP, max)")
        feats = []
        for layer in model.attention:
            x = layer(x)
            feats.append(x)
        h = torch.cat(feats + [xyz.transpose(1, 2)], dim=1)
        lap("offset attention")
        with validation(False):
            anchors = fps(xyz, m, lengths)
        lap("anchors: farthest point sampling")
        with validation(False):
            _, cand = knn(gather(xyz, anchors), xyz, head.candidates, None, lengths)
        lap("candidates: kNN of the anchors")
        logits, cand = head.sparse(h, xyz, lengths, m)  # repeats fps and kNN: subtracted below
        logits = logits / model.temperature
        best = logits.amax(dim=-1, keepdim=True)
        plain = torch.where(logits == best, cand, points.shape[1]).amin(dim=-1)
        lap("head: logits on the candidates (with its own fps and kNN)")
        _greedy_candidates(torch.log_softmax(logits, dim=-1), cand, plain, points.shape[1])
        lap("distinct picks (rank on device, greedy on host)")
    times["head: logits on the candidates (with its own fps and kNN)"] -= (
        times["anchors: farthest point sampling"] + times["candidates: kNN of the anchors"])
    return times


def main(argv=None) -> int:
    from benchmarks.bm_casnet import FovClouds
    from lidarops.models.casnet import load_casnet

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--ratio", type=int, default=8)
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--checkpoint", default="casnet_pointpillars_d8")
    p.add_argument("--json", default=None, help="write the medians here")
    a = p.parse_args(argv)
    dev = torch.device(a.device)
    model = load_casnet(a.checkpoint, dev)
    for layer in model.attention:  # the fused kernels, as bm_casnet's fastest rows
        layer.chunk = "fused"
    cloud, info = FovClouds().cloud(a.points)
    points = cloud.to(dev).unsqueeze(0)
    m = a.points // a.ratio
    report = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu", "points": a.points,
              "m": m, "checkpoint": a.checkpoint, "cloud": info, "torch": torch.__version__, "precisions": {}}
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    precisions = ["float32"] + (["float16 autocast"] if dev.type == "cuda" else [])
    for precision in precisions:
        ctx = (lambda: torch.autocast("cuda", dtype=torch.float16)) if precision != "float32" \
            else contextlib.nullcontext
        runs, whole = [], []
        for i in range(a.runs + 2):
            with ctx():
                runs.append(_stages(model, points, m))
                sync()
                t = time.perf_counter()
                model.pick(points, num_out=m, dedup=True)
                sync()
                whole.append(time.perf_counter() - t)
        runs, whole = runs[2:], whole[2:]
        medians = {k: 1e3 * statistics.median(r[k] for r in runs) for k in runs[0]}
        report["precisions"][precision] = {"stages_ms": medians, "sum_ms": sum(medians.values()),
                                           "pick_ms": 1e3 * statistics.median(whole)}
        print(f"== {precision}: CASNet.pick, {a.points:,} points -> {m:,} ({report['device']})")
        for k, v in medians.items():
            print(f"  {k:<58} {v:7.2f} ms")
        print(f"  {'sum of the stages':<58} {sum(medians.values()):7.2f} ms")
        print(f"  {'the whole pick, timed alone':<58} {1e3 * statistics.median(whole):7.2f} ms")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
