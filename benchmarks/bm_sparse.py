"""Benchmark of sparse convolution (lidarops.sparse) against dense cuDNN and spconv 2.x.

    python benchmarks/bm_sparse.py                      # CUDA when available, and CPU
    python benchmarks/bm_sparse.py --device cuda --json # write benchmarks/results/<device>.json
    python benchmarks/bm_sparse.py --quick              # smoke test (small sizes, < 1 min on 2 CPU cores)
    python benchmarks/bm_sparse.py --only layer,map     # sections: layer, map, eager, pillars, voxel
    python benchmarks/bm_sparse.py --device cuda --vs-spconv   # spconv required: its columns in the same run

Sections (times are medians in ms; the JSON has IQRs and run counts):

* ``layer``: one layer, Cin = Cout = C in {16, 32, 64, 128}, kernel 3x3, submanifold (``subm``) and
  strided (``conv``, stride 2, padding 1), on BEV grids: ``drone`` 504 x 504 with ~2k active sites,
  ``kitti`` 496 x 432 with ~15k, ``dense`` 504 x 504 with ~30k (range-weighted random sites: denser
  near the sensor, as LiDAR pillars). Like is compared with like: lidarops' registered op
  ``sparse_conv`` alone (kernel map cached) against dense cuDNN's ``F.conv2d`` on the dense
  (1, C, H, W) map; lidarops' layer module (``lidarops.compat.spconv``, called on a tensor whose
  ``indice_dict`` already holds the map, as every layer after the first with the same ``indice_key``)
  against spconv's layer module called the same way. A peer that fails has "error: ..." in its cell
  and row.
* ``map``: kernel-map construction alone (output sites + map, with validation), per grid and kind.
* ``eager``: what users see, each call from a new ``SparseConvTensor`` on a new copy of the indices (a new
  frame: kernel maps built and its sites checked in the call): a SubM 3x3 64 -> 64 layer module, and the
  16-layer down path of Sparse-PointPillars, against spconv; lidarops also under ``validation(False)``.
* ``pillars``: PointPillars' backbone made sparse (strided sparse conv at the start of each block,
  then 3/5/5 submanifold convs, channels 64/128/256, transposed upsampling x1/x2/x4 to 128 channels,
  dense concatenation), eval mode, on the KITTI grid: full forward (kernel maps built), forward
  with maps cached, that forward's kernels replayed as a CUDA graph, and ``GraphedSparseNet`` called as
  users write it (a new ``SparseConvTensor`` on the same indices each call, a copy of the output);
  against the dense PointPillars backbone (cuDNN) and spconv.
* ``voxel``: SECOND's VoxelBackBone8x on a 41 x 1600 x 1408 grid with 40k and 120k voxels of a
  LiDAR-like scan (ground rings and car surfaces, voxelised), full forward, against spconv (the dense
  3D grid does not fit: no cuDNN column).

GPU precisions (``--precisions``): ``fp32`` (TF32 off everywhere), ``tf32`` (cuDNN / cuBLAS may use
TF32; lidarops' float32 kernel stays exact float32), ``fp16``. Ratios are ``peer / lidarops``: above 1
means lidarops is faster.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
from functools import partial
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch
import torch.nn.functional as F
from torch import nn

import lidarops.compat.spconv as lspconv
from lidarops.sparse import GraphedSparseNet, SparseConvTensor
from lidarops.sparse import functional as Fs

from benchmarks.common import (env_meta, fmt_ms, fmt_ratio, print_table, short_status, time_call, time_interleaved,
                               write_results)

ops = torch.ops.lidarops

GRIDS = {"drone": ((504, 504), 2000), "kitti": ((496, 432), 15000), "dense": ((504, 504), 30000)}
CHANNELS = (16, 32, 64, 128)


def _spconv():
    try:
        import spconv.pytorch as sp  # noqa: F401
        return sp
    except Exception:  # noqa: BLE001
        return None


# ---------------------------------------------------------------- inputs

def bev_sites(shape, n, batch=1, seed=0, sensor=None) -> torch.Tensor:
    """(N, 3) int32 unique (batch, y, x) sites, density falling with the range from the sensor (like
    LiDAR pillars), plus a few dense object clusters."""
    H, W = shape
    g = torch.Generator().manual_seed(seed)
    sy, sx = sensor if sensor is not None else (H / 2, W / 2)
    rows = []
    for b in range(batch):
        got = torch.empty(0, dtype=torch.int64)
        while got.numel() < n:
            m = 4 * n
            r = torch.rand(m, generator=g).pow(1.6) * math.hypot(H, W) / 2
            a = torch.rand(m, generator=g) * 2 * math.pi
            y = (sy + r * torch.sin(a)).long()
            x = (sx + r * torch.cos(a)).long()
            keep = (y >= 0) & (y < H) & (x >= 0) & (x < W)
            lin = (y * W + x)[keep]
            got = torch.cat([got, lin])
            _, first = torch.unique(got, return_inverse=True)
            # keep first occurrences in generation order
            order = torch.arange(got.numel())
            uniq_pos = torch.full((int(first.max()) + 1,), got.numel(), dtype=torch.long).scatter_reduce(
                0, first, order, reduce="amin")
            got = got[torch.sort(uniq_pos).values]
        lin = got[:n]
        rows.append(torch.stack([torch.full_like(lin, b), lin // W, lin % W], 1))
    return torch.cat(rows).to(torch.int32)


def voxel_sites(n, shape=(41, 1600, 1408), batch=1, seed=0) -> torch.Tensor:
    """(N, 4) int32 unique (batch, z, y, x) voxels of a LiDAR-like scan in KITTI's voxel grid
    (x in [0, 70.4) m, y in [-40, 40) m at 0.05 m, z in [-3, 1) m at 0.1 m): ground returns on 64 rings
    in the front 90 degrees (60%) and the surfaces of 30 car-sized boxes (40%), voxelised; points are
    drawn until n distinct voxels are hit."""
    Z, H, W = shape
    sx, sy, sz = 70.4 / W, 80.0 / H, 4.0 / Z
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(batch):
        boxes = torch.stack([torch.rand(30, generator=g) * 55 + 5, (torch.rand(30, generator=g) - 0.5) * 50,
                             torch.rand(30, generator=g) * 6.28], 1)
        got = torch.empty(0, dtype=torch.int64)
        while got.numel() < n:
            m = 4 * n
            ground = torch.rand(m, generator=g) < 0.6
            beam = torch.randint(0, 64, (m,), generator=g).double()
            r = 3.0 * (70.0 / 3.0) ** (beam / 63.0)
            az = (torch.rand(m, generator=g) - 0.5) * (math.pi / 2)
            gx, gy = r * torch.cos(az), r * torch.sin(az)
            gz = -1.73 + torch.randn(m, generator=g) * 0.03
            k = torch.randint(0, 30, (m,), generator=g)
            u, v, hgt = (torch.rand(m, generator=g) - 0.5) * 4.0, (torch.rand(m, generator=g) - 0.5) * 1.8, \
                torch.rand(m, generator=g) * 1.5
            side = torch.rand(m, generator=g) < 0.5  # a point on a long side or on an end of the box
            u = torch.where(side, u, torch.sign(u) * 2.0)
            v = torch.where(side, torch.sign(v) * 0.9, v)
            c, s_ = torch.cos(boxes[k, 2]), torch.sin(boxes[k, 2])
            ox, oy = boxes[k, 0] + c * u - s_ * v, boxes[k, 1] + s_ * u + c * v
            x = torch.where(ground, gx, ox.double())
            y = torch.where(ground, gy, oy.double())
            z = torch.where(ground, gz, -1.73 + hgt.double())
            ix, iy, iz = (x / sx).floor().long(), ((y + 40.0) / sy).floor().long(), ((z + 3.0) / sz).floor().long()
            keep = (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H) & (iz >= 0) & (iz < Z)
            lin = ((iz * H + iy) * W + ix)[keep]
            got = torch.unique(torch.cat([got, lin]))
        lin = got[torch.randperm(got.numel(), generator=g)[:n]]
        rows.append(torch.stack([torch.full_like(lin, b), lin // (H * W), (lin // W) % H, lin % W], 1))
    return torch.cat(rows).to(torch.int32)


# ---------------------------------------------------------------- networks (any spconv-like namespace)

def sparse_pointpillars(sp, in_channels=64, layer_nums=(3, 5, 5), layer_strides=(2, 2, 2),
                        num_filters=(64, 128, 256), upsample_strides=(1, 2, 4), num_upsample_filters=(128, 128, 128)):
    norm = partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)
    blocks, deblocks = nn.ModuleList(), nn.ModuleList()
    c_in = in_channels
    for i, (n, s, f) in enumerate(zip(layer_nums, layer_strides, num_filters)):
        layers = [sp.SparseConv2d(c_in, f, 3, stride=s, padding=1, bias=False, indice_key=f"down{i}"), norm(f),
                  nn.ReLU()]
        for _ in range(n):
            layers += [sp.SubMConv2d(f, f, 3, padding=1, bias=False, indice_key=f"subm{i}"), norm(f), nn.ReLU()]
        blocks.append(sp.SparseSequential(*layers))
        u, uf = upsample_strides[i], num_upsample_filters[i]
        deblocks.append(sp.SparseSequential(sp.SparseConvTranspose2d(f, uf, u, stride=u, bias=False,
                                                                     indice_key=f"up{i}"), norm(uf), nn.ReLU()))
        c_in = f

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.blocks, self.deblocks = blocks, deblocks

        def forward(self, x):
            ups = []
            for block, deblock in zip(self.blocks, self.deblocks):
                x = block(x)
                ups.append(deblock(x))
            # every branch's maps (each branch's dict gains its own upsampling map): with all of them
            # cached a forward builds none
            self.last_dict = {k: v for u in ups for k, v in u.indice_dict.items()}
            return torch.cat([u.dense() for u in ups], 1)

    return Net()


def dense_pointpillars(in_channels=64, layer_nums=(3, 5, 5), layer_strides=(2, 2, 2), num_filters=(64, 128, 256),
                       upsample_strides=(1, 2, 4), num_upsample_filters=(128, 128, 128)):
    norm = partial(nn.BatchNorm2d, eps=1e-3, momentum=0.01)
    blocks, deblocks = nn.ModuleList(), nn.ModuleList()
    c_in = in_channels
    for n, s, f, u, uf in zip(layer_nums, layer_strides, num_filters, upsample_strides, num_upsample_filters):
        layers = [nn.Conv2d(c_in, f, 3, stride=s, padding=1, bias=False), norm(f), nn.ReLU()]
        for _ in range(n):
            layers += [nn.Conv2d(f, f, 3, padding=1, bias=False), norm(f), nn.ReLU()]
        blocks.append(nn.Sequential(*layers))
        deblocks.append(nn.Sequential(nn.ConvTranspose2d(f, uf, u, stride=u, bias=False), norm(uf), nn.ReLU()))
        c_in = f

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.blocks, self.deblocks = blocks, deblocks

        def forward(self, x):
            ups = []
            for block, deblock in zip(self.blocks, self.deblocks):
                x = block(x)
                ups.append(deblock(x))
            return torch.cat(ups, 1)

    return Net()


def voxel_backbone_8x(sp, input_channels=4):
    norm = partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)

    def block(cin, cout, k, indice_key, stride=1, padding=0, conv_type="subm"):
        if conv_type == "subm":
            conv = sp.SubMConv3d(cin, cout, k, bias=False, indice_key=indice_key)
        else:
            conv = sp.SparseConv3d(cin, cout, k, stride=stride, padding=padding, bias=False, indice_key=indice_key)
        return sp.SparseSequential(conv, norm(cout), nn.ReLU())

    return sp.SparseSequential(
        sp.SubMConv3d(input_channels, 16, 3, padding=1, bias=False, indice_key="subm1"), norm(16), nn.ReLU(),
        block(16, 16, 3, "subm1"),
        block(16, 32, 3, "spconv2", 2, 1, "spconv"), block(32, 32, 3, "subm2"), block(32, 32, 3, "subm2"),
        block(32, 64, 3, "spconv3", 2, 1, "spconv"), block(64, 64, 3, "subm3"), block(64, 64, 3, "subm3"),
        block(64, 64, 3, "spconv4", 2, (0, 1, 1), "spconv"), block(64, 64, 3, "subm4"), block(64, 64, 3, "subm4"),
        sp.SparseConv3d(64, 128, (3, 1, 1), stride=(2, 1, 1), padding=0, bias=False, indice_key="spconv_down2"),
        norm(128), nn.ReLU(), sp.ToDense())


# ---------------------------------------------------------------- precision modes

@contextlib.contextmanager
def precision(mode: str):
    old = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    tf32 = mode == "tf32"
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32
    try:
        yield torch.float16 if mode == "fp16" else torch.float32
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def _ms(t):
    """Median ms of a Timing; None for a status (skipped, error) or a measurement not taken."""
    return t.median if hasattr(t, "median") else None


def _error(e: BaseException) -> str:
    msg = str(e).strip().splitlines()[0][:160] if str(e).strip() else ""
    return f"error: {type(e).__name__}: {msg}"


def _try(fn, args, device, **kw):
    """The Timing of ``fn(*args)``, or a status string when it cannot be measured: "skipped (memory: out
    of memory)" or "error: <type>: <message>" (reported in the row and the table, never blank)."""
    try:
        return time_call(fn, args, device, **kw)
    except torch.cuda.OutOfMemoryError:
        torch.cuda.empty_cache()
        return "skipped (memory: out of memory)"
    except Exception as e:  # noqa: BLE001  (reported)
        return _error(e)


