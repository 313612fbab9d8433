"""lidarops.models.counting: CounterNet's counting parts. The Gaussian radius and the heatmap targets against
CenterPoint's functions restated in plain Python / NumPy (float64) and hand-computed windows; the focal loss against
a case written out and a float64 loop; the peaks against ``skimage.feature.peak_local_max``; Otsu against
``skimage.filters.threshold_otsu``; partitions, the merge, the region weights and the Chernoff selector on
constructed cases."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from skimage.feature import peak_local_max
from skimage.filters import threshold_otsu

import lidarops
from helpers.compare import assert_close_report, assert_equal_report
from helpers.counting_reference import (_find_peaks_reference, _gaussian_radius_python, _heatmap_targets_reference,
                                        _merge_centres_reference)
from lidarops.models.counting import (PARTITIONS, ChernoffSelector, count_peaks, find_peaks,
                                      focal_loss, gaussian_radius, heatmap_targets, merge_centres, otsu_threshold,
                                      partition_boxes, partition_weights, peak_centres, soft_count)

FLOATS = [torch.float32, torch.float64]
IDS = ["f32", "f64"]
# a KITTI-like grid: 0.16 m pillars, stride 2 -> 0.32 m cells; 40 x 30 voxels -> a 20 x 15 (W x H) map
PCR = [0.0, -2.4, -3.0, 6.4, 2.4, 1.0]
VOXEL = [0.16, 0.16, 4.0]
GRID = [40, 30]
STRIDE = 2
CELL = 0.32


def centre_of(col: int, row: int) -> tuple[float, float]:
    """Metres of the centre of map cell (row, col) on the grid above."""
    return PCR[0] + (col + 0.5) * CELL, PCR[1] + (row + 0.5) * CELL


def box(col, row, cls, dx=0.5, dy=0.5):
    x, y = centre_of(col, row)
    return [x, y, -1.0, dx, dy, 1.5, 0.3, float(cls)]


def assert_heat(got: torch.Tensor, want, what: str) -> None:
    """Equal to the NumPy reference: within 2 ulp in float64 (NumPy's exp and torch's differ in the last bit now
    and then), exactly once rounded to float32 (the one rounding hides that bit)."""
    want = torch.as_tensor(want, dtype=torch.float64)
    if got.dtype == torch.float64:
        assert_close_report(got, want, 4.5e-16, 0, what)
    else:
        assert_equal_report(got, want.to(got.dtype), what)


def window(r: int) -> np.ndarray:
    """CenterPoint's gaussian2D((2r+1, 2r+1), sigma=(2r+1)/6), by hand."""
    sigma = (2 * r + 1) / 6
    o = np.arange(-r, r + 1, dtype=np.float64)
    return np.exp(-(o[None, :] ** 2 + o[:, None] ** 2) / (2 * sigma * sigma))


# ------------------------------------------------------------------------------------------ gaussian_radius
@pytest.mark.parametrize("overlap", [0.1, 0.5, 0.7])
def test_gaussian_radius_matches_centerpoint(device, overlap):
    hand = [(1.0, 1.0), (12.1875, 5.0), (2.5, 11.0), (0.0, 4.0), (3.0, 0.0), (0.0, 0.0), (100.0, 0.25)]
    g = torch.Generator().manual_seed(0)
    rand = (torch.rand(200, 2, generator=g, dtype=torch.float64) * 30).tolist()
    sizes = torch.tensor(hand + rand, dtype=torch.float64)
    dx, dy = sizes[:, 0], sizes[:, 1]
    want = torch.tensor([_gaussian_radius_python(h, w, overlap) for w, h in sizes.tolist()],
                        dtype=torch.float64)
    got = gaussian_radius(dx.to(device), dy.to(device), overlap)
    assert got.dtype == torch.float64
    assert_close_report(got, want, 1e-14, 1e-14, f"gaussian_radius o={overlap} f64")
    got32 = gaussian_radius(dx.float().to(device), dy.float().to(device), overlap)
    assert got32.dtype == torch.float32
    assert_close_report(got32, want, 2e-6, 2e-6, f"gaussian_radius o={overlap} f32")


def test_gaussian_radius_broadcasts_and_integer_sizes():
    got = gaussian_radius(torch.tensor([[2], [4]]), torch.tensor([1, 3, 5]))
    assert got.shape == (2, 3) and got.dtype == torch.float32
    assert math.isclose(got[1, 2].item(), _gaussian_radius_python(5, 4, 0.1), rel_tol=1e-6)
    # by hand for a 4 x 5 cell box (width 4, height 5) at min_overlap 0.1: r1 = 6.47, r2 = 12, and the third
    # case, r3 = (-1.8 + sqrt(1.8^2 + 4 * 0.4 * 18)) / 2 = 1.9302, is the smallest
    assert math.isclose(got[1, 2].item(), (-1.8 + math.sqrt(1.8 ** 2 + 4 * 0.4 * 18)) / 2, rel_tol=1e-6)


# ------------------------------------------------------------------------------------------ heatmap targets
@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
def test_heatmap_one_box_is_the_hand_computed_gaussian(device, dtype):
    """A 0.5 m box is 1.5625 cells: its radius is below 2, so min_radius = 2 rules: the 5 x 5 window of
    exp(-(ox^2 + oy^2) / (2 (5/6)^2)) around its cell, 1 at the centre, 0 elsewhere and on the other channels."""
    assert _gaussian_radius_python(1.5625, 1.5625, 0.1) < 2
    boxes = torch.tensor([[box(7, 6, 2)]], dtype=dtype, device=device)
    heat = heatmap_targets(boxes, 3, PCR, VOXEL, GRID, STRIDE)
    assert heat.shape == (1, 3, 15, 20) and heat.dtype == dtype and heat.device.type == device
    want = torch.zeros(1, 3, 15, 20, dtype=torch.float64)
    want[0, 1, 4:9, 5:10] = torch.from_numpy(window(2))
    assert heat[0, 1, 6, 7].item() == 1.0
    assert_heat(heat, want, "one box")
    assert math.isclose(heat[0, 1, 6, 9].item(), math.exp(-4 / (2 * (5 / 6) ** 2)), rel_tol=1e-6)


