"""CounterNet's counting parts (Zhang et al., MM'25): per-class object counts read off a bird's-eye-view heatmap,
the way CenterPoint draws and reads its centre heatmaps, plus the pieces of the seed's partition scheme and its
per-frame model selection.

What each piece follows:

* :func:`gaussian_radius`, :func:`heatmap_targets`: CenterPoint's targets (det3d ``core/utils/center_utils.py``:
  ``gaussian_radius``, ``gaussian2D``, ``draw_umich_gaussian``; ``CenterHead``'s target assigner): one Gaussian per
  object on its class channel at its centre cell, combined by elementwise max, drawn for all objects at once.
* :func:`focal_loss`: CenterNet's focal loss on probabilities (``_neg_loss``, alpha = 2, beta = 4).
* :func:`find_peaks`, :func:`count_peaks`, :func:`peak_centres`, :func:`soft_count`: the max-pool peak test of
  CenterNet's decoder (a cell is a peak when it equals the maximum of its ``(2r+1)^2`` window), with a threshold;
  the same peaks as ``skimage.feature.peak_local_max(min_distance=r, exclude_border=False)`` on maps without ties.
* :func:`otsu_threshold`: ``skimage.filters.threshold_otsu``, row by row, batched.
* :func:`partition_boxes`, :func:`merge_centres`, :func:`partition_weights`: the seed's partitions (overlapping
  regions of the map, each thresholded on its own), its Algorithm 1 (merging the centres found twice where regions
  overlap) and its region weights.
* :class:`ChernoffSelector`: the seed's per-frame choice among several counting models (nearest model centre in
  feature space, scaled by a Chernoff bound on how well that centre is known).

Everything works on CPU and CUDA tensors, float32 and float64, batched: no Python loop per frame or per object.
The loops left: :func:`merge_centres`' greedy scan (sequential by nature; on the CPU over a boolean matrix, over
the centres that have a conflict), :func:`otsu_threshold`'s running sums (NumPy's sequential ``cumsum`` on the
host, to reproduce skimage's rounding; ``exact=False`` scans on the device instead), :func:`heatmap_targets`' chunks (one unless very
different radii would make the windows too large) and :func:`peak_centres`' split of one result into frames.
"""
from __future__ import annotations

import math
import numbers

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lidarops._checks import integer, positive_int, real
from lidarops.ops.validation import check_tensor, describe, run_value_checks, value_checks_enabled

__all__ = ["gaussian_radius", "heatmap_targets", "focal_loss", "find_peaks", "count_peaks", "peak_centres",
           "soft_count", "otsu_threshold", "partition_boxes", "merge_centres", "partition_weights",
           "ChernoffSelector", "PARTITIONS"]

#: The partition counts :func:`partition_boxes` accepts, with their (rows, columns) grids: 2 splits the width
#: (x, the driving direction).
PARTITIONS = {1: (1, 1), 2: (1, 2), 4: (2, 2), 9: (3, 3)}

#: Most window entries :func:`heatmap_targets` builds at once (objects x (2r+1)^2); beyond it the objects are drawn
#: in chunks of similar radius.
_WINDOW_BUDGET = 1 << 22
#: Rows of the distance matrix :func:`merge_centres` builds at once.
_MERGE_ROWS = 1024


# ---------------------------------------------------------------------------------------------- argument checks
def _real_tensor(t, name: str) -> None:
    check_tensor(t, name)
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name} must be a real (integer or floating) tensor, got {describe(t)}")


def _floating(t, name: str, dims: int | None = None, what: str = "") -> None:
    check_tensor(t, name)
    if dims is not None and t.dim() != dims:
        raise ValueError(f"{name} must be {what}, got {describe(t)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {describe(t)}")


def _check_heatmap(t, name: str = "heatmap") -> None:
    _floating(t, name, 4, "a (B, C, H, W) heatmap")


def _same_device(a: Tensor, a_name: str, b: Tensor, b_name: str) -> None:
    if a.device != b.device:
        raise ValueError(f"{b_name} is on {b.device} but {a_name} is on {a.device}; move them to one device "
                         f"({b_name}: {describe(b)})")


def _radius(radius) -> int:
    return integer(radius, "radius", lo=0)


def _threshold(threshold, heatmap: Tensor, name: str = "threshold"):
    """A number (not NaN; infinities allowed) or a real tensor broadcastable to the heatmap, on its device."""
    if isinstance(threshold, Tensor):
        if threshold.dtype == torch.bool or threshold.is_complex():
            raise ValueError(f"{name} must be a number or a real tensor, got {describe(threshold)}")
        _same_device(heatmap, "heatmap", threshold, name)
        try:
            shape = torch.broadcast_shapes(threshold.shape, heatmap.shape)
        except RuntimeError:
            shape = None
        if shape != heatmap.shape:
            raise ValueError(f"{name} must broadcast to the heatmap's shape {tuple(heatmap.shape)} (e.g. (B, C, 1, 1) "
                             f"or (B, C, H, W)), got {describe(threshold)}")
        return threshold
    if isinstance(threshold, (bool, np.bool_)) or not isinstance(threshold, numbers.Real) or math.isnan(threshold):
        raise ValueError(f"{name} must be a number (not NaN) or a tensor broadcastable to the heatmap, got "
                         f"{threshold!r}")
    return float(threshold)


def _floats(v, name: str, lengths: tuple, positive: bool = False) -> list:
    """A sequence (list, tuple, array, 1-D tensor) of ``lengths`` finite floats."""
    if isinstance(v, Tensor):
        v = v.detach().cpu().tolist()
    elif isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) not in lengths:
        raise ValueError(f"{name} must hold {' or '.join(map(str, lengths))} numbers, got {v!r}")
    return [real(x, f"{name}[{i}]", lo=0 if positive else None, lo_open=positive) for i, x in enumerate(v)]


def _ints(v, name: str, lengths: tuple) -> list:
    if isinstance(v, Tensor):
        v = v.detach().cpu().tolist()
    elif isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) not in lengths:
        raise ValueError(f"{name} must hold {' or '.join(map(str, lengths))} ints, got {v!r}")
    return [positive_int(x, f"{name}[{i}]") for i, x in enumerate(v)]


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


