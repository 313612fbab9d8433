"""Fuzz: CounterNet's counting parts (lidarops.models.counting): peaks and their counts against the window-by-window
reference (ties, plateaus, NaN, per-cell thresholds), Otsu's threshold against skimage bit for bit (masks, lattice
values, constant rows, tiny and overflowing ranges), the partitions (cover the map, contain the even tiling), the
greedy merge against its plain loop (and its defining properties), the heatmap targets against CenterPoint's loop.

(``test_fuzz_counting.py`` of this folder fuzzes the counting metrics of lidarops.eval.counting.)

The rule of this folder: bad shapes, dtypes, devices or values raise a ``ValueError`` naming the argument; anything
else returns the reference's result.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given
from hypothesis import strategies as st
from skimage.filters import threshold_otsu

from helpers.counting_reference import _find_peaks_reference, _heatmap_targets_reference, _merge_centres_reference
from lidarops.models.counting import (PARTITIONS, count_peaks, find_peaks, heatmap_targets, merge_centres,
                                      otsu_threshold, partition_boxes, soft_count)

from .fuzzing import assert_clear_error, assert_close, assert_no_error, assert_same, fuzz, outcome

FLOATS = [torch.float32, torch.float64]


# ---------------------------------------------------------------------------------------------- maps
@st.composite
def maps(draw, max_side: int = 9):
    """(B, C, H, W) heatmaps: continuous, lattice (ties and plateaus), constant, or with NaN and infinities."""
    B, C = draw(st.integers(0, 2), "B"), draw(st.integers(1, 3), "C")
    H, W = draw(st.integers(0, max_side), "H"), draw(st.integers(0, max_side), "W")
    dtype = draw(st.sampled_from(FLOATS), "dtype")
    kind = draw(st.sampled_from(["continuous", "lattice", "constant", "nonfinite"]), "values")
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**16), "seed"))
    h = torch.rand(B, C, H, W, generator=g, dtype=torch.float64)
    if kind == "lattice":
        h = (h * 4).floor() / 4
    elif kind == "constant":
        h = torch.full_like(h, draw(st.sampled_from([0.0, 0.5, 1.0])))
    elif kind == "nonfinite" and h.numel():
        spots = torch.rand(h.shape, generator=g) < 0.1
        h = torch.where(spots, torch.tensor([math.nan, math.inf, -math.inf])[torch.randint(0, 3, h.shape, generator=g)],
                        h)
    return h.to(dtype), kind


@st.composite
def thresholds(draw, shape):
    """A number (infinities too) or a tensor broadcastable to ``shape``: (B, C, 1, 1), (B, C, H, W), (1, 1, 1, W)."""
    B, C, H, W = shape
    form = draw(st.sampled_from(["number", "per_class", "per_cell", "per_column", "scalar_tensor"]), "threshold form")
    if form == "number":
        return draw(st.sampled_from([0.0, 0.25, 0.5, 0.99, -math.inf, math.inf]) | st.floats(-1, 2), "threshold")
    size = {"per_class": (B, C, 1, 1), "per_cell": (B, C, H, W), "per_column": (1, 1, 1, W), "scalar_tensor": ()}[form]
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**16), "threshold seed"))
    return (torch.rand(size, generator=g, dtype=torch.float64) * 4).floor() / 4  # lattice: equal to cells now and then


@fuzz
@given(data=st.data())
def test_find_peaks_and_count_peaks_match_the_window_reference(device, data):
    heat, kind = data.draw(maps())
    radius = data.draw(st.integers(0, 4), "radius")
    thr = data.draw(thresholds(heat.shape))
    what = f"find_peaks({tuple(heat.shape)}, {heat.dtype}, {kind}, r={radius}, threshold {type(thr).__name__})"
    on = thr.to(device) if isinstance(thr, torch.Tensor) else thr
    peaks, err = outcome(find_peaks, heat.to(device), on, radius)
    assert_no_error(err, what)
    assert peaks.dtype == torch.bool and peaks.shape == heat.shape, what
    assert_same(peaks, _find_peaks_reference(heat, thr, radius), what)
    counts, err = outcome(count_peaks, heat.to(device), on, radius)
    assert_no_error(err, what)
    assert counts.dtype == torch.int64 and counts.shape == heat.shape[:2], what
    assert_same(counts, peaks.sum((2, 3)), what + ": count_peaks = sum of find_peaks")
    # every peak reaches the threshold; a soft count is finite on finite maps
    if peaks.any():
        t64 = torch.broadcast_to(torch.as_tensor(thr, dtype=torch.float64), heat.shape)
        assert bool((heat.double()[peaks.cpu()] >= t64[peaks.cpu()]).all()), what
    soft, err = outcome(soft_count, heat.to(device), on, radius)
    assert_no_error(err, what + " soft_count")
    assert soft.shape == heat.shape[:2] and soft.dtype == heat.dtype, what
    if kind != "nonfinite":
        assert bool(torch.isfinite(soft).all()), what


# ---------------------------------------------------------------------------------------------- Otsu
@st.composite
def otsu_rows(draw):
    """(R, N) rows: uniform, bimodal, lattice, constant, tiny ranges (a few ulp), huge or non-finite values."""
    R, N = draw(st.integers(0, 4), "R"), draw(st.integers(0, 60), "N")
    dtype = draw(st.sampled_from(FLOATS), "dtype")
    kind = draw(st.sampled_from(["uniform", "bimodal", "lattice", "constant", "tiny", "huge", "nonfinite"]), "values")
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**16), "seed"))
    v = torch.rand(R, N, generator=g, dtype=torch.float64)
    if kind == "bimodal":
        v = torch.where(v < 0.5, v * 0.2, 0.7 + v * 0.3) + torch.randn(R, N, generator=g, dtype=torch.float64) * 0.01
    elif kind == "lattice":
        v = (v * 5).floor() - 2
    elif kind == "constant":
        v = torch.full_like(v, -1.5)
    elif kind == "tiny":
        v = 1.0 + (v * 4).floor() * torch.finfo(dtype).eps
    elif kind == "huge":
        top = float(torch.finfo(dtype).max)
        v = (v * 2 - 1) * draw(st.sampled_from([1e30, top / 2, top]))
    elif kind == "nonfinite" and v.numel():
        v[torch.rand(R, N, generator=g) < 0.2] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    mask = None
    if draw(st.booleans(), "masked"):
        mask = torch.rand(R, N, generator=g) < draw(st.sampled_from([0.0, 0.3, 0.9]))
    return v.to(dtype), mask, kind


def _skimage_or_nan(row: np.ndarray, bins: int) -> float:
    """skimage's threshold, NaN where it raises (no entry, non-finite values, a range NumPy cannot bin)."""
    if row.size == 0:
        return math.nan
    try:
        with np.errstate(all="ignore"):
            return float(threshold_otsu(row, nbins=bins))
    except ValueError:
        return math.nan


