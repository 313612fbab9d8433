"""Plain re-statements of lidarops.models.counting's pieces (loops over objects and cells, float64), the
references its tests compare with."""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

def _heatmap_targets_reference(boxes: Tensor, num_classes: int, point_cloud_range, voxel_size, grid_size,
                               stride: int, min_overlap: float = 0.1, min_radius: int = 2) -> np.ndarray:
    """CenterPoint's loop, object by object, in float64 NumPy (``draw_umich_gaussian`` with the floor rule and the
    size-0 rule of :func:`heatmap_targets`)."""
    b = boxes.detach().cpu().double().numpy()
    B = b.shape[0]
    H, W = grid_size[1] // stride, grid_size[0] // stride
    heat = np.zeros((B, num_classes, H, W))
    for f in range(B):
        for row in b[f]:
            c = int(row[7])
            if c == 0:
                continue
            cx = math.floor((row[0] - point_cloud_range[0]) / (voxel_size[0] * stride))
            cy = math.floor((row[1] - point_cloud_range[1]) / (voxel_size[1] * stride))
            if not (0 <= cx < W and 0 <= cy < H):
                continue
            w, h = row[3] / (voxel_size[0] * stride), row[4] / (voxel_size[1] * stride)
            r = max(min_radius, int(_gaussian_radius_python(h, w, min_overlap)))
            d = 2 * r + 1
            sigma = d / 6
            yy, xx = np.ogrid[-r:r + 1, -r:r + 1]
            g = np.exp(-(xx * xx + yy * yy) / (2 * sigma * sigma))
            left, right = min(cx, r), min(W - cx, r + 1)
            top, bottom = min(cy, r), min(H - cy, r + 1)
            patch = heat[f, c - 1, cy - top:cy + bottom, cx - left:cx + right]
            np.maximum(patch, g[r - top:r + bottom, r - left:r + right], out=patch)
    return heat


def _gaussian_radius_python(height: float, width: float, min_overlap: float) -> float:
    """CenterPoint's ``gaussian_radius((height, width), min_overlap)``, line for line."""
    a1 = 1
    b1 = (height + width)
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    sq1 = math.sqrt(b1 ** 2 - 4 * a1 * c1)
    r1 = (b1 + sq1) / 2
    a2 = 4
    b2 = 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    sq2 = math.sqrt(b2 ** 2 - 4 * a2 * c2)
    r2 = (b2 + sq2) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    sq3 = math.sqrt(b3 ** 2 - 4 * a3 * c3)
    r3 = (b3 + sq3) / 2
    return min(r1, r2, r3)


def _find_peaks_reference(heatmap: Tensor, threshold, radius: int) -> Tensor:
    """Window by window in float64 (the window clipped at the edges; NaN never a peak and poisoning its windows)."""
    h = heatmap.detach().cpu().double()
    thr = torch.broadcast_to(torch.as_tensor(threshold, dtype=torch.float64).cpu(), h.shape)
    B, C, H, W = h.shape
    out = torch.zeros(h.shape, dtype=torch.bool)
    for b in range(B):
        for c in range(C):
            for i in range(H):
                for j in range(W):
                    win = h[b, c, max(0, i - radius):i + radius + 1, max(0, j - radius):j + radius + 1]
                    top = math.nan if bool(torch.isnan(win).any()) else float(win.max())
                    out[b, c, i, j] = float(h[b, c, i, j]) == top and float(h[b, c, i, j]) >= float(thr[b, c, i, j])
    return out


def _merge_centres_reference(centres: Tensor, radius: float) -> Tensor:
    """Algorithm 1 in plain Python: sort by score (stable), keep a centre unless a kept one of its class is near."""
    rows = centres.detach().cpu().double().tolist()
    order = sorted(range(len(rows)), key=lambda i: -rows[i][3])
    kept = []
    for i in order:
        x, y, c, _ = rows[i]
        if all(k[2] != c or math.hypot(x - k[0], y - k[1]) > radius for k in (rows[j] for j in kept)):
            kept.append(i)
    return torch.tensor(kept, dtype=torch.int64)