def _try_interleaved(calls, device, **kw) -> list:
    """:func:`_try` for implementations timed side by side (``benchmarks.common.time_interleaved``): a Timing or a
    status string each; ``None`` for an implementation not there (its call None)."""
    present = [i for i, c in enumerate(calls) if c is not None]
    out: list = [None] * len(calls)
    for i, t in zip(present, time_interleaved([calls[i] for i in present], device, **kw)):
        if isinstance(t, torch.cuda.OutOfMemoryError):
            torch.cuda.empty_cache()
            t = "skipped (memory: out of memory)"
        elif isinstance(t, BaseException):
            t = _error(t)
        out[i] = t
    return out


def _cell(t) -> str:
    """Table cell: the median, the short status, or "-" for a measurement not taken."""
    if isinstance(t, str):
        return short_status(t)
    return fmt_ms(_ms(t))


def _row(t):
    """JSON value: the timing's dict, {"status": ...} for a status, None for a measurement not taken."""
    if isinstance(t, str):
        return {"status": t, "median_ms": None}
    return t.as_dict() if t is not None else None


def _ratio(a, b) -> str:
    return fmt_ratio(_ms(a) / _ms(b)) if _ms(a) and _ms(b) else ""


def _report_errors(rows: list[dict]) -> None:
    for r in rows:
        for k, v in r.items():
            if isinstance(v, dict) and str(v.get("status", "")).startswith(("error", "skipped")):
                print(f"  {r['op']}, {k}: {v['status']}")