@fuzz
@given(data=st.data())
def test_otsu_threshold_is_skimage_row_by_row(device, data):
    v, mask, kind = data.draw(otsu_rows())
    bins = data.draw(st.sampled_from([2, 3, 16, 256]) | st.integers(2, 300), "bins")
    what = f"otsu_threshold({tuple(v.shape)}, {v.dtype}, {kind}, bins={bins}, masked={mask is not None})"
    got, err = outcome(otsu_threshold, v.to(device), bins, None if mask is None else mask.to(device))
    assert_no_error(err, what)
    assert got.shape == v.shape[:1] and got.dtype == v.dtype, what
    npd = np.float32 if v.dtype == torch.float32 else np.float64
    for i in range(v.shape[0]):
        row = v[i] if mask is None else v[i][mask[i]]
        want = _skimage_or_nan(row.numpy().astype(npd), bins)
        g = got[i].item()
        if math.isinf(want) and not (row == want).all():  # skimage's bin centre overflowed: ours stays finite
            assert math.isfinite(g), f"{what} row {i}: got {g!r}"
        else:
            assert (math.isnan(g) and math.isnan(want)) or g == want, f"{what} row {i}: got {g!r}, skimage {want!r}"
        if not math.isnan(g):  # a bin centre of the row's own range
            assert float(row.min()) <= g <= float(row.max()), f"{what} row {i}"
    # the fast path stays within the row's range as well
    fast, err = outcome(otsu_threshold, v.to(device), bins, None if mask is None else mask.to(device), exact=False)
    assert_no_error(err, what + " exact=False")
    same_nan = torch.isnan(fast.cpu()) == torch.isnan(got.cpu())
    assert bool(same_nan.all()), what + " exact=False: NaN rows differ"


