"""What the dense BEV network of the shipped PointPillars costs on the GPU, and what bounds it: the backbone and
the anchor head of :func:`~lidarops.models.cuda_graph.inference_copy` replayed as a CUDA graph, in variants, and
each of its kernels with the multiply-adds it does and the rate it reaches.

    python benchmarks/profile/bev_convs.py [--batches 1,16] [--runs 50]

Variants (all under float16 autocast, channels-last, BatchNorm folded):

* ``unfused``: the copy with each convolution and its ReLU as two modules (cuDNN's convolution, PyTorch's bias
  addition, the ReLU);
* ``copy``: the inference copy as it is, with float32 weights that autocast casts at each call;
* ``copy, weights cast once``: its convolutions' weights in float16, as the graphs recorded under fp16 hold them
  (what ``predict`` and ``GraphedPointPillars(optimize=True, precision="fp16")`` replay).

Each with cuDNN's heuristics and with ``torch.backends.cudnn.benchmark`` (cuDNN times its algorithms per shape).
The input is a pseudo-image of the KITTI grid (64 x 496 x 432) with 8 % of its cells filled.
"""
from __future__ import annotations

import argparse
import copy
import os
import sys

import torch
from torch import nn

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_detector import load_model  # noqa: E402
from benchmarks.profile.conv_algos import graph_ms  # noqa: E402
from benchmarks.profile_eager import kernel_totals  # noqa: E402
from lidarops.models.cuda_graph import _cast_convolutions, _ConvReLU, inference_copy  # noqa: E402


def unfused(net: nn.Module) -> nn.Module:
    """The copy with each fused convolution + ReLU back as the two modules (three passes over the map: the
    convolution, PyTorch's bias addition, the ReLU)."""
    for seq in [m for m in net.modules() if isinstance(m, nn.Sequential)]:
        for i, m in enumerate(seq):
            if isinstance(m, _ConvReLU):
                seq[i] = nn.Sequential(m.conv, nn.ReLU())
    return net


def pseudo_image(B: int, fill: float = 0.08) -> torch.Tensor:
    g = torch.Generator(device="cuda").manual_seed(0)
    x = torch.rand(B, 64, 496, 432, device="cuda", generator=g)
    keep = torch.rand(B, 1, 496, 432, device="cuda", generator=g) < fill
    return (x * keep).half().contiguous(memory_format=torch.channels_last)


def conv_macs(m: nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    if isinstance(m, nn.ConvTranspose2d):  # each input cell times the whole kernel
        return x.numel() / x.shape[1] * m.in_channels * m.out_channels * m.kernel_size[0] * m.kernel_size[1]
    w = m.weight
    return y.numel() / y.shape[1] * w.shape[0] * w.shape[1] * w.shape[2] * w.shape[3]


def kernel_table(net, x) -> None:
    """Each convolution's kernels in execution order: GPU time, multiply-adds, rate."""
    convs = [(n, m) for n, m in net.named_modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))]
    macs = {}

    def hook(m, inp, out):
        macs[m] = conv_macs(m, inp[0], out)

    hooks = [m.register_forward_hook(hook) for _, m in convs]
    run = lambda: net(x)  # noqa: E731
    with torch.no_grad(), torch.autocast("cuda", torch.float16):
        run()
        torch.cuda.synchronize()
        acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=acts) as prof:
            for _ in range(10):
                run()
            torch.cuda.synchronize()
    for h in hooks:
        h.remove()
    kernels = kernel_totals(prof.events(), 10)
    total = sum(us for _, us, _ in kernels)
    all_macs = sum(macs.values())
    print(f"  GPU kernel time {total:.1f} us per call; {all_macs / 1e9:.2f} G multiply-adds in the convolutions "
          f"({2 * all_macs / total / 1e6:.0f} TFLOP/s over the whole call)")
    for name, us, n in kernels[:25]:
        print(f"  {us:8.1f} us x{n:3.0f}  {name[:120]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", default="1,16")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--no-kernels", action="store_true", help="skip the per-kernel tables")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("bev_convs.py profiles CUDA graphs; no CUDA device here")
        return 1
    model = load_model("cuda", "dense")
    base = inference_copy(model)
    net_of = lambda m: nn.Sequential(m.backbone_2d, m.dense_head)  # noqa: E731
    cast = copy.deepcopy(base)
    _cast_convolutions(cast, torch.float16)
    variants = [("unfused", net_of(unfused(copy.deepcopy(base)))), ("copy", net_of(base)),
                ("copy, weights cast once", net_of(cast))]
    with torch.no_grad():
        for B in [int(b) for b in args.batches.split(",")]:
            x = pseudo_image(B)
            for bench in (False, True):
                torch.backends.cudnn.benchmark = bench
                for name, net in variants:
                    def fn(x, net=net):
                        with torch.autocast("cuda", torch.float16):
                            return net(x)
                    try:
                        ms = graph_ms(lambda: fn(x), reps=1, replays=args.runs)
                        print(f"batch {B:2d}  cudnn.benchmark={bench!s:5}  {name:24s} {ms:7.3f} ms per call, "
                              f"{ms / B:6.3f} ms per frame", flush=True)
                    except Exception as e:  # a variant cuDNN refuses: say so, go on
                        print(f"batch {B:2d}  cudnn.benchmark={bench!s:5}  {name:24s} failed: "
                              f"{type(e).__name__}: {str(e)[:200]}", flush=True)
            # the variants agree (float16 rounding)
            with torch.autocast("cuda", torch.float16):
                want = variants[0][1](x)
                for name, net in variants[1:]:
                    got = net(x)
                    err = max(float((got[k].float() - want[k].float()).abs().max()) for k in want)
                    print(f"batch {B:2d}  {name:24s} max |diff| against the unfused copy: {err:.3g}")
            if not args.no_kernels:
                torch.backends.cudnn.benchmark = False
                for name, net in variants:
                    print(f"\nbatch {B}, {name}: kernels")
                    kernel_table(net, x)
    return 0


if __name__ == "__main__":
    sys.exit(main())