# ---------------------------------------------------------------- sections

def bench_layers(device, modes, quick, rows_out):
    sp = _spconv() if torch.device(device).type == "cuda" else None
    grids = {"drone": GRIDS["drone"]} if quick else GRIDS
    chans = (16, 64) if quick else CHANNELS
    table = []
    first = len(rows_out)
    for gname, (shape, n) in grids.items():
        idx = bev_sites(shape, n).to(device)
        for kind in ("subm", "conv"):
            for mode in modes:
                with precision(mode) as dtype:
                    for C in chans:
                        x = SparseConvTensor(torch.randn(idx.shape[0], C, device=device, dtype=dtype), idx,
                                             list(shape), 1)
                        w = torch.randn(C, 3, 3, C, device=device, dtype=dtype) / (3 * math.sqrt(C))
                        km = Fs.build_kernel_map(x, kind, 3, 2 if kind == "conv" else 1, 1, 1)
                        w3 = w.reshape(C, 9, C)
                        t_op = _try(ops.sparse_conv, (x.features, w3, km.neighbors, km.order), device)
                        t_mod = _module_layer_time(lspconv, kind, x, w, device)
                        dense = x.dense()
                        wd = w.permute(0, 3, 1, 2).contiguous()
                        s = 2 if kind == "conv" else 1
                        t_dense = _try(lambda d, ww: F.conv2d(d, ww, None, s, 1), (dense, wd), device)
                        t_sp = _module_layer_time(sp, kind, x, w, device) if sp is not None else None
                        table.append([gname, idx.shape[0], kind, mode, C, _cell(t_op), _cell(t_mod), _cell(t_dense),
                                      _ratio(t_dense, t_op), _cell(t_sp), _ratio(t_sp, t_mod)])
                        rows_out.append({"section": "layer", "op": f"layer/{gname}/{kind}/{mode}/C{C}", "grid": gname,
                                         "sites": int(idx.shape[0]), "kind": kind, "precision": mode, "channels": C,
                                         "lidarops": _row(t_op), "lidarops_module": _row(t_mod),
                                         "dense_cudnn": _row(t_dense), "spconv": _row(t_sp)})
    # like with like: the raw op against dense cuDNN's F.conv2d; the module call (kernel map cached under
    # its indice_key) against spconv's module call, cached the same way
    print_table(f"single layers, 3x3, kernel map cached ({device}); op: torch.ops.lidarops.sparse_conv, module: "
                "lidarops.compat.spconv layer (as spconv's)",
                ["grid", "sites", "kind", "prec", "C", "lidarops op", "lidarops module", "dense", "dense/op",
                 "spconv module", "spconv/module"],
                table, right=(1, 4, 5, 6, 7, 8, 9, 10))
    _report_errors(rows_out[first:])