def test_heatmap_radius_follows_the_box_size(device):
    """A 4 m x 2 m box on 0.32 m cells: 12.5 x 6.25 cells, CenterPoint's radius int(r) with min_overlap 0.1."""
    r = int(_gaussian_radius_python(6.25, 12.5, 0.1))
    assert r > 2
    boxes = torch.tensor([[box(10, 7, 1, dx=4.0, dy=2.0)]], dtype=torch.float64, device=device)
    heat = heatmap_targets(boxes, 1, PCR, VOXEL, GRID, STRIDE)
    want = np.zeros((15, 20))
    top, bottom, left, right = min(7, r), min(15 - 7, r + 1), min(10, r), min(20 - 10, r + 1)
    want[7 - top:7 + bottom, 10 - left:10 + right] = window(r)[r - top:r + bottom, r - left:r + right]
    assert_heat(heat[0, 0], want, f"radius {r}")


def test_heatmap_overlapping_boxes_take_the_max_not_the_sum(device):
    boxes = torch.tensor([[box(5, 5, 1), box(7, 5, 1)]], dtype=torch.float64, device=device)
    heat = heatmap_targets(boxes, 1, PCR, VOXEL, GRID, STRIDE)[0, 0].cpu()
    g = window(2)
    # the cell between them is 1 off both centres: max(g[2, 1], g[2, 3]) = g[2, 1], not twice
    assert heat[5, 6].item() == g[2, 1]
    assert heat[5, 5].item() == 1.0 and heat[5, 7].item() == 1.0  # a neighbour's Gaussian does not lift a centre
    want = np.zeros((15, 20))
    want[3:8, 3:8] = g
    want[3:8, 5:10] = np.maximum(want[3:8, 5:10], g)
    assert_heat(heat, want, "two boxes")
    assert heat.max().item() == 1.0


def test_heatmap_boxes_at_the_map_edges_are_clipped(device):
    """Centres in the corner cells: only the quadrant of the window on the map is drawn."""
    boxes = torch.tensor([[box(0, 0, 1), box(19, 14, 1)]], dtype=torch.float64, device=device)
    heat = heatmap_targets(boxes, 1, PCR, VOXEL, GRID, STRIDE)[0, 0].cpu()
    g = window(2)
    want = np.zeros((15, 20))
    want[0:3, 0:3] = g[2:, 2:]
    want[12:15, 17:20] = g[:3, :3]
    assert_heat(heat, want, "corners")


def test_heatmap_skips_centres_off_the_map(device):
    """x below x0 by a fraction of a cell: CenterPoint's int() would put it in column 0; floor skips it."""
    x0, y0 = PCR[0], PCR[1]
    rows = [[x0 - 0.1, y0 + 1.0, 0, 1, 1, 1, 0, 1], [x0 + 20 * CELL + 0.01, y0 + 1.0, 0, 1, 1, 1, 0, 1],
            [x0 + 1.0, y0 + 15 * CELL + 0.01, 0, 1, 1, 1, 0, 1], [x0 + 1.0, y0 - 1e-9, 0, 1, 1, 1, 0, 1]]
    heat = heatmap_targets(torch.tensor([rows], device=device), 1, PCR, VOXEL, GRID, STRIDE)
    assert heat.abs().sum().item() == 0


