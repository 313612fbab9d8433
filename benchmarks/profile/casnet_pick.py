"""Where the time of a CAS-Net sampling call goes: the shipped ``casnet_pointpillars_d8`` picking one point in 8 of a
20,000-point field-of-view cloud (``CASNet.pick``, the anchored head, distinct picks), stage by stage.

    python benchmarks/profile/casnet_pick.py --device cuda            # float32 and float16 autocast
    python benchmarks/profile/casnet_pick.py --device cpu --points 4000

The stages are the pick's own calls, run one after the other with a synchronisation between them (so each
stage's time includes its launches and host reads): input checks, the points in the model's dtype, farthest
point sampling of the anchors, the anchors' candidates (kNN), the neighbour embedding, the offset attention, the
head's logits on the candidates, the distinct picks (ranked and assigned on the device) and the sampler's filling
of the rows left without a free candidate. The embedding, attention and head run as the pick runs them at inference
(rows, BatchNorm folded into the convolutions). On CUDA the pick
itself runs the anchors and candidates on a second stream beside the embedding and the attention, so the whole
call takes less than the sum: it is timed alone, also with that second stream off ("one stream"), and as users
call it (``CASNetSampler(model, whole=True)``). Medians of ``--runs`` after two warm-up calls.
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
    from lidarops.models.casnet import _fill_repeats, _greedy_candidates
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

    head, N = model.head, points.shape[1]
    with torch.no_grad():
        sync()
        t = time.perf_counter()
        lengths = model._check_input(points, None)
        lap("input checks")
        xyz, mask = model._xyz(points, lengths, full=True)
        lap("points in the model's dtype")
        with validation(False):
            anchors = fps(xyz, m, lengths)
            lap("anchors: farthest point sampling")
            d2, cand = knn(gather(xyz, anchors), xyz, head.candidates, None, lengths)
            lap("candidates: kNN of the anchors")
        x = model.embedding.rows(xyz, lengths)  # the pick's inference path: rows, BatchNorm folded
        lap("embedding")
        feats = []
        for layer in model.attention:
            x = layer.rows(x)
            feats.append(x)
        h = torch.cat(feats + [xyz.to(x.dtype)], dim=-1)
        lap("offset attention")
        logits, cand = head.logits(head.project_rows(h), (anchors, cand, d2), padded=False)
        logits = logits / model.temperature
        best = logits.amax(dim=-1, keepdim=True)
        plain = torch.where(logits == best, cand, N).amin(dim=-1)
        lap("head: logits on the candidates")
        picks = _greedy_candidates(torch.log_softmax(logits, dim=-1), cand, plain, N, padded=False)
        lap("distinct picks (ranked and assigned on the device)")
        _fill_repeats(points[0, :, :3], picks[0])
        lap("the sampler's repeats filled (lidarops::fill_repeats)")
    return times


def _one_stream(call, *args, **kwargs):
    """``call`` with CAS-Net's second CUDA stream off: every stage on the current stream, one after another."""
    from lidarops.models import casnet

    side = casnet._side_stream
    casnet._side_stream = lambda device: None
    try:
        return call(*args, **kwargs)
    finally:
        casnet._side_stream = side


def main(argv=None) -> int:
    from benchmarks.bm_casnet import FovClouds
    from lidarops.models.casnet import CASNetSampler, load_casnet

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
    cloud, info = FovClouds().cloud(a.points)
    points = cloud.to(dev).unsqueeze(0)
    m = a.points // a.ratio
    from benchmarks.common import _git_commit

    report = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu", "commit": _git_commit(),
              "points": a.points,
              "m": m, "checkpoint": a.checkpoint, "cloud": info, "torch": torch.__version__, "precisions": {}}
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    precisions = ["float32"] + (["float16 autocast"] if dev.type == "cuda" else [])
    for precision in precisions:
        ctx = (lambda: torch.autocast("cuda", dtype=torch.float16)) if precision != "float32" \
            else contextlib.nullcontext
        sampler = CASNetSampler(model, whole=True)
        calls = {"pick_ms": lambda: model.pick(points, num_out=m, dedup=True),
                 "pick_one_stream_ms": lambda: _one_stream(model.pick, points, num_out=m, dedup=True),
                 "sampler_ms": lambda: sampler(points, m)}
        if dev.type != "cuda":
            del calls["pick_one_stream_ms"]
        runs, whole = [], {k: [] for k in calls}
        for i in range(a.runs + 2):
            with ctx():
                runs.append(_stages(model, points, m))
                for k, call in calls.items():
                    sync()
                    t = time.perf_counter()
                    call()
                    sync()
                    whole[k].append(time.perf_counter() - t)
        runs = runs[2:]
        medians = {k: 1e3 * statistics.median(r[k] for r in runs) for k in runs[0]}
        report["precisions"][precision] = {"stages_ms": medians, "sum_ms": sum(medians.values()),
                                           **{k: 1e3 * statistics.median(v[2:]) for k, v in whole.items()}}
        print(f"== {precision}: CASNet.pick, {a.points:,} points -> {m:,} ({report['device']})")
        for k, v in medians.items():
            print(f"  {k:<58} {v:7.2f} ms")
        print(f"  {'sum of the stages':<58} {sum(medians.values()):7.2f} ms")
        names = {"pick_ms": "the whole pick, timed alone", "pick_one_stream_ms": "the whole pick, one stream",
                 "sampler_ms": "CASNetSampler(model, whole=True)(points, m)"}
        for k in calls:
            print(f"  {names[k]:<58} {report['precisions'][precision][k]:7.2f} ms")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