def _module_layer_time(sp, kind, x, w, device):
    """One spconv-style layer module (``sp``: spconv.pytorch or lidarops.compat.spconv) called on a tensor
    whose ``indice_dict`` already holds its kernel map: a Timing, or an "error: ..." status."""
    C = w.shape[0]
    try:
        if kind == "subm":
            layer = sp.SubMConv2d(C, C, 3, padding=1, bias=False, indice_key="k")
        else:
            layer = sp.SparseConv2d(C, C, 3, stride=2, padding=1, bias=False, indice_key="k")
        layer = layer.to(device=device, dtype=w.dtype).eval()
        with torch.no_grad():
            layer.weight.copy_(w)
            st = sp.SparseConvTensor(x.features, x.indices, x.spatial_shape, x.batch_size)
            y = layer(st)
            cached = sp.SparseConvTensor(x.features, x.indices, x.spatial_shape, x.batch_size,
                                         indice_dict=y.indice_dict)

            def run(f):
                cached_in = cached.replace_feature(f)
                return layer(cached_in)
            return _try(run, (x.features,), device)
    except Exception as e:  # noqa: BLE001  (e.g. spconv's strided layers: reported, not blanked)
        return _error(e)


def bench_maps(device, quick, rows_out):
    grids = {"drone": GRIDS["drone"]} if quick else GRIDS
    table = []
    first = len(rows_out)
    for gname, (shape, n) in grids.items():
        idx = bev_sites(shape, n).to(device)
        x = SparseConvTensor(torch.zeros(idx.shape[0], 1, device=device), idx, list(shape), 1)
        for kind in ("subm", "conv", "transposed"):
            for method in ("auto", "dense", "hash"):
                s = 2 if kind != "subm" else 1
                t = _try(lambda: Fs.build_kernel_map(x, kind, 3, s, 1, 1, method=method), (), device)
                table.append([gname, idx.shape[0], kind, method, _cell(t)])
                rows_out.append({"section": "map", "op": f"map/{gname}/{kind}/{method}", "grid": gname,
                                 "sites": int(idx.shape[0]), "kind": kind, "method": method,
                                 "lidarops": _row(t)})
    print_table(f"kernel-map construction, 3x3 (stride 2 for conv/transposed) ({device})",
                ["grid", "sites", "kind", "table", "ms"], table, right=(1, 4))
    _report_errors(rows_out[first:])