def test_heatmap_padding_rows_classes_and_ragged_batches(device):
    """Frame 0 holds three objects of classes 1, 3, 3, frame 1 one of class 2 and padding, frame 2 only padding
    (with garbage, even NaN, in its other columns): each drawn on its own frame and channel."""
    pad = [0.0] * 8
    garbage = [math.nan, 1e30, 0, -5, -5, 0, 0, 0.0]
    boxes = torch.tensor([[box(3, 3, 1), box(10, 4, 3), box(12, 10, 3)],
                          [box(15, 12, 2), pad, garbage],
                          [pad, garbage, pad]], dtype=torch.float64, device=device)
    heat = heatmap_targets(boxes, 3, PCR, VOXEL, GRID, STRIDE).cpu()
    want = torch.from_numpy(_heatmap_targets_reference(boxes, 3, PCR, VOXEL, GRID, STRIDE))
    assert_heat(heat, want, "ragged")
    assert count_peaks(heat, 0.99).tolist() == [[1, 0, 2], [0, 1, 0], [0, 0, 0]]
    # the frames do not see each other: frame 1 alone gives the same map
    alone = heatmap_targets(boxes[1:2], 3, PCR, VOXEL, GRID, STRIDE).cpu()
    assert_equal_report(alone[0], heat[1], "frame 1 alone")


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heatmap_random_boxes_match_centerpoint_loop(device, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    B, M, C = 3, 25, 4
    xy = torch.rand(B, M, 2, generator=g, dtype=torch.float64) * torch.tensor([7.4, 5.8]) + torch.tensor([-0.5, -2.9])
    size = torch.rand(B, M, 3, generator=g, dtype=torch.float64) * 5
    cls = torch.randint(0, C + 1, (B, M, 1), generator=g).double()
    boxes = torch.cat([xy, torch.zeros(B, M, 1, dtype=torch.float64), size, torch.zeros(B, M, 1, dtype=torch.float64),
                       cls], -1).to(dtype)
    heat = heatmap_targets(boxes.to(device), C, PCR, VOXEL, GRID, STRIDE, min_overlap=0.1, min_radius=1)
    want = _heatmap_targets_reference(boxes, C, PCR, VOXEL, GRID, STRIDE, 0.1, 1)
    assert_heat(heat, want, f"random boxes seed {seed}")


def test_heatmap_huge_boxes_and_the_chunked_path(device, monkeypatch):
    """Boxes far larger than the map (the window stops at the map; sigma keeps the true radius) next to small
    ones, drawn in one pass and in chunks of similar radius (a tiny window budget)."""
    from lidarops.models import counting

    g = torch.Generator().manual_seed(3)
    rows = [box(int(c), int(r), 1 + int(k), dx=float(s), dy=float(s)) for c, r, k, s in zip(
        torch.randint(0, 20, (30,), generator=g), torch.randint(0, 15, (30,), generator=g),
        torch.randint(0, 2, (30,), generator=g), torch.rand(30, generator=g) * 2)]
    rows += [box(3, 4, 1, dx=300.0, dy=120.0), box(17, 2, 2, dx=40.0, dy=25.0)]
    boxes = torch.tensor([rows], dtype=torch.float64, device=device)
    want = torch.from_numpy(_heatmap_targets_reference(boxes, 2, PCR, VOXEL, GRID, STRIDE))
    one = heatmap_targets(boxes, 2, PCR, VOXEL, GRID, STRIDE)
    assert_heat(one, want, "one pass")
    monkeypatch.setattr(counting, "_WINDOW_BUDGET", 200)
    chunked = heatmap_targets(boxes, 2, PCR, VOXEL, GRID, STRIDE)
    assert_heat(chunked, want, "chunked")
    assert_equal_report(chunked, one, "chunked = one pass")


def test_heatmap_integer_boxes_empty_inputs_and_grid_forms(device):
    boxes = torch.tensor([[[1, 0, 0, 1, 1, 1, 0, 1]]], device=device)  # integer: float32 out
    heat = heatmap_targets(boxes, 2, PCR, VOXEL, np.array(GRID + [1]), STRIDE)
    assert heat.dtype == torch.float32 and heat.max().item() == 1.0
    empty = heatmap_targets(torch.zeros(2, 0, 8, device=device), 2, PCR, VOXEL, GRID, STRIDE)
    assert empty.shape == (2, 2, 15, 20) and empty.abs().sum().item() == 0
    assert heatmap_targets(torch.zeros(0, 3, 8), 2, PCR, VOXEL, GRID, STRIDE).shape == (0, 2, 15, 20)
    assert heatmap_targets(boxes, 2, PCR, VOXEL, [1, 1], STRIDE).shape == (1, 2, 0, 0)


# ------------------------------------------------------------------------------------------ focal loss
def test_focal_loss_hand_computed_two_by_two():
    """pred [[0.9, 0.2], [0.3, 0.5]], target [[1, 0.5], [0, 0.8]]: one positive (0.9), three negatives:
    -( (0.1)^2 log 0.9 + (0.5)^4 0.2^2 log 0.8 + 1 * 0.3^2 log 0.7 + (0.2)^4 0.5^2 log 0.5 ) / 1."""
    pred = torch.tensor([[[[0.9, 0.2], [0.3, 0.5]]]], dtype=torch.float64)
    target = torch.tensor([[[[1.0, 0.5], [0.0, 0.8]]]], dtype=torch.float64)
    want = -(0.1 ** 2 * math.log(0.9) + 0.5 ** 4 * 0.2 ** 2 * math.log(0.8) + 0.3 ** 2 * math.log(0.7)
             + 0.2 ** 4 * 0.5 ** 2 * math.log(0.5))
    got = focal_loss(pred, target)
    assert got.dtype == torch.float64 and got.shape == ()
    assert math.isclose(got.item(), want, rel_tol=1e-14), (got.item(), want)
    # no positive: divided by 1, not 0
    none = focal_loss(pred, target * 0.5)
    want0 = -sum((1 - t) ** 4 * p ** 2 * math.log(1 - p) for p, t in zip([0.9, 0.2, 0.3, 0.5], [0.5, 0.25, 0, 0.4]))
    assert math.isclose(none.item(), want0, rel_tol=1e-14)


def _focal_loop(pred: torch.Tensor, target: torch.Tensor, eps=1e-4) -> float:
    p, t = pred.double().flatten().tolist(), target.double().flatten().tolist()
    pos, total = 0, 0.0
    for pi, ti in zip(p, t):
        pi = min(max(pi, eps), 1 - eps)
        if ti == 1:
            pos += 1
            total += (1 - pi) ** 2 * math.log(pi)
        elif ti < 1:
            total += (1 - ti) ** 4 * pi ** 2 * math.log(1 - pi)
    return -total / max(1, pos)


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
def test_focal_loss_matches_a_float64_loop_with_finite_gradient(device, dtype):
    boxes = torch.tensor([[box(3, 3, 1), box(10, 4, 2), box(11, 5, 2)], [box(15, 12, 2)] + [[0.0] * 8] * 2])
    target = heatmap_targets(boxes, 2, PCR, VOXEL, GRID, STRIDE)
    g = torch.Generator().manual_seed(5)
    pred = torch.rand(target.shape, generator=g, dtype=torch.float64)
    pred[0, 0, 0, 0], pred[0, 0, 3, 3], pred[1, 1, 0, 1] = 0.0, 1.0, 1.0  # the clamp bites
    pred = pred.to(dtype).to(device).requires_grad_(True)
    loss = focal_loss(pred, target.to(device))
    want = _focal_loop(pred.detach().cpu(), target)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert loss.dtype == dtype and math.isclose(loss.item(), want, rel_tol=tol), (loss.item(), want)
    (grad,) = torch.autograd.grad(loss, pred)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    assert grad[0, 0, 0, 0].item() == 0 and grad[0, 0, 3, 3].item() == 0  # clamped cells


def test_focal_loss_gradcheck():
    g = torch.Generator().manual_seed(6)
    pred = (torch.rand(2, 2, 3, 3, generator=g, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    target = torch.rand(2, 2, 3, 3, generator=g, dtype=torch.float64)
    target[0, 1, 1, 1] = target[1, 0, 2, 0] = 1.0
    assert torch.autograd.gradcheck(lambda p: focal_loss(p, target), (pred,))


# ------------------------------------------------------------------------------------------ peaks
def _random_maps(B, C, H, W, seed, dtype=torch.float64):
    """Continuous values: no two cells equal (checked)."""
    g = torch.Generator().manual_seed(seed)
    h = torch.rand(B, C, H, W, generator=g, dtype=torch.float64)
    assert h.flatten().unique().numel() == h.numel()
    return h.to(dtype)


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
@pytest.mark.parametrize("radius", [0, 1, 2, 3, 7])
def test_find_peaks_matches_skimage_peak_local_max(device, dtype, radius):
    heat = _random_maps(2, 3, 13, 17, seed=radius, dtype=dtype)
    for threshold in [0.0, 0.3, 0.8]:
        got = find_peaks(heat.to(device), threshold, radius).cpu()
        assert got.dtype == torch.bool and got.shape == heat.shape
        for b in range(2):
            for c in range(3):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # min_distance = 0: skimage warns
                    coords = peak_local_max(heat[b, c].double().numpy(), min_distance=radius, threshold_abs=threshold,
                                            exclude_border=False)
                want = torch.zeros(13, 17, dtype=torch.bool)
                want[tuple(torch.from_numpy(coords).T)] = True
                assert_equal_report(got[b, c], want, f"r={radius} t={threshold} ({b}, {c})")
        assert count_peaks(heat.to(device), threshold, radius).tolist() == got.sum((2, 3)).tolist()


def test_find_peaks_plateaus_every_flat_maximum_cell_is_a_peak(device):
    """A flat 2 x 3 top of 0.9 on a 0.1 background: all six cells are peaks (skimage keeps one of them); a constant
    map is all peaks where it reaches the threshold (skimage: none); a flat background below the threshold none."""
    heat = torch.full((1, 1, 9, 9), 0.1, dtype=torch.float64)
    heat[0, 0, 3:5, 2:5] = 0.9
    peaks = find_peaks(heat.to(device), 0.5, 2).cpu()
    assert peaks.sum().item() == 6 and peaks[0, 0, 3:5, 2:5].all()
    assert count_peaks(heat.to(device), 0.05, 2).item() == 6 + sum(  # background cells with no 0.9 in their window
        1 for i in range(9) for j in range(9) if not (i - 2 <= 4 and i + 2 >= 3 and j - 2 <= 4 and j + 2 >= 2))
    flat = torch.full((2, 1, 4, 5), 0.7, device=device)
    assert count_peaks(flat, 0.5).tolist() == [[20], [20]] and count_peaks(flat, 0.8).tolist() == [[0], [0]]
    assert_equal_report(find_peaks(heat, 0.05, 2), _find_peaks_reference(heat, 0.05, 2), "reference on plateaus")


def test_find_peaks_tensor_thresholds(device):
    """(B, C, 1, 1) per frame and class, and a per-cell map (two partitions with their own thresholds)."""
    heat = _random_maps(2, 2, 8, 10, seed=11).to(device)
    thr = torch.tensor([[0.2, 0.9], [0.5, 0.0]], dtype=torch.float64, device=device)[:, :, None, None]
    got = find_peaks(heat, thr, 1)
    for b in range(2):
        for c in range(2):
            assert_equal_report(got[b, c], find_peaks(heat[b:b + 1, c:c + 1], float(thr[b, c]), 1)[0, 0], "per class")
    cells = torch.full((1, 1, 8, 10), 0.95, device=device)
    cells[..., :5] = 0.1  # the left half with a low threshold, the right half with a high one
    got = find_peaks(heat, cells, 1)
    assert not got[..., 5:][heat[..., 5:] < 0.95].any()
    assert_equal_report(got[..., :5], find_peaks(heat, 0.1, 1)[..., :5], "left partition")
    assert_equal_report(got.cpu(), _find_peaks_reference(heat, cells, 1), "reference")


def test_find_peaks_nan_and_empty_maps(device):
    heat = torch.zeros(1, 1, 5, 5, device=device)
    heat[0, 0, 2, 2] = 1.0
    heat[0, 0, 0, 4] = math.nan
    got = find_peaks(heat, 0.5, 1)
    assert got.sum().item() == 1 and got[0, 0, 2, 2]
    assert_equal_report(got.cpu(), _find_peaks_reference(heat, 0.5, 1), "NaN")
    assert find_peaks(torch.zeros(2, 3, 0, 4, device=device), 0.5).shape == (2, 3, 0, 4)
    assert count_peaks(torch.zeros(0, 3, 4, 4, device=device), 0.5).shape == (0, 3)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16], ids=["f16", "bf16"])
def test_find_peaks_half_maps(dtype):
    heat = _random_maps(1, 2, 9, 9, seed=3)
    got = find_peaks(heat.to(dtype), 0.4, 2)
    assert_equal_report(got, _find_peaks_reference(heat.to(dtype), 0.4, 2), str(dtype))


# ------------------------------------------------------------------------------------------ centres
def test_peak_centres_by_hand_and_batched(device):
    heat = torch.zeros(3, 2, 15, 20, dtype=torch.float64, device=device)
    heat[0, 1, 2, 3] = 0.8
    heat[0, 0, 14, 19] = 0.6
    heat[2, 1, 0, 0] = 0.9
    peaks = find_peaks(heat, 0.5)
    got = peak_centres(heat, peaks, PCR, VOXEL, STRIDE)
    assert len(got) == 3 and [t.shape for t in got] == [(2, 4), (0, 4), (1, 4)]
    assert got[0].dtype == torch.float64 and got[0].device.type == device
    want0 = torch.tensor([[(19 + 0.5) * 0.16 * 2 + 0.0, (14 + 0.5) * 0.16 * 2 - 2.4, 0, 0.6],
                          [(3 + 0.5) * 0.16 * 2 + 0.0, (2 + 0.5) * 0.16 * 2 - 2.4, 1, 0.8]], dtype=torch.float64)
    assert_close_report(got[0], want0, 0, 1e-15, "frame 0 (class, row, column order)")
    assert_close_report(got[2], torch.tensor([[0.16, -2.4 + 0.16, 1, 0.9]], dtype=torch.float64), 0, 1e-15, "frame 2")


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
def test_peak_centres_recover_the_boxes_behind_heatmap_targets(device, dtype):
    """Boxes at cell centres -> targets -> peaks -> centres: the same x, y and (0-based) class, score 1."""
    cells = [(2, 3, 1), (9, 9, 2), (16, 5, 1)]
    boxes = torch.tensor([[box(c, r, k) for c, r, k in cells], [box(0, 0, 2), [0.0] * 8, [0.0] * 8]],
                         dtype=dtype, device=device)
    heat = heatmap_targets(boxes, 2, PCR, VOXEL, GRID, STRIDE)
    got = peak_centres(heat, find_peaks(heat, 0.99), PCR, VOXEL, STRIDE)
    for frame, want_rows in enumerate([[(c, r, k) for c, r, k in cells], [(0, 0, 2)]]):
        want = sorted([(*centre_of(c, r), k - 1, 1.0) for c, r, k in want_rows], key=lambda t: (t[2], t[1], t[0]))
        assert_close_report(got[frame], torch.tensor(want, dtype=torch.float64), 0, 1e-6, f"frame {frame}")
    assert got[0].dtype == dtype


def test_peak_centres_gradient_reaches_the_scores():
    heat = torch.rand(1, 1, 6, 6, dtype=torch.float64, requires_grad=True)
    (c,) = peak_centres(heat, find_peaks(heat, 0.0, 1), PCR, VOXEL, STRIDE)
    (g,) = torch.autograd.grad(c[:, 3].sum(), heat)
    assert_equal_report(g != 0, find_peaks(heat, 0.0, 1), "gradient at the peaks")


# ------------------------------------------------------------------------------------------ soft count
def _sharp_map(device, dtype=torch.float64):
    """Peaks of 0.95 (two of class 0 in frame 0, one of class 1, and one in frame 1) with a narrow Gaussian
    falloff, on a 0.01 background."""
    heat = torch.full((2, 2, 16, 16), 0.01, dtype=torch.float64)
    blob = torch.from_numpy(window(1)) * 0.94 + 0.01
    for b, c, i, j in [(0, 0, 3, 3), (0, 0, 10, 12), (0, 1, 7, 7), (1, 0, 14, 1)]:
        heat[b, c, i - 1:i + 2, j - 1:j + 2] = blob
    return heat.to(dtype).to(device)


def test_soft_count_is_close_to_count_peaks_on_a_sharp_map(device):
    heat = _sharp_map(device)
    hard = count_peaks(heat, 0.5)
    soft = soft_count(heat, threshold=0.5, temperature=0.05)
    assert hard.tolist() == [[2, 1], [1, 0]]
    assert soft.shape == (2, 2) and soft.dtype == torch.float64
    assert_close_report(soft, hard.double(), 0, 0.02, "soft vs hard")
    # the background's share, by the docstring's rule: sigmoid((0.01 - 0.5) / 0.05) per flat local maximum
    flat = (_local_max_count(heat) - hard).double()
    assert_close_report(soft, hard * torch.sigmoid(torch.tensor((0.95 - 0.5) / 0.05, dtype=torch.float64))
                        + flat * torch.sigmoid(torch.tensor((0.01 - 0.5) / 0.05, dtype=torch.float64)), 1e-12, 0,
                        "soft count by hand")


def _local_max_count(heat):
    return count_peaks(heat, -math.inf)


def test_soft_count_gradient_at_the_local_maxima_only(device):
    heat = _sharp_map(device).requires_grad_(True)
    soft = soft_count(heat, 0.5, 2, 0.05)
    (g,) = torch.autograd.grad(soft.sum(), heat)
    maxima = find_peaks(heat, -math.inf, 2)
    assert (g[~maxima] == 0).all()  # off the local maxima: exactly zero
    assert (g[maxima] > 0).all()
    peaks = find_peaks(heat, 0.5, 2)
    assert (g[peaks] > 1e-3).all()  # sigmoid'(9) / 0.05 = 2.5e-3 at the real peaks
    # a frame of pure background gets (almost) no count, with the gradient still finite
    assert soft[1, 1].item() < 0.02 and torch.isfinite(g).all()


# ------------------------------------------------------------------------------------------ Otsu
def _rows(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    if kind == "uniform":
        return rng.random(n)
    if kind == "bimodal":
        return np.concatenate([rng.normal(0.2, 0.05, n // 2), rng.normal(0.8, 0.08, n - n // 2)])
    if kind == "constant":
        return np.full(n, 0.37)
    if kind == "ties":
        return rng.integers(0, 4, n).astype(np.float64) * 0.25
    if kind == "skewed":
        return rng.exponential(1.0, n) * 1e3 - 40
    raise ValueError(kind)


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
@pytest.mark.parametrize("bins", [2, 7, 16, 256])
def test_otsu_matches_skimage_bit_for_bit(device, dtype, bins):
    rng = np.random.default_rng(bins)
    npd = np.float32 if dtype == torch.float32 else np.float64
    for n in [1, 2, 3, 10, 97, 1000]:
        for kind in ["uniform", "bimodal", "constant", "ties", "skewed"]:
            rows = np.stack([_rows(kind, n, rng) for _ in range(6)]).astype(npd)
            got = otsu_threshold(torch.from_numpy(rows).to(device), bins)
            assert got.shape == (6,) and got.dtype == dtype
            want = torch.tensor([float(threshold_otsu(row, nbins=bins)) for row in rows], dtype=dtype)
            assert_equal_report(got, want, f"n={n} {kind}")


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
def test_otsu_fast_path_within_a_bin_except_near_ties(device, dtype):
    """exact=False: float64 scans. On rows without near-ties the same bin as skimage, or the next one; the
    documented exception: splits that tie to within skimage's rounding may resolve to another bin."""
    rng = np.random.default_rng(3)
    npd = np.float32 if dtype == torch.float32 else np.float64
    far = total = 0
    for bins in [16, 256]:
        for n in [10, 97, 1000]:
            for kind in ["uniform", "bimodal", "skewed"]:
                rows = np.stack([_rows(kind, n, rng) for _ in range(8)]).astype(npd)
                got = otsu_threshold(torch.from_numpy(rows).to(device), bins, exact=False).cpu()
                for i, row in enumerate(rows):
                    want = float(threshold_otsu(row, nbins=bins))
                    width = (float(row.max()) - float(row.min())) / bins
                    total += 1
                    far += abs(got[i].item() - want) > width * 1.001 + 1e-12
    assert far <= total // 100, f"{far} of {total} rows more than a bin from skimage"
    # a near-tie found by a sweep: two splits 33 bins apart whose variances differ below float32's rounding
    row = np.array([0.8016968369483948, 0.6363889575004578, 0.947799801826477, 0.36471205949783325,
                    0.4280623495578766], dtype=np.float32)
    want = float(threshold_otsu(row, nbins=64))
    assert otsu_threshold(torch.from_numpy(row).to(device), 64).item() == want == 0.42393189668655396
    assert otsu_threshold(torch.from_numpy(row).to(device), 64, exact=False).item() == 0.6334790587425232


def test_otsu_batches_over_leading_axes_and_masks(device):
    rng = np.random.default_rng(7)
    values = torch.from_numpy(rng.random((2, 3, 50))).to(device)
    mask = torch.from_numpy(rng.random((2, 3, 50)) < 0.6).to(device)
    mask[1, 2] = False  # no selected entry: NaN
    mask[0, 1] = False
    mask[0, 1, 7] = True  # one entry: constant, that value
    got = otsu_threshold(values, 64, mask).cpu()
    assert got.shape == (2, 3)
    for b in range(2):
        for p in range(3):
            sel = values[b, p][mask[b, p]].cpu().numpy()
            if sel.size == 0:
                assert math.isnan(got[b, p].item())
            else:
                assert got[b, p].item() == float(threshold_otsu(sel, nbins=64)), (b, p)
                assert math.isclose(otsu_threshold(values[b, p][mask[b, p]], 64, exact=False).item(),
                                    got[b, p].item(), abs_tol=1 / 64)
    assert got[0, 1].item() == values[0, 1, 7].item()
    # masked-out entries do not count, whatever they hold
    garbage = torch.where(mask, values, torch.tensor(1e9, dtype=torch.float64, device=device))
    torch.testing.assert_close(otsu_threshold(garbage, 64, mask).cpu(), got, rtol=0, atol=0, equal_nan=True)
    assert otsu_threshold(values, 64).shape == (2, 3)


def test_otsu_nonfinite_and_empty_rows(device):
    v = torch.tensor([[0.1, 0.9, 0.5], [0.1, math.nan, 0.5], [0.1, math.inf, 0.5]], device=device)
    got = otsu_threshold(v).cpu()
    assert math.isfinite(got[0].item()) and math.isnan(got[1].item()) and math.isnan(got[2].item())
    assert otsu_threshold(torch.zeros(3, 0, device=device)).isnan().all()
    assert otsu_threshold(torch.zeros(0, 5, device=device)).shape == (0,)
    assert otsu_threshold(torch.tensor([2.0, 2.0, 2.0], device=device)).item() == 2.0  # 1-D: a 0-d result


# ------------------------------------------------------------------------------------------ partitions
def test_partition_boxes_ten_by_ten():
    assert partition_boxes(10, 10, 1).tolist() == [[0, 10, 0, 10]]
    assert partition_boxes(10, 10, 1, 0.5).tolist() == [[0, 10, 0, 10]]
    # 2: the width (x) is split
    assert partition_boxes(4, 10, 2).tolist() == [[0, 4, 0, 5], [0, 4, 5, 10]]
    assert partition_boxes(4, 10, 2, 0.1).tolist() == [[0, 4, 0, 6], [0, 4, 4, 10]]  # ceil(0.5) = 1
    # 4 with delta 0.2: 5-cell regions grow by ceil(1.0) = 1 cell on each side, clipped to the map
    assert partition_boxes(10, 10, 4, 0.2).tolist() == [[0, 6, 0, 6], [0, 6, 4, 10], [4, 10, 0, 6], [4, 10, 4, 10]]
    assert partition_boxes(10, 10, 4, 0.21).tolist() == [[0, 7, 0, 7], [0, 7, 3, 10], [3, 10, 0, 7], [3, 10, 3, 10]]
    # 9: boundaries 0, 3, 6, 10; delta 0.2 grows 3-cell regions by ceil(0.6) = 1 and the 4-cell ones by ceil(0.8) = 1
    assert partition_boxes(10, 10, 9).tolist() == [[y0, y1, x0, x1] for y0, y1 in [(0, 3), (3, 6), (6, 10)]
                                                   for x0, x1 in [(0, 3), (3, 6), (6, 10)]]
    assert partition_boxes(10, 10, 9, 0.2)[4].tolist() == [2, 7, 2, 7]
    # 0.1 of 30 cells is 3, not 4 (floating point says 3.0000000000000004)
    assert partition_boxes(60, 60, 4, 0.1)[0].tolist() == [0, 33, 0, 33]


@pytest.mark.parametrize("pt", sorted(PARTITIONS))
@pytest.mark.parametrize("delta", [0.0, 0.15, 1.5])
def test_partition_boxes_cover_the_map(device, pt, delta):
    H, W = 13, 17
    regions = partition_boxes(H, W, pt, delta, device=device)
    assert regions.shape == (pt, 4) and regions.dtype == torch.int64 and regions.device.type == device
    cover = torch.zeros(H, W, dtype=torch.int64)
    for y0, y1, x0, x1 in regions.tolist():
        assert 0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W
        cover[y0:y1, x0:x1] += 1
    assert (cover >= 1).all()
    if delta == 0:
        assert (cover == 1).all()


# ------------------------------------------------------------------------------------------ merge
def c4(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def test_merge_centres_constructed_cases(device):
    # two centres of one class 0.1 m apart merge into the higher-scored one
    got = merge_centres(c4([1.0, 2.0, 0, 0.7], [1.1, 2.0, 0, 0.9]).to(device), 0.5)
    assert got.tolist() == [[1.1, 2.0, 0, 0.9]] and got.device.type == device
    # of two classes they do not; the result is sorted by decreasing score
    got = merge_centres(c4([1.0, 2.0, 0, 0.7], [1.1, 2.0, 1, 0.9]).to(device), 0.5)
    assert got.tolist() == [[1.1, 2.0, 1, 0.9], [1.0, 2.0, 0, 0.7]]
    # distance exactly the radius merges (<=); just beyond does not
    assert merge_centres(c4([0.0, 0.0, 0, 0.9], [3.0, 4.0, 0, 0.8]).to(device), 5.0).shape[0] == 1
    assert merge_centres(c4([0.0, 0.0, 0, 0.9], [3.0, 4.0, 0, 0.8]).to(device), 4.999).shape[0] == 2


@pytest.mark.parametrize("scores,kept", [
    ((0.9, 0.8, 0.7), ["a", "c"]),  # a kept; b near a: dropped; c: only the dropped b near it: kept
    ((0.9, 0.7, 0.8), ["a", "c"]),  # a, then c (far from a), then b near both: dropped
    ((0.8, 0.9, 0.7), ["b"]),  # b first drops a and c
    ((0.7, 0.8, 0.9), ["c", "a"]),  # c kept, b near c dropped, a far from c kept
])
def test_merge_centres_chain(device, scores, kept):
    """a - b - c on a line, 0.8 m apart, radius 1: a-b and b-c within, a-c (1.6 m) not."""
    pos = {"a": 0.0, "b": 0.8, "c": 1.6}
    rows = c4(*[[pos[k], 5.0, 2, s] for k, s in zip("abc", scores)])
    got = merge_centres(rows.to(device), 1.0).cpu()
    assert [next(k for k in pos if pos[k] == x) for x in got[:, 0].tolist()] == kept
    assert_equal_report(got, rows[_merge_centres_reference(rows, 1.0)], "reference")


@pytest.mark.parametrize("dtype", FLOATS, ids=IDS)
def test_merge_centres_random_matches_the_plain_loop(device, dtype, monkeypatch):
    from lidarops.models import counting

    g = torch.Generator().manual_seed(9)
    K = 300
    rows = torch.cat([torch.rand(K, 2, generator=g, dtype=torch.float64) * 10,
                      torch.randint(0, 3, (K, 1), generator=g).double(),
                      torch.rand(K, 1, generator=g, dtype=torch.float64).round(decimals=2)], 1).to(dtype)  # ties
    want = rows[_merge_centres_reference(rows, 0.8)]
    assert_equal_report(merge_centres(rows.to(device), 0.8).cpu(), want, "K=300")
    monkeypatch.setattr(counting, "_MERGE_ROWS", 7)  # the blocked conflict matrix
    assert_equal_report(merge_centres(rows.to(device), 0.8).cpu(), want, "blocks of 7 rows")
    assert merge_centres(rows[:0].to(device), 0.8).shape == (0, 4)
    assert merge_centres(rows.to(device), 0.0).shape[0] == rows[:, :3].unique(dim=0).shape[0]


# ------------------------------------------------------------------------------------------ weights
def test_partition_weights(device):
    counts = torch.tensor([[2, 0, 6, 0], [0, 0, 0, 0], [1, 1, 1, 1]], device=device)
    got = partition_weights(counts)
    assert got.dtype == torch.float32
    want = torch.tensor([[0.25 + 2 / 8, 0.25, 0.25 + 6 / 8, 0.25], [0.25] * 4, [0.5] * 4], dtype=torch.float64)
    assert_close_report(got, want, 1e-7, 0, "weights")
    soft = partition_weights(torch.tensor([[0.2, 0.3]], dtype=torch.float64, device=device))  # sum < 1: divided by 1
    assert soft.dtype == torch.float64 and soft.tolist() == [[0.5 + 0.2, 0.5 + 0.3]]


# ------------------------------------------------------------------------------------------ Chernoff selector
def test_chernoff_selector_two_clusters_and_an_empty_model(device):
    g = torch.Generator().manual_seed(12)
    a = torch.randn(20, 3, generator=g, dtype=torch.float64) * 0.1 + torch.tensor([5.0, 0, 0], dtype=torch.float64)
    b = torch.randn(30, 3, generator=g, dtype=torch.float64) * 0.1 - torch.tensor([5.0, 0, 0], dtype=torch.float64)
    feats = torch.cat([a, b]).to(device)
    best = torch.tensor([0] * 20 + [2] * 30, device=device)  # model 1 counts no frame best
    sel = ChernoffSelector().fit(feats, best, 3, epsilon=0.05)
    assert sel.counts.tolist() == [20, 0, 30]
    assert_close_report(sel.centres[0], a.mean(0), 1e-12, 1e-12, "omega_0")
    assert_close_report(sel.variances[2], (b - b.mean(0)).square().sum(1).mean(), 1e-12, 0, "xi_2^2")
    assert_equal_report(sel.select(feats).cpu(), best.cpu(), "own clusters")
    # model 1 is never chosen, not even at its (zero) centre or for features right on top of nothing else
    probe = torch.cat([torch.zeros(1, 3, dtype=torch.float64), torch.randn(50, 3, generator=g, dtype=torch.float64)])
    assert 1 not in sel.select(probe.to(device)).tolist()


def test_chernoff_factor_by_hand():
    """Model 0: frames (0, 0) and (2, 0): omega (1, 0), xi^2 = (1 + 1) / 2 = 1, n = 2; epsilon 0.5:
    P_0 = exp(-2 * 0.25 / 2) = exp(-0.25). Model 1: frames (10, 0), (10, 4): omega (10, 2), xi^2 = 4, n = 2,
    P_1 = exp(-2 * 0.25 / 8). Model 2: one frame (0, 10): xi = 0, P_2 = 1 (not 0)."""
    feats = torch.tensor([[0.0, 0], [2, 0], [10, 0], [10, 4], [0, 10]], dtype=torch.float64)
    sel = ChernoffSelector().fit(feats, torch.tensor([0, 0, 1, 1, 2]), 3, 0.5)
    assert sel.centres.tolist() == [[1.0, 0.0], [10.0, 2.0], [0.0, 10.0]]
    assert sel.variances.tolist() == [1.0, 4.0, 0.0]
    assert_close_report(sel.factors, torch.tensor([math.exp(-0.25), math.exp(-0.0625), 1.0], dtype=torch.float64),
                        1e-15, 0, "P_m")
    # at (5.5, 0): distances 4.5 and sqrt(4.5^2 + 4) = 4.92; scaled: 4.5 e^-0.25 = 3.50, 4.92 e^-0.0625 = 4.63
    f = torch.tensor([[5.5, 0.0], [9.0, 2.0], [0.5, 9.0]], dtype=torch.float64)
    dist = torch.cdist(f, sel.centres)
    assert_equal_report(sel.select(f), (dist * sel.factors).argmin(1), "argmin ||f - omega|| P")
    assert sel.select(f).tolist() == [0, 1, 2]
    # the factor decides where distance alone would not: (5.9, 0) is nearer model 1 (4.56) than model 0 (4.9) ...
    g = torch.tensor([[5.9, 0.0]], dtype=torch.float64)
    assert torch.cdist(g, sel.centres).argmin().item() == 1
    # ... but 4.9 e^-0.25 = 3.82 < 4.56 e^-0.0625 = 4.29
    assert sel.select(g).item() == 0


def test_chernoff_identical_frames_and_state_round_trip(device):
    """Three identical frames (0.1, 0.1): the mean would round to 0.1 + 1e-17 and xi^2 to 1e-34, making P = 0;
    detected exactly: xi = 0, P = 1."""
    feats = torch.tensor([[0.1, 0.1]] * 3 + [[1.0, 1.0], [3.0, 1.0]], dtype=torch.float64, device=device)
    sel = ChernoffSelector().fit(feats, torch.tensor([0, 0, 0, 1, 1], device=device), 2, 0.3)
    assert sel.variances[0].item() == 0.0 and sel.factors[0].item() == 1.0
    assert sel.centres[0].tolist() == [0.1, 0.1]
    state = sel.state_dict()
    assert set(state) == {"centres", "variances", "counts", "epsilon"}
    assert all(isinstance(v, torch.Tensor) for v in state.values())
    again = ChernoffSelector.from_state(state)
    probe = torch.randn(40, 2, dtype=torch.float64, device=device) * 2
    assert_equal_report(again.select(probe), sel.select(probe), "from_state")
    assert again.epsilon == 0.3
    buf = __import__("io").BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    loaded = ChernoffSelector.from_state(torch.load(buf, weights_only=True))
    assert_equal_report(loaded.select(probe), sel.select(probe), "through torch.save")
    assert sel.select(probe.float()).dtype == torch.int64  # float32 features on a float64 fit


# ------------------------------------------------------------------------------------------ bad input
H4 = torch.rand(2, 3, 5, 6)


@pytest.mark.parametrize("call,name", [
    (lambda: gaussian_radius([1.0], torch.ones(1)), "dx"),
    (lambda: gaussian_radius(torch.ones(2), torch.ones(3)), "dy"),
    (lambda: gaussian_radius(torch.ones(2), torch.ones(2, dtype=torch.bool)), "dy"),
    (lambda: gaussian_radius(torch.ones(2), torch.ones(2).to("meta")), "dy"),
    (lambda: gaussian_radius(torch.ones(2), torch.ones(2), 0.0), "min_overlap"),
    (lambda: gaussian_radius(torch.ones(2), torch.ones(2), 1.0), "min_overlap"),
    (lambda: gaussian_radius(torch.tensor([-1.0]), torch.ones(1)), "dx"),
    (lambda: gaussian_radius(torch.ones(1), torch.tensor([math.nan])), "dy"),
    (lambda: heatmap_targets(torch.zeros(2, 3, 7), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.zeros(3, 8), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8, dtype=torch.bool), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 0, PCR, VOXEL, GRID, 2), "num_classes"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR[:4], VOXEL, GRID, 2), "point_cloud_range"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, [0.16, 0.0], GRID, 2), "voxel_size"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, [0.16], GRID, 2), "voxel_size"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, VOXEL, [40, 0], 2), "grid_size"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, VOXEL, GRID, 0), "stride"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, VOXEL, GRID, 2, min_overlap=2), "min_overlap"),
    (lambda: heatmap_targets(torch.zeros(1, 3, 8), 3, PCR, VOXEL, GRID, 2, min_radius=-1), "min_radius"),
    (lambda: heatmap_targets(torch.tensor([[box(1, 1, 4)]]), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.tensor([[box(1, 1, 1.5)]]), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.tensor([[box(1, 1, -1)]]), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.tensor([[box(1, 1, 1, dx=-1.0)]]), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: heatmap_targets(torch.tensor([[box(1, 1, 1, dy=math.inf)]]), 3, PCR, VOXEL, GRID, 2), "boxes"),
    (lambda: focal_loss(H4[0], H4[0]), "pred"),
    (lambda: focal_loss(H4.long(), H4), "pred"),
    (lambda: focal_loss(H4, H4[:1]), "target"),
    (lambda: focal_loss(H4, H4 > 0.5), "target"),
    (lambda: focal_loss(H4, H4.to("meta")), "target"),
    (lambda: focal_loss(H4, H4, eps=0.0), "eps"),
    (lambda: find_peaks(H4[0], 0.5), "heatmap"),
    (lambda: find_peaks(H4.long(), 0.5), "heatmap"),
    (lambda: find_peaks(H4 > 0.5, 0.5), "heatmap"),
    (lambda: find_peaks(H4, 0.5, -1), "radius"),
    (lambda: find_peaks(H4, 0.5, 1.5), "radius"),
    (lambda: find_peaks(H4, 0.5, True), "radius"),
    (lambda: find_peaks(H4, math.nan), "threshold"),
    (lambda: find_peaks(H4, "0.5"), "threshold"),
    (lambda: find_peaks(H4, torch.rand(3, 2, 1, 1)), "threshold"),
    (lambda: find_peaks(H4, torch.rand(1, 2, 3, 5, 6)), "threshold"),
    (lambda: find_peaks(H4, torch.rand(2, 3, 1, 1).to("meta")), "threshold"),
    (lambda: count_peaks(torch.rand(3, 5, 6), 0.5), "heatmap"),
    (lambda: peak_centres(H4, H4, PCR, VOXEL, 2), "peaks"),
    (lambda: peak_centres(H4, (H4 > 2)[:1], PCR, VOXEL, 2), "peaks"),
    (lambda: peak_centres(H4, (H4 > 2).to("meta"), PCR, VOXEL, 2), "peaks"),
    (lambda: peak_centres(H4, H4 > 2, PCR, VOXEL, -2), "stride"),
    (lambda: peak_centres(H4, H4 > 2, "range", VOXEL, 2), "point_cloud_range"),
    (lambda: soft_count(H4.double().long(), 0.5), "heatmap"),
    (lambda: soft_count(H4, 0.5, temperature=0.0), "temperature"),
    (lambda: soft_count(H4, 0.5, radius=-2), "radius"),
    (lambda: otsu_threshold(torch.tensor(0.5)), "values"),
    (lambda: otsu_threshold(torch.arange(5)), "values"),
    (lambda: otsu_threshold(H4, bins=1), "bins"),
    (lambda: otsu_threshold(H4, bins=2.0), "bins"),
    (lambda: otsu_threshold(H4, mask=H4), "mask"),
    (lambda: otsu_threshold(H4, mask=(H4 > 0)[..., :2]), "mask"),
    (lambda: otsu_threshold(H4, mask=(H4 > 0).to("meta")), "mask"),
    (lambda: otsu_threshold(H4, exact="yes"), "exact"),
    (lambda: partition_boxes(10, 10, 3), "pt"),
    (lambda: partition_boxes(10, 10, 16), "pt"),
    (lambda: partition_boxes(10, 10, 4.0), "pt"),
    (lambda: partition_boxes(10, 10, 4, -0.1), "delta"),
    (lambda: partition_boxes(10, 10, 4, math.nan), "delta"),
    (lambda: partition_boxes(0, 10, 1), "height"),
    (lambda: partition_boxes(2, 10, 9), "height"),
    (lambda: partition_boxes(10, 1, 2), "width"),
    (lambda: merge_centres(torch.rand(5, 3), 1.0), "centres"),
    (lambda: merge_centres(torch.ones(5, 4, dtype=torch.int64), 1.0), "centres"),
    (lambda: merge_centres(torch.rand(5, 4), -1.0), "radius"),
    (lambda: merge_centres(torch.tensor([[0.0, math.nan, 0, 1]]), 1.0), "centres"),
    (lambda: partition_weights(torch.ones(3)), "region_counts"),
    (lambda: partition_weights(torch.ones(3, 0)), "region_counts"),
    (lambda: partition_weights(torch.ones(3, 2, dtype=torch.bool)), "region_counts"),
    (lambda: ChernoffSelector().fit(torch.rand(4), torch.zeros(4).long(), 2, 0.1), "features"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2).long(), torch.zeros(4).long(), 2, 0.1), "features"),
    (lambda: ChernoffSelector().fit(torch.rand(0, 2), torch.zeros(0).long(), 2, 0.1), "features"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(4), 2, 0.1), "best"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(3).long(), 2, 0.1), "best"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.tensor([0, 1, 2, 0]), 2, 0.1), "best"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(4).long().to("meta"), 2, 0.1), "best"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(4).long(), 0, 0.1), "num_models"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(4).long(), 2, 0.0), "epsilon"),
    (lambda: ChernoffSelector().fit(torch.rand(4, 2), torch.zeros(4).long(), 2, 0.1).select(torch.rand(4, 3)),
     "features"),
    (lambda: ChernoffSelector().select(torch.rand(4, 3)), "fit"),
    (lambda: ChernoffSelector.from_state({"centres": torch.rand(2, 2)}), "state"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_bad_arguments_raise_value_error_naming_them(call, name):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call()


def test_value_checks_can_be_turned_off():
    """Off: a class id beyond num_classes is skipped rather than refused, a negative size drawn at min_radius."""
    boxes = torch.tensor([[box(1, 1, 4), box(5, 5, 1, dx=-1.0)]])
    with lidarops.validation(False):
        heat = heatmap_targets(boxes, 3, PCR, VOXEL, GRID, 2)
    assert count_peaks(heat, 0.99).tolist() == [[1, 0, 0]]