# ---------------------------------------------------------------------------------------------- partitions
@fuzz
@given(data=st.data())
def test_partition_boxes_cover_the_map_and_contain_the_even_tiling(device, data):
    H, W = data.draw(st.integers(1, 40), "height"), data.draw(st.integers(1, 40), "width")
    pt = data.draw(st.sampled_from(sorted(PARTITIONS)) | st.sampled_from([0, 3, 5, 16, -4, 2.0, True, "4", None]),
                   "pt")
    delta = data.draw(st.sampled_from([0.0, 0.1, 0.2, 0.5, 1.0, 1e9, 1.7e308]) | st.floats(0, 3)
                      | st.sampled_from([-0.1, math.nan, math.inf, "0.2", None]), "delta")
    what = f"partition_boxes({H}, {W}, pt={pt!r}, delta={delta!r})"
    got, err = outcome(partition_boxes, H, W, pt, delta, device=device)
    pt_ok = isinstance(pt, int) and not isinstance(pt, bool) and pt in PARTITIONS
    if not pt_ok:
        return assert_clear_error(err, ValueError, ["pt"], what)
    if not isinstance(delta, float) or not (delta >= 0) or not math.isfinite(delta):
        return assert_clear_error(err, ValueError, ["delta"], what)
    rows, cols = PARTITIONS[pt]
    if H < rows or W < cols:
        return assert_clear_error(err, ValueError, ["height", "width"], what)
    assert_no_error(err, what)
    assert got.shape == (pt, 4) and got.dtype == torch.int64 and got.device.type == device, what
    cover = torch.zeros(H, W, dtype=torch.int64)
    for k, (y0, y1, x0, x1) in enumerate(got.tolist()):
        assert 0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W, f"{what}: region {k} {[y0, y1, x0, x1]}"
        i, j = divmod(k, cols)
        ty0, ty1, tx0, tx1 = i * H // rows, (i + 1) * H // rows, j * W // cols, (j + 1) * W // cols
        assert y0 <= ty0 and ty1 <= y1 and x0 <= tx0 and tx1 <= x1, f"{what}: region {k} misses its tile"
        d = min(delta, 1e6)  # beyond the map either way (delta * size may overflow)
        gy, gx = math.ceil(round(d * (ty1 - ty0), 9)), math.ceil(round(d * (tx1 - tx0), 9))
        assert [y0, y1, x0, x1] == [max(0, ty0 - gy), min(H, ty1 + gy), max(0, tx0 - gx), min(W, tx1 + gx)], what
        cover[y0:y1, x0:x1] += 1
    assert bool((cover >= 1).all()), f"{what}: cells outside every region"
    if delta == 0:
        assert bool((cover == 1).all()), f"{what}: the tiling overlaps"


# ---------------------------------------------------------------------------------------------- merge
@st.composite
def centre_sets(draw):
    """(K, 4) centres on a coarse lattice (exact distance ties, duplicates), few classes, tied scores."""
    K = draw(st.integers(0, 30), "K")
    dtype = draw(st.sampled_from(FLOATS), "dtype")
    step = draw(st.sampled_from([0.25, 0.5, 1.0]), "lattice step")
    xy = st.integers(-6, 6).map(lambda v: v * step)
    rows = [[draw(xy), draw(xy), float(draw(st.integers(0, 2))), draw(st.sampled_from([0.1, 0.5, 0.9]) | st.floats(0, 1))]
            for _ in range(K)]
    return torch.tensor(rows, dtype=torch.float64).reshape(K, 4).to(dtype)