def pillars_input(device, dtype, quick=False):
    """The pillars section's network and input: (the lidarops Sparse-PointPillars net in eval mode,
    its input SparseConvTensor, the same input with every kernel map cached). KITTI grid, 15k
    range-weighted pillars (128 x 128 with 1,500 when ``quick``). Call under ``torch.no_grad()``."""
    shape, n = ((128, 128), 1500) if quick else GRIDS["kitti"]
    idx = bev_sites(shape, n, sensor=(shape[0] / 2, 0)).to(device)
    feats = torch.randn(idx.shape[0], 64, device=device, dtype=dtype)
    net = sparse_pointpillars(lspconv).to(device=device, dtype=dtype).eval()
    x = SparseConvTensor(feats, idx, list(shape), 1)
    net(x)  # builds the maps
    return net, x, SparseConvTensor(feats, idx, list(shape), 1, indice_dict=net.last_dict)


def bench_pillars(device, modes, quick, rows_out):
    sp = _spconv() if torch.device(device).type == "cuda" else None
    shape = (128, 128) if quick else GRIDS["kitti"][0]
    table = []
    first = len(rows_out)
    for mode in modes:
        with precision(mode) as dtype, torch.no_grad():
            net, x, cached = pillars_input(device, dtype, quick)
            feats, idx, shape = x.features, x.indices, x.spatial_shape
            t_full = _try(net, (x,), device)
            t_cached = _try(lambda f: net(cached.replace_feature(f)), (feats,), device)
            t_graph = _graphed(net, cached, feats) if torch.device(device).type == "cuda" else None
            # the user's call: a new SparseConvTensor on the same indices each frame, replayed with a copy of the
            # output (GraphedSparseNet's default)
            graphed = GraphedSparseNet(net)
            t_user = _try(lambda f: graphed(SparseConvTensor(f, idx, list(shape), 1)), (feats,), device)
            if graphed.reason is not None:
                print(f"  (GraphedSparseNet runs eagerly: {graphed.reason})")
            dnet = dense_pointpillars().to(device=device, dtype=dtype).eval()
            t_dense = _try(dnet, (x.dense(),), device)
            t_sp = None
            if sp is not None:
                try:
                    snet = sparse_pointpillars(sp).to(device=device, dtype=dtype).eval()
                    t_sp = _try(lambda f: snet(sp.SparseConvTensor(f, idx, list(shape), 1)), (feats,), device)
                except Exception as e:  # noqa: BLE001  (reported in the row)
                    t_sp = _error(e)
            table.append([mode, idx.shape[0], _cell(t_full), _cell(t_cached), _cell(t_graph), _cell(t_user),
                          _cell(t_dense), _ratio(t_dense, t_full), _cell(t_sp), _ratio(t_sp, t_full)])
            rows_out.append({"section": "pillars", "op": f"pillars/{mode}", "precision": mode,
                             "sites": int(idx.shape[0]), "grid": list(shape),
                             "lidarops_full": _row(t_full),
                             "lidarops_cached_maps": _row(t_cached),
                             "lidarops_cached_maps_cuda_graph": _row(t_graph),
                             "lidarops_graphed_sparse_net": _row(t_user),
                             "dense_cudnn": _row(t_dense),
                             "spconv": _row(t_sp)})
    print_table(f"Sparse-PointPillars backbone, grid {shape[0]} x {shape[1]} ({device})",
                ["prec", "pillars", "lidarops", "maps cached", "+ CUDA graph", "GraphedSparseNet", "dense",
                 "dense/ours", "spconv", "spconv/ours"], table, right=(1, 2, 3, 4, 5, 6, 7, 8, 9))
    _report_errors(rows_out[first:])