# ---------------------------------------------------------------------------------------------- targets
def gaussian_radius(dx: Tensor, dy: Tensor, min_overlap: float = 0.1) -> Tensor:
    """CenterPoint's (and CenterNet's) Gaussian radius of boxes of size ``dx`` x ``dy`` cells, elementwise.

    The three cases of ``gaussian_radius((height, width), min_overlap)`` (det3d ``core/utils/center_utils.py``),
    with height = ``dy`` and width = ``dx``, each the larger root of a quadratic, and the smallest of the three::

        r1 = (b1 + sqrt(b1^2 - 4 c1)) / 2,       b1 = h + w,           c1 = w h (1 - o) / (1 + o)
        r2 = (b2 + sqrt(b2^2 - 16 c2)) / 2,      b2 = 2 (h + w),       c2 = (1 - o) w h
        r3 = (b3 + sqrt(b3^2 - 16 o c3)) / 2,    b3 = -2 o (h + w),    c3 = (o - 1) w h

    (``/ 2`` rather than ``/ (2 a)`` in r2 and r3, as in CenterNet's code, which CenterPoint keeps; the formula is
    symmetric in ``dx`` and ``dy``.)

    Args:
        dx, dy (Tensor[...]): box sizes in cells along x (width) and y (height), >= 0; any real dtype, shapes that
            broadcast, one device.
        min_overlap (float): in (0, 1); CenterPoint uses 0.1, CenterNet 0.7.

    Returns:
        Tensor[...]: the radius in cells (not rounded), in the inputs' floating dtype (float32 for integer sizes).
        A size of 0 gives r3 = 0.

    Raises:
        ValueError: naming ``dx``, ``dy`` or ``min_overlap``; with the value checks on, a negative, NaN or
            infinite size.
    """
    _real_tensor(dx, "dx")
    _real_tensor(dy, "dy")
    _same_device(dx, "dx", dy, "dy")
    try:
        torch.broadcast_shapes(dx.shape, dy.shape)
    except RuntimeError:
        raise ValueError(f"dx and dy must broadcast to one shape, got dx {describe(dx)}, dy {describe(dy)}") from None
    o = real(min_overlap, "min_overlap", 0, 1, lo_open=True, hi_open=True)
    dt = torch.promote_types(dx.dtype, dy.dtype)
    if not dt.is_floating_point:
        dt = torch.get_default_dtype()
    w, h = dx.to(dt), dy.to(dt)
    if value_checks_enabled() and w.device.type != "meta":
        run_value_checks([(~(w >= 0).all(),  # NaN fails too
                           lambda: f"dx must hold sizes >= 0, got {describe(dx)} with min {float(dx.min()):g}"),
                          (~(h >= 0).all(),
                           lambda: f"dy must hold sizes >= 0, got {describe(dy)} with min {float(dy.min()):g}"),
                          (~torch.isfinite(w).all() | ~torch.isfinite(h).all(),
                           lambda: f"dx and dy must be finite, got dx {describe(dx)}, dy {describe(dy)}")])
    return _gaussian_radius(w, h, o)


def _div(a: Tensor, b: float) -> Tensor:
    """``a / b`` rounded once, on every device: CUDA divides a tensor by a Python number as a product with its
    reciprocal (off by an ulp where ``1 / b`` is not exact: 6, 7), a tensor divisor is a true division. (``full``,
    not ``tensor``: a fill on the device, which a CUDA graph can hold; ``tensor`` copies from the host.)"""
    return a / torch.full((), b, dtype=a.dtype, device=a.device)