@fuzz
@given(data=st.data())
def test_merge_centres_is_the_greedy_rule(device, data):
    centres = data.draw(centre_sets())
    radius = data.draw(st.sampled_from([0.0, 0.5, 1.0, 1.5, 3.0]) | st.floats(0, 5), "radius")
    what = f"merge_centres(K={centres.shape[0]}, {centres.dtype}, radius={radius})"
    got, err = outcome(merge_centres, centres.to(device), radius)
    assert_no_error(err, what)
    assert got.dtype == centres.dtype and got.device.type == device, what
    got = got.cpu()
    assert_same(got, centres[_merge_centres_reference(centres, radius)], what)
    c = got.double()
    # sorted by decreasing score; no two kept centres of one class within the radius
    assert bool((c[1:, 3] <= c[:-1, 3]).all()), what
    for i in range(c.shape[0]):
        for j in range(i + 1, c.shape[0]):
            if c[i, 2] == c[j, 2]:
                assert math.hypot(c[i, 0] - c[j, 0], c[i, 1] - c[j, 1]) > radius, f"{what}: kept {i} and {j} close"
    # each dropped centre has a kept one of its class, scoring at least as much, within the radius
    kept = {tuple(r) for r in c.tolist()}
    for r in centres.double().tolist():
        if tuple(r) in kept:
            continue
        assert any(k[2] == r[2] and k[3] >= r[3] and math.hypot(k[0] - r[0], k[1] - r[1]) <= radius
                   for k in c.tolist()), f"{what}: {r} dropped with no kept neighbour"


# ---------------------------------------------------------------------------------------------- targets
@fuzz
@given(data=st.data())
def test_heatmap_targets_match_centerpoint_loop(device, data):
    B, M, C = data.draw(st.integers(0, 3), "B"), data.draw(st.integers(0, 8), "M"), data.draw(st.integers(1, 3), "C")
    dtype = data.draw(st.sampled_from(FLOATS), "dtype")
    stride = data.draw(st.sampled_from([1, 2, 4]), "stride")
    grid = [data.draw(st.integers(1, 24), "nx"), data.draw(st.integers(1, 24), "ny")]
    voxel = [data.draw(st.sampled_from([0.16, 0.2, 0.5]), "vx"), data.draw(st.sampled_from([0.16, 0.25]), "vy"), 4.0]
    pcr = [-1.0, -2.0, -3.0, 1.0, 2.0, 1.0]
    overlap = data.draw(st.sampled_from([0.1, 0.5, 0.7]), "min_overlap")
    min_radius = data.draw(st.integers(0, 3), "min_radius")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**16), "seed"))
    span = torch.tensor([grid[0] * voxel[0], grid[1] * voxel[1]], dtype=torch.float64)
    xy = torch.rand(B, M, 2, generator=g, dtype=torch.float64) * span * 1.2 + torch.tensor(pcr[:2]) - 0.1 * span
    size = torch.rand(B, M, 3, generator=g, dtype=torch.float64) * data.draw(st.sampled_from([0.0, 1.0, 6.0, 60.0]))
    cls = torch.randint(0, C + 1, (B, M, 1), generator=g).double()
    boxes = torch.cat([xy, torch.zeros(B, M, 1, dtype=torch.float64), size, torch.zeros(B, M, 1, dtype=torch.float64),
                       cls], -1).to(dtype)
    what = f"heatmap_targets(B={B}, M={M}, C={C}, grid={grid}, stride={stride}, {dtype})"
    got, err = outcome(heatmap_targets, boxes.to(device), C, pcr, voxel, grid, stride, overlap, min_radius)
    assert_no_error(err, what)
    want = torch.from_numpy(_heatmap_targets_reference(boxes, C, pcr, voxel, grid, stride, overlap, min_radius))
    assert got.dtype == dtype and got.shape == want.shape, what
    if dtype == torch.float64:
        assert_close(got, want, 4.5e-16, 0, what)
    else:
        assert_same(got, want.float(), what)


# ---------------------------------------------------------------------------------------------- bad input
_BAD = ["heatmap_dims", "heatmap_dtype", "heatmap_list", "radius", "threshold_nan", "threshold_shape",
        "threshold_device", "threshold_dtype", "bins", "values_dtype", "mask_shape", "mask_dtype", "mask_device",
        "centres_shape", "centres_dtype", "merge_radius", "boxes_class"]


