"""How much faster than a full recomputation can SSCATeR be on a stream? The bound set by the work.

    python benchmarks/profile/sscater_work_bound.py       # drone_bridge, 30 steps, CPU
    python benchmarks/profile/sscater_work_bound.py --steps 60 --relu-zeros 0.5 --scenario driving_city
    python benchmarks/profile/sscater_work_bound.py --checkpoint shipped --scenario driving_city   # a trained detector

Runs the recycling backbone of ``benchmarks/bm_sscater.py`` (same seeded weights, BatchNorm calibrated
to the same share of ReLU zeros; or, with ``--checkpoint``, a trained PointPillars streamed by
``SSCATeRPointPillars.from_detector``: its own weights, every site of the dense map active) and counts, per
convolution and step, the multiply-adds:

* full: what the sparse layer does, one per (active output, active input under its kernel, Cin, Cout);
* SSCATeR: what the delta scatter does, one per (changed input, active output it reaches, Cin, Cout),
  plus the full sums of the outputs that just became active;
* SSCATeR with zero channels skipped: the same, counting only the nonzero channels of each changed
  input's delta (a channel that stays <= 0 before and after ReLU has a zero delta).

The ratio full / SSCATeR is the most any implementation of the update can gain over the full layer
at equal speed per multiply-add. Counts are exact (from the site maps), not timed.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402


def _reach_counts(layer, in_active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per input site: the active outputs its kernel reaches; per output site: the active inputs under
    its kernel (float maps of the input's and the output's shape)."""
    ones = torch.ones(1, 1, layer.kh, layer.kw)
    out_active, x = layer.active.float()[None, None], in_active.float()[None, None]
    s, p = layer.stride, layer.padding
    if layer.transposed:  # kernel == stride: each child has one parent
        per_in = F.conv2d(out_active, ones, stride=s)[0, 0]
        per_out = F.conv_transpose2d(x, ones, stride=s)[0, 0]
    else:
        per_out = F.conv2d(x, ones, stride=s, padding=p)[0, 0]
        op = [n_in - ((n_out - 1) * s - 2 * p + k)
              for n_in, n_out, k in zip(in_active.shape, layer.active.shape, (layer.kh, layer.kw))]
        per_in = F.conv_transpose2d(out_active, ones, stride=s, padding=p, output_padding=tuple(op))[0, 0]
    return per_in * in_active.float(), per_out * layer.active.float()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="drone_bridge")
    ap.add_argument("--realism", default=None,
                    help="with --checkpoint: the scene's realism profile (default: the one the checkpoint's first "
                         "frames of that scene were made with; none: ray-cast); without it, ray-cast")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--relu-zeros", type=float, default=0.5)
    ap.add_argument("--checkpoint", default=None, help="a trained PointPillars: 'shipped', a shipped name or a file "
                                                       "(its own activations; --relu-zeros is then unused)")
    a = ap.parse_args(argv)
    from benchmarks.bm_sscater import _model
    from lidarops.models.sscater_calibration import calibrate_on_window
    from lidarops.data.synthetic import Simulator
    from lidarops.sscater.delta import DeltaBackbone

    dev = torch.device("cpu")
    realism = None
    if a.checkpoint:
        from benchmarks.bm_sscater import stream_realism

        realism = stream_realism(a.checkpoint, a.scenario, a.realism)
    elif a.realism not in (None, "none"):
        ap.error("--realism needs --checkpoint (the random-weights mode streams ray-cast scenes)")
    if a.checkpoint:
        from lidarops.models import load_model, weights
        from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

        path = weights.path() if a.checkpoint == "shipped" else \
            (weights.path(a.checkpoint) if a.checkpoint in weights.available() else Path(a.checkpoint))
        model = SSCATeRPointPillars.from_detector(load_model(path).float().eval(), device=dev)
    else:
        model, _ = _model(a.scenario, dev, a.relu_zeros)
    delta = model.delta
    assert not delta.sync_free  # trimmed lists on CPU: every row of a change is a real site
    work: dict = {}
    recording = [False]
    original = DeltaBackbone._layer_step

    def counting_step(self, layer, change):
        if not recording[0]:
            return original(self, layer, change)
        in_active = self.in_active  # the input node's active map (after its own update this step)
        for other in self.layers:
            if other.feats is layer.input:
                in_active = other.active
        out_was = layer.active.clone()
        result = original(self, layer, change)
        per_in, per_out = _reach_counts(layer, in_active)
        cc = layer.cin * layer.cout
        s = change.sites.long()
        reach = per_in[s[:, 0], s[:, 1]]
        nonzero = (change.delta != 0).sum(1).to(reach.dtype)
        newly = (layer.active & ~out_was).float()
        gather = float((per_out * newly).sum()) * cc if layer.kind != "up" else 0.0  # a child's parent is its delta
        w = work.setdefault(layer.name, [0.0, 0.0, 0.0, 0, 0])
        w[0] += float(per_out.sum()) * cc                        # the full layer
        w[1] += float(reach.sum()) * cc + gather                 # the delta scatter (+ the new sites' sums)
        w[2] += float((reach * nonzero).sum()) * layer.cout + gather  # zero delta channels skipped
        w[3] += int(layer.active.sum())
        w[4] += s.shape[0]
        return result

    DeltaBackbone._layer_step = counting_step
    slices = list(Simulator(a.scenario, seed=0, realism=realism).slices(0.0, 0.01 * (20 + a.steps), 0.01))
    for i, (p, t) in enumerate(slices[:10]):
        model.step(torch.from_numpy(p), torch.from_numpy(t), now=0.01 * (i + 1))
    if not a.checkpoint:
        calibrate_on_window(model, a.relu_zeros)
    for i, (p, t) in enumerate(slices):
        recording[0] = i >= 20 and not (model._since_refresh is not None and model.refresh_every
                                        and model._since_refresh + 1 >= model.refresh_every)
        model.step(torch.from_numpy(p), torch.from_numpy(t), now=0.01 * (i + 1))
    DeltaBackbone._layer_step = original
    n = a.steps
    what = f"the trained {a.checkpoint}" if a.checkpoint else f"ReLU zeros {a.relu_zeros:.0%}"
    scene = f"{a.scenario} ({realism} profile)" if realism else a.scenario
    print(f"{scene}, {n} steps, {what}: multiply-adds per step (millions)")
    print(f"{'layer':16s} {'active':>7s} {'changed in':>10s} {'full':>8s} {'SSCATeR':>8s} {'skip 0 ch':>9s}")
    tot = [0.0, 0.0, 0.0]
    for name, (full, ss, sk, act, ch) in work.items():
        print(f"{name:16s} {act / n:7.0f} {ch / n:10.0f} {full / n / 1e6:8.1f} {ss / n / 1e6:8.1f} {sk / n / 1e6:9.1f}")
        tot = [tot[0] + full, tot[1] + ss, tot[2] + sk]
    print(f"{'total':16s} {'':7s} {'':10s} {tot[0] / n / 1e6:8.1f} {tot[1] / n / 1e6:8.1f} {tot[2] / n / 1e6:9.1f}")
    print(f"work share of SSCATeR: {tot[1] / tot[0]:.3f} (bound on its speed-up: {tot[0] / tot[1]:.2f}x); "
          f"with zero delta channels skipped: {tot[2] / tot[0]:.3f} ({tot[0] / tot[2]:.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