def _graphed(net, cached, feats):
    """The forward with maps cached, captured in a CUDA graph (no launch or Python overhead): the time
    of its kernels alone. Each timed call copies new features into the graph's static input."""
    static = feats.clone()
    x = cached.replace_feature(static)
    try:
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                net(x)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            net(x)
    except RuntimeError as e:  # a host synchronisation in the forward cannot be captured
        print(f"  (CUDA graph capture of the cached-map forward failed: {str(e).splitlines()[0]})")
        return _error(e)
    return _try(lambda f: (static.copy_(f), graph.replay()), (feats,), feats.device)


def down_path(net):
    """The down path of a ``sparse_pointpillars`` net: its three blocks (a strided convolution and 3 / 5 / 5
    submanifold ones each, 16 layers with BatchNorm and ReLU), without the upsampling branches."""
    def run(x):
        for block in net.blocks:
            x = block(x)
        return x
    return run


def _on_new_sites(net, ns, checks: bool, idx, shape, feats) -> tuple:
    """``(call, args)``: ``net`` on a new SparseConvTensor over a new copy of ``idx`` (a new frame), with the value
    checks on or off."""
    from lidarops.ops.validation import validation

    def call(f):
        with validation(checks):
            return net(ns.SparseConvTensor(f, idx.clone(), list(shape), 1))
    return call, (feats,)