@fuzz
@given(data=st.data())
def test_bad_arguments_raise_value_errors_naming_them(device, data):
    kind = data.draw(st.sampled_from(_BAD), "kind")
    heat = torch.rand(2, 3, 5, 4, dtype=torch.float64, device=device)
    if kind.startswith("heatmap") or kind.startswith("radius") or kind.startswith("threshold"):
        fn = data.draw(st.sampled_from([find_peaks, count_peaks, soft_count]), "function")
        thr, radius, name = 0.5, 2, kind.split("_")[0]
        if kind == "heatmap_dims":
            heat = heat.reshape(data.draw(st.sampled_from([(6, 5, 4), (2, 3, 5, 4, 1), (120,)])))
        elif kind == "heatmap_dtype":
            heat = heat.to(data.draw(st.sampled_from([torch.int64, torch.int32, torch.bool, torch.uint8])))
        elif kind == "heatmap_list":
            heat = heat.tolist()
        elif kind == "radius":
            radius = data.draw(st.sampled_from([-1, -100, 1.5, 2.0, True, None, "2", math.nan]))
        elif kind == "threshold_nan":
            thr = data.draw(st.sampled_from([math.nan, None, "0.5", [0.5], True]))
        elif kind == "threshold_shape":
            thr = torch.rand(data.draw(st.sampled_from([(3, 2, 1, 1), (2, 3, 5, 5), (1, 2, 3, 5, 4), (7,)])),
                             device=device)
        elif kind == "threshold_device":
            thr = torch.rand(2, 3, 1, 1, device="meta")
        else:
            thr = torch.ones(2, 3, 1, 1, dtype=data.draw(st.sampled_from([torch.bool, torch.complex64])),
                             device=device)
        _, err = outcome(fn, heat, thr, radius)
        return assert_clear_error(err, ValueError, [name], f"{fn.__name__} with bad {kind}")
    if kind in ("bins", "values_dtype", "mask_shape", "mask_dtype", "mask_device"):
        values, bins, mask = torch.rand(3, 7, device=device), 256, None
        if kind == "bins":
            bins = data.draw(st.sampled_from([1, 0, -3, 2.0, 256.5, True, None, "256"]))
        elif kind == "values_dtype":
            values = values.to(data.draw(st.sampled_from([torch.int64, torch.bool]))) if data.draw(st.booleans()) \
                else torch.tensor(0.5, device=device)
        elif kind == "mask_shape":
            mask = torch.ones(data.draw(st.sampled_from([(3, 6), (7,), (1, 3, 7)])), dtype=torch.bool, device=device)
        elif kind == "mask_dtype":
            mask = torch.ones(3, 7, dtype=data.draw(st.sampled_from([torch.float32, torch.int64])), device=device)
        else:
            mask = torch.ones(3, 7, dtype=torch.bool, device="meta")
        _, err = outcome(otsu_threshold, values, bins, mask)
        return assert_clear_error(err, ValueError, [kind.split("_")[0]], f"otsu_threshold with bad {kind}")
    if kind in ("centres_shape", "centres_dtype", "merge_radius"):
        centres, radius = torch.rand(5, 4, device=device), 1.0
        if kind == "centres_shape":
            centres = centres.reshape(data.draw(st.sampled_from([(20,), (4, 5), (5, 2, 2)])))
        elif kind == "centres_dtype":
            centres = centres.long()
        else:
            radius = data.draw(st.sampled_from([-1.0, math.nan, math.inf, None, "1"]))
        _, err = outcome(merge_centres, centres, radius)
        return assert_clear_error(err, ValueError, ["centres" if kind.startswith("centres") else "radius"],
                                  f"merge_centres with bad {kind}")
    cls = data.draw(st.sampled_from([-1.0, 4.0, 1.5, math.nan, 1e9]))
    boxes = torch.tensor([[[0.1, 0.1, 0, 1, 1, 1, 0, cls]]], device=device)
    _, err = outcome(heatmap_targets, boxes, 3, [0, 0, -3, 4, 4, 1], [0.2, 0.2], [20, 20], 1)
    assert_clear_error(err, ValueError, ["boxes"], f"heatmap_targets with class id {cls}")