def _gaussian_radius(w: Tensor, h: Tensor, o: float) -> Tensor:
    b1 = h + w
    c1 = _div(w * h * (1 - o), 1 + o)
    r1 = (b1 + torch.sqrt(b1 ** 2 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - o) * w * h
    r2 = (b2 + torch.sqrt(b2 ** 2 - 16 * c2)) / 2
    a3 = 4 * o
    b3 = -2 * o * (h + w)
    c3 = (o - 1) * w * h
    r3 = (b3 + torch.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return torch.minimum(torch.minimum(r1, r2), r3)


def heatmap_targets(boxes: Tensor, num_classes: int, point_cloud_range, voxel_size, grid_size, stride: int,
                    min_overlap: float = 0.1, min_radius: int = 2) -> Tensor:
    """CenterPoint's centre heatmaps: one Gaussian per object on its class channel, combined by elementwise max.

    For each object (a row whose class id is not 0), on a map of ``H = ny // stride`` by ``W = nx // stride``
    cells of ``vx * stride`` by ``vy * stride`` metres:

    * centre cell ``(cx, cy) = (floor((x - x0) / (vx stride)), floor((y - y0) / (vy stride)))``; objects whose
      centre cell lies outside the map are skipped (CenterPoint truncates with ``int()`` instead, which also keeps
      centres up to one cell left of or below the map in column or row 0; here they are skipped);
    * ``r = max(min_radius, int(gaussian_radius(dx / (vx stride), dy / (vy stride), min_overlap)))``;
    * ``exp(-(ox^2 + oy^2) / (2 sigma^2))`` with ``sigma = (2 r + 1) / 6`` at every offset ``|ox|, |oy| <= r``
      around the centre cell that falls on the map (the window is clipped at the map's edges), combined with the
      map by elementwise max (``draw_umich_gaussian``). The centre cell gets exactly 1.

    Unlike CenterPoint, objects of size 0 are drawn (with ``min_radius``): a labelled object counts. Positions,
    radii and Gaussians are computed in float64 and rounded once to the output dtype, so CPU and CUDA agree
    exactly. All objects are drawn at once (a window per object, one ``scatter_reduce(amax)``); objects with very
    different radii are drawn in chunks when the windows would exceed ``2^22`` entries.

    Args:
        boxes (Tensor[B, M, 8]): x, y, z, dx, dy, dz, heading, class id (1-based; 0 marks a padding row, whose other
            values are ignored), LiDAR frame, metres; any real dtype.
        num_classes (int): channels C; class ids lie in [0, C].
        point_cloud_range (sequence of 6 floats): x0, y0, z0, x1, y1, z1 (only x0, y0 are used).
        voxel_size (sequence of 2 or 3 floats > 0): vx, vy[, vz].
        grid_size (sequence of 2 or 3 ints >= 1): nx, ny[, nz] of the voxel grid.
        stride (int >= 1): the heatmap's cells per voxel along each axis (CenterPoint's ``out_size_factor``).
        min_overlap (float): :func:`gaussian_radius`'s, in (0, 1).
        min_radius (int >= 0): the smallest radius in cells.

    Returns:
        Tensor[B, C, H, W]: the heatmap, in ``boxes``' dtype if floating, else float32; on ``boxes``' device.

    Raises:
        ValueError: naming the bad argument; with the value checks on, a non-padding row with a class id that is
            not an integer in [1, C], a NaN or infinite value, or a negative dx or dy.
    """
    _real_tensor(boxes, "boxes")
    if boxes.dim() != 3 or boxes.shape[-1] != 8:
        raise ValueError(f"boxes must be (B, M, 8): x, y, z, dx, dy, dz, heading, class id; got {describe(boxes)}")
    C = positive_int(num_classes, "num_classes")
    pcr = _floats(point_cloud_range, "point_cloud_range", (6,))
    vs = _floats(voxel_size, "voxel_size", (2, 3), positive=True)
    grid = _ints(grid_size, "grid_size", (2, 3))
    s = positive_int(stride, "stride")
    o = real(min_overlap, "min_overlap", 0, 1, lo_open=True, hi_open=True)
    min_r = integer(min_radius, "min_radius", lo=0)
    B, M = boxes.shape[0], boxes.shape[1]
    H, W = grid[1] // s, grid[0] // s
    dtype = boxes.dtype if boxes.is_floating_point() else torch.float32
    out = torch.zeros(B * C * H * W + 1, dtype=dtype, device=boxes.device)  # + 1: where clipped cells go
    if B * M == 0 or boxes.device.type == "meta":
        return out[:-1].reshape(B, C, H, W)
    b64 = boxes.detach().to(torch.float64)
    cls = b64[..., 7]
    real_row = cls != 0
    class_ok = (cls == cls.round()) & (cls >= 1) & (cls <= C)
    if value_checks_enabled():
        bad_class = real_row & ~class_ok
        bad_value = real_row & ~torch.isfinite(b64).all(-1)
        bad_size = real_row & ~((b64[..., 3] >= 0) & (b64[..., 4] >= 0))
        run_value_checks([
            (bad_class.any(), lambda: f"boxes: class ids (column 7) must be integers in [1, {C}] (0 for padding "
                                      f"rows), got {_first_bad(cls, bad_class)} ({describe(boxes)})"),
            (bad_value.any(), lambda: f"boxes must be finite in every non-padding row, got a row "
                                      f"{_first_row(b64, bad_value)} ({describe(boxes)})"),
            (bad_size.any(), lambda: f"boxes must have dx, dy >= 0, got a row {_first_row(b64, bad_size)} "
                                     f"({describe(boxes)})")])
    if H * W == 0:
        return out[:-1].reshape(B, C, H, W)
    cell_x, cell_y = vs[0] * s, vs[1] * s
    cx = torch.floor(_div(b64[..., 0] - pcr[0], cell_x))
    cy = torch.floor(_div(b64[..., 1] - pcr[1], cell_y))
    drawn = real_row & class_ok & (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
    sel = drawn.reshape(-1).nonzero().squeeze(1)
    if sel.numel() == 0:
        return out[:-1].reshape(B, C, H, W)
    flat = b64.reshape(-1, 8)[sel]
    frame = sel // M
    channel = cls.reshape(-1)[sel].long() - 1
    cx, cy = cx.reshape(-1)[sel].long(), cy.reshape(-1)[sel].long()
    size_x = torch.nan_to_num(_div(flat[:, 3].clamp(min=0), cell_x), nan=0.0)
    size_y = torch.nan_to_num(_div(flat[:, 4].clamp(min=0), cell_y), nan=0.0)
    radius = torch.nan_to_num(_gaussian_radius(size_x, size_y, o), nan=math.inf)  # inf - inf in r3: a huge box
    r = torch.floor(radius).clamp(min=min_r, max=2.0**40).long()
    base = (frame * C + channel) * H
    # beyond max(H, W) - 1 cells every offset is off the map: the window stops there, sigma keeps the true r
    reach = max(H, W) - 1
    for part in _radius_chunks(r, reach):
        k = min(int(r[part].max()), reach)
        _draw_gaussians(out, base[part], cx[part], cy[part], r[part], k, H, W)
    return out[:-1].reshape(B, C, H, W)


def _first_bad(values: Tensor, bad: Tensor) -> str:
    return repr(values[bad][0].item())


def _first_row(rows: Tensor, bad: Tensor) -> str:
    return str([round(v, 6) for v in rows[bad][0].tolist()])


def _radius_chunks(r: Tensor, reach: int) -> list:
    """Index tensors of the objects to draw together: all at once when their windows fit the budget, else chunks
    of similar radius (sorted; one read of the radii to the host)."""
    k = min(int(r.max()), reach)
    if r.numel() * (2 * k + 1) ** 2 <= _WINDOW_BUDGET:
        return [torch.arange(r.numel(), device=r.device)]
    order = torch.argsort(r)
    sizes = [(2 * min(v, reach) + 1) ** 2 for v in r[order].tolist()]
    chunks, start = [], 0
    while start < len(sizes):
        end = start + 1
        while end < len(sizes) and (end + 1 - start) * sizes[end] <= _WINDOW_BUDGET:
            end += 1
        chunks.append(order[start:end])
        start = end
    return chunks


def _draw_gaussians(out: Tensor, base: Tensor, cx: Tensor, cy: Tensor, r: Tensor, k: int, H: int, W: int) -> None:
    """Max the (2k+1)^2 windows (masked to each object's own r) into ``out`` (flat, its last entry a sink)."""
    offsets = torch.arange(-k, k + 1, device=out.device)
    oy, ox = offsets.view(1, -1, 1), offsets.view(1, 1, -1)
    sigma = _div((2 * r + 1).to(torch.float64), 6)
    gauss = torch.exp(-(ox * ox + oy * oy).to(torch.float64) / (2 * sigma * sigma).view(-1, 1, 1))
    x, y = cx.view(-1, 1, 1) + ox, cy.view(-1, 1, 1) + oy
    rr = r.view(-1, 1, 1)
    inside = (ox.abs() <= rr) & (oy.abs() <= rr) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    index = torch.where(inside, (base.view(-1, 1, 1) + y) * W + x, out.numel() - 1)
    values = torch.where(inside, gauss, 0.0).to(out.dtype)
    out.scatter_reduce_(0, index.reshape(-1), values.reshape(-1), "amax", include_self=True)


def focal_loss(pred: Tensor, target: Tensor, eps: float = 1e-4) -> Tensor:
    """CenterNet's focal loss (alpha = 2, beta = 4) on predicted probabilities, normalised by the positives.

    With ``p = clamp(pred, eps, 1 - eps)`` (zero gradient where the clamp bites, as CenterPoint's
    ``clamp(sigmoid(x), 1e-4, 1 - 1e-4)``)::

        loss = -( sum_{target == 1} (1 - p)^2 log p  +  sum_{target < 1} (1 - target)^4 p^2 log(1 - p) )
               / max(1, #{target == 1})

    summed over the whole batch (CenterNet's ``_neg_loss``: ``target < 1`` marks the negatives, so a target above
    1, which a heatmap never holds, counts in neither sum).

    Args:
        pred (Tensor[B, C, H, W]): probabilities (after the sigmoid), floating.
        target (Tensor[B, C, H, W]): the heatmap of :func:`heatmap_targets`, values in [0, 1], any real dtype,
            same device.
        eps (float): the clamp, in (0, 0.5).

    Returns:
        Tensor[]: the loss, float64 for float64 ``pred``, else float32 (half inputs are computed in float32, where
        ``1 - 1e-4`` is not 1).

    Raises:
        ValueError: naming ``pred``, ``target`` or ``eps``.
    """
    _check_heatmap(pred, "pred")
    _real_tensor(target, "target")
    if target.shape != pred.shape:
        raise ValueError(f"target must have pred's shape {tuple(pred.shape)}, got {describe(target)}")
    _same_device(pred, "pred", target, "target")
    e = real(eps, "eps", 0, 0.5, lo_open=True, hi_open=True)
    ct = _compute_dtype(pred.dtype)
    p = pred.to(ct).clamp(e, 1 - e)
    t = target.to(ct)
    pos, neg = t == 1, t < 1
    zero = p.new_zeros(())
    pos_loss = torch.where(pos, torch.log(p) * (1 - p) ** 2, zero).sum()
    neg_loss = torch.where(neg, torch.log(1 - p) * p ** 2 * (1 - t) ** 4, zero).sum()
    num_pos = pos.sum().clamp(min=1).to(ct)
    return -(pos_loss + neg_loss) / num_pos


# ---------------------------------------------------------------------------------------------- peaks
def _local_max(heatmap: Tensor, radius: int) -> Tensor:
    """The max-pool mask: cells equal to the maximum of their window (bool, no gradient)."""
    h = heatmap.detach()
    if h.numel() == 0:
        return torch.zeros(h.shape, dtype=torch.bool, device=h.device)
    r = min(radius, max(h.shape[2], h.shape[3]) - 1)  # a larger window covers nothing more
    if r == 0:
        return h == h  # NaN is no peak
    return h == F.max_pool2d(h, 2 * r + 1, stride=1, padding=r)


def find_peaks(heatmap: Tensor, threshold, radius: int = 2) -> Tensor:
    """Peaks of a heatmap: cells that equal the maximum of their ``(2r+1) x (2r+1)`` window and reach the threshold.

    The window is the max-pool of CenterNet's decoder (``max_pool2d(kernel 2r+1, stride 1, padding r)``): at the
    map's edges it is clipped, so border cells can be peaks. On a map without ties these are the peaks of
    ``skimage.feature.peak_local_max(image, min_distance=r, threshold_abs=threshold, exclude_border=False)`` per
    channel (which keeps ``image > threshold``: the two differ only on cells exactly at the threshold).

    Plateaus: every cell of a flat maximum is a peak (each equals its window's maximum), so a flat top of n cells
    counts n times, and a constant map is all peaks where it reaches the threshold (``peak_local_max`` returns no
    peak for a constant image, and thins plateaus by distance). Heatmaps out of a sigmoid have no exact plateaus
    at their maxima in practice; a threshold above the background keeps flat backgrounds out. NaN cells are never
    peaks, and (max-pool propagates NaN) neither is any cell whose window holds a NaN.

    Args:
        heatmap (Tensor[B, C, H, W]): floating.
        threshold (float or Tensor): the smallest peak value (``>=``): a number (not NaN; compared exactly, not
            first rounded to the heatmap's dtype), or a real tensor on the heatmap's device broadcastable to
            (B, C, H, W): (B, C, 1, 1) per frame and class, (B, C, H, W) per cell (e.g. each partition's own
            threshold painted on its cells).
        radius (int >= 0): the window's half-size r; 0 makes every cell reaching the threshold a peak.

    Returns:
        Tensor[B, C, H, W] bool.

    Raises:
        ValueError: naming ``heatmap``, ``threshold`` or ``radius``.
    """
    _check_heatmap(heatmap)
    r = _radius(radius)
    thr = _threshold(threshold, heatmap)
    return _local_max(heatmap, r) & _at_least(heatmap.detach(), thr)


def _at_least(h: Tensor, thr) -> Tensor:
    """``h >= thr`` exactly: torch rounds a Python number to the tensor's dtype first (1e-96 would become 0 in
    float32 and a cell of 0 would pass), so the number is rounded up to the next value of that dtype instead."""
    if not isinstance(thr, float):
        return h >= thr  # tensors promote to the wider dtype: exact
    if h.dtype not in (torch.float32, torch.float64):
        h = h.float()
    npd = np.float64 if h.dtype == torch.float64 else np.float32
    with np.errstate(over="ignore"):
        t = npd(thr)
    if float(t) < thr:
        t = np.nextafter(t, npd(math.inf))
    return h >= float(t)


def count_peaks(heatmap: Tensor, threshold, radius: int = 2) -> Tensor:
    """The number of :func:`find_peaks` per frame and class.

    Args: as :func:`find_peaks`.

    Returns:
        Tensor[B, C] int64.
    """
    return find_peaks(heatmap, threshold, radius).sum(dim=(2, 3))


def peak_centres(heatmap: Tensor, peaks: Tensor, point_cloud_range, voxel_size, stride: int) -> list:
    """The peaks as metric centres, frame by frame: ``[x, y, class, score]`` per peak.

    Cell ``(row i, column j)`` of the map has its centre at ``x = (j + 0.5) * vx * stride + x0``,
    ``y = (i + 0.5) * vy * stride + y0`` (computed in float64); the class is the channel (0-based); the score is
    the heatmap's value there (the gradient flows to it). One ``nonzero`` over the whole batch, then a split by
    frame (one read of the per-frame counts to the host).

    Args:
        heatmap (Tensor[B, C, H, W]): floating.
        peaks (Tensor[B, C, H, W] bool): e.g. :func:`find_peaks`' mask; same device.
        point_cloud_range (sequence of 6 floats): x0, y0, ... (only x0, y0 are used).
        voxel_size (sequence of 2 or 3 floats > 0): vx, vy[, vz].
        stride (int >= 1): heatmap cells per voxel, as in :func:`heatmap_targets`.

    Returns:
        list of B Tensor[K_b, 4]: x, y (metres), class (0-based), score; rows in the order class, row, column;
        float64 for a float64 heatmap, else float32.

    Raises:
        ValueError: naming the bad argument.
    """
    _check_heatmap(heatmap)
    check_tensor(peaks, "peaks")
    if peaks.dtype != torch.bool or peaks.shape != heatmap.shape:
        raise ValueError(f"peaks must be a bool tensor of the heatmap's shape {tuple(heatmap.shape)}, got "
                         f"{describe(peaks)}")
    _same_device(heatmap, "heatmap", peaks, "peaks")
    pcr = _floats(point_cloud_range, "point_cloud_range", (6,))
    vs = _floats(voxel_size, "voxel_size", (2, 3), positive=True)
    s = positive_int(stride, "stride")
    B = heatmap.shape[0]
    ct = _compute_dtype(heatmap.dtype)
    where = peaks.nonzero()  # (K, 4): frame, class, row, column
    score = heatmap[peaks].to(ct)
    ij = where[:, 2:].to(torch.float64)
    x = (ij[:, 1] + 0.5) * vs[0] * s + pcr[0]
    y = (ij[:, 0] + 0.5) * vs[1] * s + pcr[1]
    centres = torch.stack([x.to(ct), y.to(ct), where[:, 1].to(ct), score], dim=1)
    counts = torch.bincount(where[:, 0], minlength=B).tolist() if B else []
    return list(torch.split(centres, counts)) if B else []


def soft_count(heatmap: Tensor, threshold: float = 0.5, radius: int = 2, temperature: float = 0.05) -> Tensor:
    """A differentiable stand-in for :func:`count_peaks`: ``sum over local maxima of sigmoid((p - t) / T)``.

    The local maxima are :func:`find_peaks`' max-pool mask (without the threshold), computed without gradient;
    the gradient flows through ``p`` at those cells only (zero elsewhere). A peak well above the threshold adds
    about 1, one well below about 0, so on a sharp map this is close to ``count_peaks(heatmap, threshold,
    radius)``. Every cell of a flat region is a local maximum (see :func:`find_peaks`), so a flat background of
    value b adds ``sigmoid((b - t) / T)`` per cell: keep T small against ``t - b`` (at b = 0.01, t = 0.5,
    T = 0.05 that is 5.6e-5 per cell).

    Args:
        heatmap (Tensor[B, C, H, W]): probabilities, floating.
        threshold (float or Tensor): as :func:`find_peaks`' (a tensor broadcastable to the heatmap works too).
        radius (int >= 0): the window's half-size.
        temperature (float > 0): the sigmoid's T.

    Returns:
        Tensor[B, C] in the heatmap's dtype.

    Raises:
        ValueError: naming ``heatmap``, ``threshold``, ``radius`` or ``temperature``.
    """
    _check_heatmap(heatmap)
    r = _radius(radius)
    thr = _threshold(threshold, heatmap)
    T = real(temperature, "temperature", 0, lo_open=True)
    if isinstance(thr, Tensor):
        thr = thr.to(heatmap.dtype)  # the result keeps the heatmap's dtype
    mask = _local_max(heatmap, r)
    soft = torch.sigmoid((heatmap - thr) / T)
    return torch.where(mask, soft, soft.new_zeros(())).sum(dim=(2, 3))


# ---------------------------------------------------------------------------------------------- Otsu
def otsu_threshold(values: Tensor, bins: int = 256, mask: Tensor | None = None, *, exact: bool = True) -> Tensor:
    """Otsu's threshold of each row (the last axis), batched over the leading axes, as
    ``skimage.filters.threshold_otsu(row, nbins=bins)`` computes it.

    Per row, over its selected entries: a row whose entries all equal one value returns that value (skimage's
    constant-image rule); otherwise the histogram is NumPy's (``bins`` equal bins over [min, max], edges from
    ``linspace`` in the values' dtype, the last bin closed, NumPy's index corrections at the edges), and the
    threshold is the bin centre ``(e_k + e_{k+1}) / 2`` (values' dtype) maximising the between-class variance
    ``w1(k) w2(k+1) (m1(k) - m2(k+1))^2`` over the splits k = 0 .. bins - 2, first maximum on ties.

    Rounding of the variance (``exact``):

    * ``True`` (default): skimage's arithmetic step for step (float32 counts and weights, running sums accumulated
      one bin at a time in the values' dtype, the same operation order): bit for bit skimage's threshold, on CPU
      and CUDA, at the cost of one round trip of the (rows, bins) sums to the host (NumPy's ``cumsum``).
    * ``False`` (one scan per sum: faster on CUDA): the variance in float64, each run of equal splits (an empty
      bin repeats the previous split) represented by its first, as skimage's sequential sums do. Where two
      different splits tie to within skimage's rounding (exact ties of symmetric or lattice-valued rows, or a
      relative 1e-7 with float32 sums), the two may pick different ones, possibly many bins apart (equally good
      by Otsu's criterion); elsewhere the result is skimage's (about 0.2% of small random rows differ).

    Args:
        values (Tensor[..., N]): floating (float16/bfloat16 computed as float32).
        bins (int >= 2): histogram bins.
        mask (Tensor[..., N] bool, optional): the entries that count (default all); same shape and device.
        exact (bool): see above.

    Returns:
        Tensor[...]: the thresholds, float64 for float64 values, else float32. A constant row returns its value
        (infinities too, as skimage). NaN for a row with no selected entry (N = 0 or an all-False mask row), with
        a NaN selected entry, or (not constant) with an infinite entry, a range max - min that overflows the
        dtype, or a range too narrow for ``bins`` distinct edges in the dtype (a few ulp): skimage raises for all
        of these but the first (NumPy's histogram refuses them). Where skimage's bin centre overflows to inf
        (edges near the dtype's largest value) the centre is ``e_k / 2 + e_{k+1} / 2`` instead.

    Raises:
        ValueError: naming ``values``, ``bins``, ``mask`` or ``exact``.
    """
    check_tensor(values, "values")
    if values.dim() < 1 or not values.is_floating_point():
        raise ValueError(f"values must be a floating tensor with at least one axis (..., N), got {describe(values)}")
    n_bins = integer(bins, "bins", lo=2)
    if mask is not None:
        check_tensor(mask, "mask")
        if mask.dtype != torch.bool or mask.shape != values.shape:
            raise ValueError(f"mask must be a bool tensor of values' shape {tuple(values.shape)}, got "
                             f"{describe(mask)}")
        _same_device(values, "values", mask, "mask")
    if not isinstance(exact, (bool, np.bool_)):
        raise ValueError(f"exact must be True or False, got {exact!r}")
    lead, N = values.shape[:-1], values.shape[-1]
    ct = _compute_dtype(values.dtype)
    if values.numel() == 0:  # no rows, or rows with no entry (NaN)
        return torch.full(lead, math.nan, dtype=ct, device=values.device)
    v = values.detach().to(ct).reshape(-1, N)
    R = v.shape[0]
    m = torch.ones_like(v, dtype=torch.bool) if mask is None else mask.reshape(-1, N)
    inf = torch.full((), math.inf, dtype=ct, device=v.device)
    vmin = torch.where(m, v, inf).amin(1)
    vmax = torch.where(m, v, -inf).amax(1)
    has_nan = (m & torch.isnan(v)).any(1)
    const = (vmin == vmax) & ~has_nan  # skimage's first test: every entry equals the first (inf too)
    # no entry; NaN; else (not constant) an infinite entry or a range max - min beyond the dtype
    bad = ~m.any(1) | has_nan | (~const & ~torch.isfinite(vmax - vmin))
    usable = ~bad & ~const
    lo = torch.where(usable, vmin, 0)
    hi = torch.where(usable, vmax, 1)
    edges = _linspace_rows(lo, hi, n_bins)  # (R, bins + 1)
    # NumPy refuses bins that rounding leaves empty ("Too many bins for data range"): those rows are NaN too
    bad = bad | (usable & (edges[:, :-1] >= edges[:, 1:]).any(1))
    x = torch.where(m & usable[:, None], v, lo[:, None])
    index = _numpy_bin_index(x, lo, hi, edges, n_bins)
    counts = torch.zeros(R, n_bins, dtype=torch.float64, device=v.device)
    counts.scatter_add_(1, index, (m & usable[:, None]).to(torch.float64))
    centres = _bin_centres(edges)
    between = _between_exact(counts, centres) if exact else _between_fast(counts, centres)
    best = between.argmax(1, keepdim=True)
    out = centres.gather(1, best).squeeze(1)
    out = torch.where(const, vmin, out)
    out = torch.where(bad, torch.full_like(out, math.nan), out)
    return out.reshape(lead)


def _bin_centres(edges: Tensor) -> Tensor:
    """``(e_k + e_{k+1}) / 2`` as skimage computes it; where that sum overflows (edges near the dtype's largest
    value, where skimage's centre is inf), ``e_k / 2 + e_{k+1} / 2``, so the threshold stays within the row."""
    centres = (edges[:, :-1] + edges[:, 1:]) / 2.0
    halves = edges[:, :-1] / 2.0 + edges[:, 1:] / 2.0
    return torch.where(torch.isfinite(centres), centres, halves)


def _between_fast(counts: Tensor, centres: Tensor) -> Tensor:
    """The between-class variance of each split in float64, scans; a split after an empty bin (the same
    partition as the split before it) gets -inf, so the first of each run of equal splits wins as in skimage."""
    c64 = centres.to(torch.float64)
    w1 = counts.cumsum(1)
    w2 = counts.flip(1).cumsum(1).flip(1)
    s1 = (counts * c64).cumsum(1)
    s2 = (counts * c64).flip(1).cumsum(1).flip(1)
    between = w1[:, :-1] * w2[:, 1:] * (s1[:, :-1] / w1[:, :-1] - s2[:, 1:] / w2[:, 1:]) ** 2
    first_of_run = torch.ones_like(between, dtype=torch.bool)
    first_of_run[:, 1:] = counts[:, 1:-1] > 0
    return torch.where(first_of_run & ~torch.isnan(between), between, -math.inf)


def _between_exact(counts: Tensor, centres: Tensor) -> Tensor:
    """skimage's ``threshold_otsu`` arithmetic: float32 counts, ``np.cumsum`` (one rounding per bin, in order),
    ``counts * bin_centers`` in the centres' dtype, ``weight1[:-1] * weight2[1:]`` in float32."""
    c32 = counts.to(torch.float32)
    weighted = c32.to(centres.dtype) * centres
    if centres.dtype == torch.float32:  # one loop for the four sums
        w1, w2, s1, s2 = _running_sums(torch.stack([c32, c32.flip(1), weighted, weighted.flip(1)]))
    else:
        w1, w2 = _running_sums(torch.stack([c32, c32.flip(1)]))
        s1, s2 = _running_sums(torch.stack([weighted, weighted.flip(1)]))
    w2, s2 = w2.flip(1), s2.flip(1)
    mean1 = s1 / w1.to(centres.dtype)
    mean2 = s2 / w2.to(centres.dtype)  # NumPy: cumsum of the reversed / reversed weight2, then reversed
    return (w1[:, :-1] * w2[:, 1:]).to(centres.dtype) * (mean1[:, :-1] - mean2[:, 1:]) ** 2


def _running_sums(x: Tensor) -> Tensor:
    """``numpy.cumsum`` along the last axis in ``x``'s dtype: one addition (one rounding) per step, in order
    (``torch.cumsum`` accumulates float32 in float64 on the CPU and scans in a tree on CUDA). NumPy's own, on the
    host: the sums are small (rows x bins), and a loop of one launch per bin cost CUDA ~3 ms per call."""
    return torch.from_numpy(np.cumsum(x.detach().cpu().numpy(), axis=-1)).to(x.device)


def _linspace_rows(lo: Tensor, hi: Tensor, n_bins: int) -> Tensor:
    """``numpy.linspace(lo, hi, n_bins + 1)`` per row, in the rows' dtype (NumPy's step, its special case for a
    step that underflows to 0, and the exact last edge)."""
    k = torch.arange(n_bins + 1, dtype=lo.dtype, device=lo.device)
    delta = (hi - lo)[:, None]
    step = _div(delta, n_bins)
    y = torch.where(step == 0, _div(k, n_bins) * delta, k * step) + lo[:, None]
    y[:, -1] = hi
    return y


def _numpy_bin_index(x: Tensor, lo: Tensor, hi: Tensor, edges: Tensor, n_bins: int) -> Tensor:
    """``numpy.histogram``'s bin of each value for equal bins over [lo, hi] (its float index, then its corrections
    against the edges; the last bin is closed)."""
    f = ((x - lo[:, None]) / (hi - lo)[:, None]) * n_bins
    index = torch.nan_to_num(f, nan=0.0).clamp(0, n_bins).to(torch.int64)
    index = torch.where(index == n_bins, n_bins - 1, index)
    index = index - (x < edges.gather(1, index)).long()
    index = index.clamp(0, n_bins - 1)
    index = index + ((x >= edges.gather(1, index + 1)) & (index != n_bins - 1)).long()
    return index


# ---------------------------------------------------------------------------------------------- partitions
def _grow(delta: float, size: int) -> int:
    # rounded to 9 decimals first: 0.1 * 30 is 3.0000000000000004 in floating point, and 3 cells are meant
    return math.ceil(round(delta * size, 9))


def partition_boxes(height: int, width: int, pt: int, delta: float = 0.0, *, device=None) -> Tensor:
    """The seed's partitions of an H x W map: ``pt`` even regions, each grown by ``delta`` of its own size.

    ``pt`` = 1: the whole map; 2: two halves along x (the driving direction: the width is split); 4: 2 x 2;
    9: 3 x 3. Region boundaries along an axis of n cells split into k parts lie at ``floor(i n / k)``; each region
    of h x w cells then grows by ``ceil(delta * h)`` rows above and below and ``ceil(delta * w)`` columns left and
    right (``delta * size`` rounded to 9 decimals first, so 0.1 * 30 is 3 cells), clipped to the map.

    Args:
        height, width (int >= 1): the map's H and W (at least the grid's rows and columns: no empty region).
        pt (int): 1, 2, 4 or 9 (:data:`PARTITIONS`).
        delta (float >= 0): the overlap, a fraction of the region's size on every side.
        device: where the result goes (default CPU).

    Returns:
        Tensor[pt, 4] int64: ``[y0, y1, x0, x1]`` per region, half-open (rows ``y0 <= i < y1``), row-major order
        (top-left region first, then along x).

    Raises:
        ValueError: naming ``height``, ``width``, ``pt`` or ``delta``.
    """
    H = positive_int(height, "height")
    W = positive_int(width, "width")
    if isinstance(pt, (bool, np.bool_)) or not isinstance(pt, numbers.Integral) or int(pt) not in PARTITIONS:
        raise ValueError(f"pt must be one of {sorted(PARTITIONS)}, got {pt!r}")
    d = min(real(delta, "delta", lo=0), float(max(H, W)))  # more grows past the map's far edge: the same result
    rows, cols = PARTITIONS[int(pt)]
    if H < rows:
        raise ValueError(f"height must be at least {rows} for pt={pt} (one row per region), got {H}")
    if W < cols:
        raise ValueError(f"width must be at least {cols} for pt={pt} (one column per region), got {W}")
    ys = [i * H // rows for i in range(rows + 1)]
    xs = [j * W // cols for j in range(cols + 1)]
    regions = []
    for i in range(rows):
        gy = _grow(d, ys[i + 1] - ys[i])
        for j in range(cols):
            gx = _grow(d, xs[j + 1] - xs[j])
            regions.append([max(0, ys[i] - gy), min(H, ys[i + 1] + gy), max(0, xs[j] - gx), min(W, xs[j + 1] + gx)])
    return torch.tensor(regions, dtype=torch.int64, device=device)


def merge_centres(centres: Tensor, radius: float) -> Tensor:
    """The seed's Algorithm 1: merge the centres of one frame found in several overlapping partitions.

    Greedy by decreasing score (equal scores: lower row first): a centre is dropped when a centre already kept, of
    the same class, lies within ``radius`` (Euclidean distance in x, y, ``hypot(dx, dy) <= radius``, in float64).
    Dropped centres suppress nothing, so for a chain a - b - c where a-b and b-c are within the radius and a-c is
    not, scores a > b > c keep a and c; a > c > b keeps a and c; b above both keeps b alone.

    Cost: the K x K conflict matrix is built on the centres' device in blocks of 1024 rows (O(K^2) time, K^2 bytes
    on the host), then scanned on the CPU over the centres that have a conflict (a loop over those only; fine for
    K up to a few thousand).

    Args:
        centres (Tensor[K, 4]): x, y, class, score (e.g. :func:`peak_centres`' rows from several regions),
            floating.
        radius (float >= 0): metres.

    Returns:
        Tensor[K', 4]: the kept rows, by decreasing score; same dtype and device.

    Raises:
        ValueError: naming ``centres`` or ``radius``; with the value checks on, a NaN or infinite value.
    """
    _floating(centres, "centres")
    if centres.dim() != 2 or centres.shape[1] != 4:
        raise ValueError(f"centres must be (K, 4): x, y, class, score; got {describe(centres)}")
    rad = real(radius, "radius", lo=0)
    K = centres.shape[0]
    if K == 0 or centres.device.type == "meta":
        return centres
    if value_checks_enabled():
        run_value_checks([(~torch.isfinite(centres).all(),
                           lambda: f"centres must be finite, got {describe(centres)} with "
                                   f"{int((~torch.isfinite(centres)).sum())} NaN or infinite values")])
    order = torch.sort(centres[:, 3].detach(), descending=True, stable=True).indices
    c = centres[order]
    xy = c[:, :2].detach().to(torch.float64)
    cls = c[:, 2].detach()
    later = torch.arange(K, device=c.device)
    blocks = []
    for start in range(0, K, _MERGE_ROWS):
        stop = min(K, start + _MERGE_ROWS)
        d = torch.hypot(xy[start:stop, None, 0] - xy[None, :, 0], xy[start:stop, None, 1] - xy[None, :, 1])
        blocks.append((d <= rad) & (cls[start:stop, None] == cls[None, :])
                      & (later[None, :] > later[start:stop, None]))
    conflict = torch.cat(blocks).cpu().numpy()
    keep = _greedy_scan(conflict)
    return c[torch.from_numpy(keep).to(c.device)]


def _greedy_scan(conflict: np.ndarray) -> np.ndarray:
    """Greedy over an upper-triangular conflict matrix (row i suppresses the later j it conflicts with) when i is
    itself kept; only the rows with a conflict are visited."""
    keep = np.ones(conflict.shape[0], dtype=bool)
    for i in np.flatnonzero(conflict.any(1)):
        if keep[i]:
            keep[i + 1:] &= ~conflict[i, i + 1:]
    return keep


def partition_weights(region_counts: Tensor) -> Tensor:
    """The seed's region weights ``w_i = 1 / |R| + |r_i.objs| / sum_r |r.objs|``.

    Args:
        region_counts (Tensor[B, P]): objects per region (P >= 1), any real dtype (soft counts too).

    Returns:
        Tensor[B, P]: ``1 / P + region_counts / max(1, sum over regions)``, in the counts' dtype if floating, else
        float32. Rows sum to 2 when their count is at least 1, to 1 when it is 0.

    Raises:
        ValueError: naming ``region_counts``.
    """
    _real_tensor(region_counts, "region_counts")
    if region_counts.dim() != 2 or region_counts.shape[1] == 0:
        raise ValueError(f"region_counts must be (B, P) with P >= 1, got {describe(region_counts)}")
    dt = region_counts.dtype if region_counts.is_floating_point() else torch.float32
    c = region_counts.to(dt)
    total = c.sum(1, keepdim=True).clamp(min=1)
    return 1.0 / region_counts.shape[1] + c / total


# ---------------------------------------------------------------------------------------------- model selection
class ChernoffSelector:
    """The seed's per-frame model selection: the model whose frames' centre is nearest, scaled by a Chernoff
    bound on how well that centre is known.

    ``fit`` summarises, for each model m, the frames it counts best: ``n_m`` frames, their centre ``omega_m``
    (the mean feature), and ``xi_m^2``, the mean over them of ``||f - omega_m||^2`` (the trace of their covariance:
    how the vector variance enters the scalar bound). The Chernoff factor is
    ``P_m = exp(-n_m epsilon^2 / (2 xi_m^2))``: small when many, tight frames pin the centre down.
    ``select`` picks ``argmin_m ||f - omega_m|| P_m`` (computed as ``log ||f - omega_m|| + log P_m``, the same
    order without underflow; equal scores: the lower model).

    Decisions where the bound says nothing:

    * a model with no frames (n_m = 0) is never chosen (its score is +inf);
    * a model whose frames are all one point (one frame, or identical frames) has xi_m = 0, where the bound
      would give P_m = 0 and that model would win every frame; its factor is taken as P_m = 1 instead (no
      spread measured, no confidence claimed), so it wins by distance alone. Identical frames are detected
      exactly (compared with the model's first frame), not by a variance that rounding leaves at 1e-34.

    The state is plain tensors (:meth:`state_dict`, :meth:`from_state`).
    """

    def __init__(self) -> None:
        self.centres: Tensor | None = None  # (M, D)
        self.variances: Tensor | None = None  # (M,)
        self.counts: Tensor | None = None  # (M,) int64
        self.epsilon: float | None = None

    # -- fitting
    def fit(self, features: Tensor, best: Tensor, num_models: int, epsilon: float) -> "ChernoffSelector":
        """Summarise each model's frames.

        Args:
            features (Tensor[F, D]): one feature vector per frame (F, D >= 1), floating, finite.
            best (Tensor[F] integer): the model that counts each frame best, in [0, num_models); same device.
            num_models (int >= 1): M.
            epsilon (float > 0): the bound's epsilon, in the features' units.

        Returns:
            self.

        Raises:
            ValueError: naming ``features``, ``best``, ``num_models`` or ``epsilon``.
        """
        _floating(features, "features", 2, "(F, D) per-frame features")
        if features.shape[0] == 0 or features.shape[1] == 0:
            raise ValueError(f"features must hold at least one frame and one dimension, got {describe(features)}")
        check_tensor(best, "best")
        if best.dim() != 1 or best.shape[0] != features.shape[0] or best.is_floating_point() \
                or best.is_complex() or best.dtype == torch.bool:
            raise ValueError(f"best must be an integer (F,) tensor with F = {features.shape[0]}, got {describe(best)}")
        _same_device(features, "features", best, "best")
        M = positive_int(num_models, "num_models")
        eps = real(epsilon, "epsilon", 0, lo_open=True)
        best = best.long()
        run_value_checks([((best < 0).any() | (best >= M).any(),
                           lambda: f"best must lie in [0, {M}), got values in [{int(best.min())}, {int(best.max())}]"),
                          (~torch.isfinite(features).all(), lambda: f"features must be finite ({describe(features)})")])
        f = features.detach()
        D = f.shape[1]
        counts = torch.bincount(best, minlength=M)
        n = counts.clamp(min=1).to(f.dtype)
        centres = torch.zeros(M, D, dtype=f.dtype, device=f.device).index_add_(0, best, f) / n[:, None]
        # frames all equal to their model's first frame: an exact centre and no spread
        frame = torch.arange(f.shape[0], device=f.device)
        first = torch.full((M,), f.shape[0], device=f.device).scatter_reduce(0, best, frame, "amin")
        same = (f == f[first.clamp(max=f.shape[0] - 1)[best]]).all(1)
        single = torch.ones(M, dtype=torch.int64, device=f.device).scatter_reduce(0, best, same.long(), "amin") == 1
        has = counts > 0
        centres = torch.where((single & has)[:, None], f[first.clamp(max=f.shape[0] - 1)], centres)
        sq = (f - centres[best]).square().sum(1)
        variances = torch.zeros(M, dtype=f.dtype, device=f.device).index_add_(0, best, sq) / n
        self.centres = centres
        self.variances = torch.where(single, torch.zeros_like(variances), variances)
        self.counts = counts
        self.epsilon = eps
        return self

    def _fitted(self) -> None:
        if self.centres is None:
            raise ValueError("ChernoffSelector is not fitted: call fit(features, best, num_models, epsilon) or "
                             "ChernoffSelector.from_state(state) first")

    @property
    def log_factors(self) -> Tensor:
        """(M,): ``log P_m = -n_m epsilon^2 / (2 xi_m^2)``; 0 where xi_m = 0 or n_m = 0."""
        self._fitted()
        n = self.counts.to(self.variances.dtype)
        spread = self.variances > 0
        safe = torch.where(spread, self.variances, torch.ones_like(self.variances))
        return torch.where(spread, -n * self.epsilon ** 2 / (2 * safe), torch.zeros_like(safe))

    @property
    def factors(self) -> Tensor:
        """(M,): the Chernoff factors ``P_m`` (may underflow to 0; :meth:`select` works in logs)."""
        return torch.exp(self.log_factors)

    # -- selection
    def select(self, features: Tensor) -> Tensor:
        """The model for each frame: ``argmin_m ||f - omega_m|| P_m``.

        Args:
            features (Tensor[F, D]): floating, D as fitted; any device (the state follows).

        Returns:
            Tensor[F] int64 in [0, M), on the features' device.

        Raises:
            ValueError: not fitted, or ``features`` of the wrong shape or dtype.
        """
        self._fitted()
        D = self.centres.shape[1]
        _floating(features, "features", 2, f"(F, {D}) per-frame features")
        if features.shape[1] != D:
            raise ValueError(f"features must be (F, {D}) as fitted, got {describe(features)}")
        dt = torch.promote_types(features.dtype, self.centres.dtype)
        f = features.detach().to(dt)
        centres = self.centres.to(device=f.device, dtype=dt)
        dist = torch.cdist(f, centres, compute_mode="donot_use_mm_for_euclid_dist")  # (F, M)
        score = torch.log(dist) + self.log_factors.to(device=f.device, dtype=dt)
        score = torch.where(self.counts.to(f.device) > 0, score, math.inf)
        return score.argmin(1)

    # -- state
    def state_dict(self) -> dict:
        """``{"centres": (M, D), "variances": (M,), "counts": (M,) int64, "epsilon": () float64}``."""
        self._fitted()
        return {"centres": self.centres.clone(), "variances": self.variances.clone(), "counts": self.counts.clone(),
                "epsilon": torch.tensor(self.epsilon, dtype=torch.float64)}

    @classmethod
    def from_state(cls, state: dict) -> "ChernoffSelector":
        """A selector from :meth:`state_dict`'s dictionary.

        Raises:
            ValueError: naming ``state`` when a key is missing or a tensor has the wrong shape or dtype.
        """
        if not isinstance(state, dict):
            raise ValueError(f"state must be the dict of ChernoffSelector.state_dict(), got {type(state).__name__}")
        missing = [k for k in ("centres", "variances", "counts", "epsilon") if not isinstance(state.get(k), Tensor)]
        if missing:
            raise ValueError(f"state must hold tensors centres, variances, counts and epsilon; missing or not a tensor: "
                             f"{missing}")
        c, v, n, e = state["centres"], state["variances"], state["counts"], state["epsilon"]
        if c.dim() != 2 or not c.is_floating_point() or 0 in c.shape or v.shape != (c.shape[0],) \
                or n.shape != (c.shape[0],) or n.is_floating_point() or e.numel() != 1:
            raise ValueError(f"state has inconsistent tensors: centres {describe(c)}, variances {describe(v)}, "
                             f"counts {describe(n)}, epsilon {describe(e)}")
        self = cls()
        self.centres = c.clone()
        self.variances = v.to(device=c.device, dtype=c.dtype).clone()
        self.counts = n.to(device=c.device, dtype=torch.int64).clone()
        self.epsilon = real(float(e), "state['epsilon']", 0, lo_open=True)
        return self