def bench_eager(device, modes, quick, rows_out, block=1):
    """What users see: every call starts from a new ``SparseConvTensor`` on a new copy of the indices (no
    ``indice_dict``, sites never seen: a new frame), so each call builds and checks its kernel maps. One SubM
    3x3 64 -> 64 layer module, and the 16-layer down path of the Sparse-PointPillars backbone, lidarops
    (its default, which checks a new frame's sites once: one host synchronisation, and under
    ``lidarops.validation(False)``) against spconv (which checks nothing). The copy is in every column. The three
    columns' calls are interleaved (``benchmarks.common.time_interleaved``), so that their ratios compare calls
    made side by side; on CUDA each from an idle GPU, the order turning each round (none always follows the same
    other), and with ``block`` > 1 each column's turn ``block`` calls in a row, the first not timed (a user's loop
    of one library)."""
    sp = _spconv() if torch.device(device).type == "cuda" else None
    cuda = torch.device(device).type == "cuda"
    timing = "the columns' calls interleaved" + (", order turning each round, each call from an idle GPU"
                                                 if cuda else "")
    if cuda and block > 1:
        timing += f", each column's turn {block} calls in a row, the first not timed"
    grids = {"drone": GRIDS["drone"]} if quick else GRIDS
    table = []
    first = len(rows_out)
    for gname, (shape, n) in grids.items():
        idx = bev_sites(shape, n).to(device)
        for mode in modes:
            with precision(mode) as dtype, torch.no_grad():
                feats = torch.randn(idx.shape[0], 64, device=device, dtype=dtype)
                # the three implementations' calls interleaved: their ratios compare calls made side by side
                impls = (("lidarops", lspconv, True), ("lidarops_unchecked", lspconv, False), ("spconv", sp, True))
                layers, downs, failed = [], [], {}
                for impl, ns, checks in impls:
                    layer = down = None
                    if ns is not None:
                        try:
                            layer = ns.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k")
                            layer = layer.to(device=device, dtype=dtype).eval()
                            down = down_path(sparse_pointpillars(ns).to(device=device, dtype=dtype).eval())
                        except Exception as e:  # noqa: BLE001  (reported in the row)
                            failed[impl], layer, down = _error(e), None, None
                    layers.append(None if layer is None else _on_new_sites(layer, ns, checks, idx, shape, feats))
                    downs.append(None if down is None else _on_new_sites(down, ns, checks, idx, shape, feats))
                t_layers = _try_interleaved(layers, device, idle=True, rotate=True, block=block)
                t_downs = _try_interleaved(downs, device, idle=True, rotate=True, block=block)
                cells = {impl: (failed.get(impl) or t_layers[j], failed.get(impl) or t_downs[j])
                         for j, (impl, _, _) in enumerate(impls)}
                (l_ours, d_ours), (l_off, d_off), (l_sp, d_sp) = (cells["lidarops"], cells["lidarops_unchecked"],
                                                                  cells["spconv"])
                table.append([gname, idx.shape[0], mode, _cell(l_ours), _cell(l_off), _cell(l_sp),
                              _ratio(l_sp, l_ours), _cell(d_ours), _cell(d_off), _cell(d_sp), _ratio(d_sp, d_ours)])
                rows_out.append({"section": "eager", "op": f"eager/{gname}/{mode}", "grid": gname,
                                 "sites": int(idx.shape[0]), "precision": mode, "channels": 64,
                                 "indices": "a new copy per call", "timing": timing,
                                 "subm_with_map": {"lidarops": _row(l_ours), "lidarops_validation_off": _row(l_off),
                                                   "spconv": _row(l_sp)},
                                 "down_path_16_layers": {"lidarops": _row(d_ours),
                                                         "lidarops_validation_off": _row(d_off),
                                                         "spconv": _row(d_sp)}})
    print_table(f"eager calls, each on a new copy of the indices, kernel maps built in the call ({device}): SubM 3x3 "
                "64 -> 64 module; the 16-layer down path of Sparse-PointPillars (C 64/128/256, BatchNorm, ReLU); "
                "'checks off': lidarops under lidarops.validation(False)",
                ["grid", "sites", "prec", "SubM", "checks off", "spconv", "spconv/ours", "down path", "checks off",
                 "spconv", "spconv/ours"], table, right=(1, 3, 4, 5, 6, 7, 8, 9, 10))
    _report_errors(rows_out[first:])


def bench_voxels(device, modes, quick, rows_out):
    sp = _spconv() if torch.device(device).type == "cuda" else None
    shape = (41, 400, 352) if quick else (41, 1600, 1408)
    counts = (5000,) if quick else ((40000, 120000) if torch.device(device).type == "cuda" else (40000,))
    table = []
    first = len(rows_out)
    for n in counts:
        idx = voxel_sites(n, shape).to(device)
        for mode in modes:
            with precision(mode) as dtype, torch.no_grad():
                feats = torch.randn(idx.shape[0], 4, device=device, dtype=dtype)
                net = voxel_backbone_8x(lspconv).to(device=device, dtype=dtype).eval()
                t_ours = _try(lambda f: net(SparseConvTensor(f, idx, list(shape), 1)), (feats,), device)
                t_sp = None
                if sp is not None:
                    try:
                        snet = voxel_backbone_8x(sp).to(device=device, dtype=dtype).eval()
                        t_sp = _try(lambda f: snet(sp.SparseConvTensor(f, idx, list(shape), 1)), (feats,), device)
                    except Exception as e:  # noqa: BLE001  (reported in the row)
                        t_sp = _error(e)
                table.append([n, mode, _cell(t_ours), _cell(t_sp), _ratio(t_sp, t_ours)])
                rows_out.append({"section": "voxel", "op": f"voxel/{n}/{mode}", "voxels": n, "precision": mode,
                                 "grid": list(shape), "lidarops": _row(t_ours), "spconv": _row(t_sp)})
    print_table(f"VoxelBackBone8x, grid {shape} ({device})", ["voxels", "prec", "lidarops", "spconv", "spconv/ours"],
                table, right=(0, 2, 3, 4))
    _report_errors(rows_out[first:])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", choices=["cpu", "cuda", "all"], default="all")
    ap.add_argument("--only", default="layer,map,eager,pillars,voxel")
    ap.add_argument("--precisions", default="fp32,tf32,fp16")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--eager-block", type=int, default=1, metavar="K",
                    help="eager section on CUDA: each column's turn is K calls in a row, the first not timed (1: one "
                         "call a turn)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--vs-spconv", action="store_true",
                    help="spconv must be importable (its columns are otherwise left empty); its version goes into "
                         "the results' meta")
    args = ap.parse_args(argv)
    if args.eager_block < 1:
        ap.error(f"--eager-block must be >= 1, got {args.eager_block}")
    if args.vs_spconv and _spconv() is None:
        ap.error("--vs-spconv: spconv.pytorch does not import (spconv 2.x wheels: ../shared/tools/spconv-bundle.sh)")
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or torch.cuda.is_available()]
    only = set(args.only.split(","))
    for device in devices:
        modes = args.precisions.split(",") if device == "cuda" else ["fp32"]
        rows: list[dict] = []
        if "layer" in only:
            bench_layers(device, modes, args.quick, rows)
        if "map" in only:
            bench_maps(device, args.quick, rows)
        if "eager" in only:
            bench_eager(device, modes, args.quick, rows, block=args.eager_block)
        if "pillars" in only:
            bench_pillars(device, modes, args.quick, rows)
        if "voxel" in only:
            bench_voxels(device, modes, args.quick, rows)
        if args.json:
            meta = env_meta(device)
            if device == "cuda" and _spconv() is not None:
                import spconv
                meta["peers"] = {"spconv": getattr(spconv, "__version__", "unknown")}
            path = write_results("sparse", device, rows, meta)
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
