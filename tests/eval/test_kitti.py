"""Tests of the KITTI evaluation (lidarops.eval.kitti).

Expected values are derived by hand from the protocol (comments), or come from a float64 re-implementation
of the whole protocol in this file (``ref_evaluate``: per-frame Python loops, its own threshold rule, IoUs
from the float64 polygon-clipping references of lidarops.ops.boxes).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers.kitti import random_annos
from lidarops.data.formats.kitti import (
    KittiCalib,
    boxes_to_kitti_labels,
    camera_to_lidar_boxes,
    kitti_fov_mask,
    read_label,
    write_kitti_frame,
    write_label,
)
from lidarops.data.frame import CLASSES
from lidarops.data.synthetic import SyntheticFrames
from lidarops.eval import kitti
from lidarops.ops.boxes import _box_iou_3d_reference, _box_iou_bev_reference

DIFFS = ("easy", "moderate", "hard")

# ---------------------------------------------------------------------------------------------
# the reference: the protocol written out one frame, one object at a time
# ---------------------------------------------------------------------------------------------
REF_MIN_HEIGHT, REF_MAX_OCC, REF_MAX_TRUNC = (40, 25, 25), (0, 1, 2), (0.15, 0.3, 0.5)
REF_OVERLAPS = {  # [strict, loose] x [bbox, bev, 3d]
    "car": [[0.7, 0.7, 0.7], [0.7, 0.5, 0.5]], "pedestrian": [[0.5, 0.5, 0.5], [0.5, 0.25, 0.25]],
    "cyclist": [[0.5, 0.5, 0.5], [0.5, 0.25, 0.25]], "van": [[0.7, 0.7, 0.7], [0.7, 0.5, 0.5]],
}
NO_DET = -10000000.0


def ref_get_thresholds(scores, num_gt):
    scores = sorted((float(s) for s in scores), reverse=True)
    current, out = 0, []
    for i, score in enumerate(scores):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < len(scores) - 1 else l_recall
        if r_recall - current < current - l_recall and i < len(scores) - 1:
            continue
        out.append(score)
        current += 1 / 40.0
    return out


def ref_clean(gt, dt, cls, diff):
    cls = cls.lower()
    ignored_gt, ignored_dt, dontcare, num_valid = [], [], [], 0
    for i, name in enumerate(gt["name"]):
        name_l = str(name).lower()
        if name_l == cls:
            valid = 1
        elif (cls, name_l) in (("car", "van"), ("pedestrian", "person_sitting")):
            valid = 0
        else:
            valid = -1
        bbox = gt["bbox"][i]
        too_hard = (gt["occluded"][i] > REF_MAX_OCC[diff] or gt["truncated"][i] > REF_MAX_TRUNC[diff]
                    or bbox[3] - bbox[1] <= REF_MIN_HEIGHT[diff])
        if valid == 1 and not too_hard:
            ignored_gt.append(0)
            num_valid += 1
        elif valid == 0 or valid == 1:
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
        if name == "DontCare":
            dontcare.append(bbox)
    for j, name in enumerate(dt["name"]):
        if abs(dt["bbox"][j][3] - dt["bbox"][j][1]) < REF_MIN_HEIGHT[diff]:
            ignored_dt.append(1)
        else:
            ignored_dt.append(0 if str(name).lower() == cls else -1)
    return ignored_gt, ignored_dt, dontcare, num_valid


def ref_box_overlap_2d(a, b, criterion):
    iw = min(a[2], b[2]) - max(a[0], b[0])
    ih = min(a[3], b[3]) - max(a[1], b[1])
    if iw <= 0 or ih <= 0:
        return 0.0
    area_a = (a[2] - a[0]) * (a[3] - a[1])
    return iw * ih / (area_a + (b[2] - b[0]) * (b[3] - b[1]) - iw * ih if criterion == "iou" else area_a)


def ref_world_boxes(anno):
    """Camera boxes as (x, y, z, dx, dy, dz, heading) in the frame x = x_cam, y = z_cam, z = -y_cam (up),
    where the length axis (cos ry, -sin ry) of the (x, z) camera plane has heading -ry."""
    loc, dims, ry = (np.asarray(anno[k], dtype=np.float64) for k in ("location", "dimensions", "rotation_y"))
    loc, dims = loc.reshape(-1, 3), dims.reshape(-1, 3)
    return torch.tensor(np.stack([loc[:, 0], loc[:, 2], -loc[:, 1] + dims[:, 1] / 2, dims[:, 0], dims[:, 2],
                                  dims[:, 1], -ry.reshape(-1)], 1))


def ref_overlaps(gt, dt, metric):
    """(D, G) overlaps of one frame."""
    d, g = len(dt["name"]), len(gt["name"])
    if metric == "bbox":
        return [[ref_box_overlap_2d(dt["bbox"][j], gt["bbox"][i], "iou") for i in range(g)] for j in range(d)]
    if d == 0 or g == 0:
        return [[0.0] * g for _ in range(d)]
    fn = _box_iou_bev_reference if metric == "bev" else _box_iou_3d_reference
    return fn(ref_world_boxes(dt), ref_world_boxes(gt)).tolist()


def ref_statistics(overlaps, gt, dt, ignored_gt, ignored_dt, dontcare, metric, min_overlap, thresh, compute_fp,
                   compute_aos):
    """One frame: (tp, fp, fn, similarity, scores of the true positives)."""
    scores = [float(s) for s in dt["score"]]
    below = [compute_fp and s < thresh for s in scores]
    assigned = [False] * len(scores)
    tp = fp = fn = 0
    similarity, matched = 0.0, []
    for i in range(len(ignored_gt)):
        if ignored_gt[i] == -1:
            continue
        det, valid, max_overlap, took_ignored = -1, NO_DET, 0.0, False
        for j in range(len(scores)):
            if ignored_dt[j] == -1 or assigned[j] or below[j] or not overlaps[j][i] > min_overlap:
                continue
            if not compute_fp:
                if scores[j] > valid:
                    det, valid = j, scores[j]
            elif (overlaps[j][i] > max_overlap or took_ignored) and ignored_dt[j] == 0:
                det, valid, max_overlap, took_ignored = j, 1.0, overlaps[j][i], False
            elif valid == NO_DET and ignored_dt[j] == 1:
                det, valid, took_ignored = j, 1.0, True
        if valid == NO_DET:
            fn += ignored_gt[i] == 0
        elif ignored_gt[i] == 1 or ignored_dt[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            matched.append(scores[det])
            if compute_aos:
                similarity += (1.0 + math.cos(gt["alpha"][i] - dt["alpha"][det])) / 2.0
            assigned[det] = True
    if compute_fp:
        for j in range(len(scores)):
            if assigned[j] or ignored_dt[j] != 0 or below[j]:
                continue
            in_dontcare = metric == "bbox" and any(
                ref_box_overlap_2d(dt["bbox"][j], box, "area") > min_overlap for box in dontcare)
            fp += not in_dontcare
    return tp, fp, fn, similarity, matched


def ref_evaluate(gt_annos, dt_annos, classes, overlaps=REF_OVERLAPS):
    compute_aos = False
    for dt in dt_annos:
        if len(dt["alpha"]):
            compute_aos = dt["alpha"][0] != -10
            break
    frame_overlaps = {m: [ref_overlaps(g, d, m) for g, d in zip(gt_annos, dt_annos)] for m in ("bbox", "bev", "3d")}
    out = {}
    for cls in classes:
        for diff in range(3):
            cleaned = [ref_clean(g, d, cls, diff) for g, d in zip(gt_annos, dt_annos)]
            num_gt = sum(c[3] for c in cleaned)
            for s, suffix in enumerate(("", "_loose")):
                for m, metric in enumerate(("bbox", "bev", "3d")):
                    min_overlap = overlaps[cls.lower()][s][m]
                    aos = compute_aos and metric == "bbox"

                    def stats(f, thresh, compute_fp):
                        ig, idt, dc, _ = cleaned[f]
                        return ref_statistics(frame_overlaps[metric][f], gt_annos[f], dt_annos[f], ig, idt, dc, metric,
                                              min_overlap, thresh, compute_fp, aos)

                    matched = [s_ for f in range(len(gt_annos)) for s_ in stats(f, 0.0, False)[4]]
                    thresholds = ref_get_thresholds(matched, num_gt)
                    prec, orient = [0.0] * 41, [0.0] * 41
                    for t, thresh in enumerate(thresholds):
                        tp = fp = sim = 0.0
                        for f in range(len(gt_annos)):
                            a, b, _, c, _ = stats(f, thresh, True)
                            tp, fp, sim = tp + a, fp + b, sim + c
                        prec[t], orient[t] = tp / (tp + fp), sim / (tp + fp)
                    for name, curve in ((metric, prec), ("aos", orient)):
                        if name == "aos" and not aos:
                            continue
                        mono = [max(curve[i:]) for i in range(41)]
                        key = f"{cls}_{name}_{DIFFS[diff]}"
                        out[f"{key}_R11{suffix}"] = sum(mono[0::4]) / 11 * 100
                        out[f"{key}_R40{suffix}"] = sum(mono[1:]) / 40 * 100
    return out


def assert_results_equal(got: dict, want: dict, tol: float = 1e-9) -> None:
    assert set(got) == set(want), sorted(set(got) ^ set(want))
    worst = max(want, key=lambda k: abs(got[k] - want[k]))
    assert abs(got[worst] - want[worst]) <= tol, f"{worst}: got {got[worst]!r}, want {want[worst]!r}"


# ---------------------------------------------------------------------------------------------
# building annotations by hand
# ---------------------------------------------------------------------------------------------
def obj(name, x, z, bbox, score=None, lhw=(3.9, 1.55, 1.6), ry=0.0, occluded=0, truncated=0.0, alpha=None):
    """One object at camera (x, 1.65, z) (bottom centre on the ground)."""
    o = dict(name=name, location=(x, 1.65, z), dimensions=lhw, rotation_y=ry, bbox=bbox, occluded=occluded,
             truncated=truncated, alpha=ry - math.atan2(x, z) if alpha is None else alpha)
    if score is not None:
        o["score"] = score
    return o


def anno(objects):
    keys = ("name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score")
    out = {}
    for key in keys:
        if objects and key not in objects[0]:
            continue
        width = {"bbox": 4, "dimensions": 3, "location": 3}.get(key)
        values = [o[key] for o in objects]
        out[key] = (np.array(values, dtype=str) if key == "name" else
                    np.array(values, dtype=np.float64).reshape((-1, width) if width else (-1,)))
    return out


def box_2d(i, row=0, height=60):
    """A 2D box in column i, row ``row``; boxes of different (i, row) are disjoint."""
    return (20 + 110 * i, 40 + 120 * row, 120 + 110 * i, 40 + 120 * row + height)


# Two easy Cars A, B hit at scores 0.8 and 0.7, and a third detection X at 0.9 away from them.
# N = 2 counted gts: get_thresholds takes both matched scores (i = 0: r - c = 1 - 0 is not < 0 - 0.5;
# i = 1 is the last), so the curve has two points.
#   X a false positive: precision 1/2 at 0.8, 2/3 at 0.7 -> monotone [2/3, 2/3, 0, ...]
#       R11 = (2/3) / 11 * 100, R40 = (2/3) / 40 * 100
#   X not counted: precision [1, 1, 0, ...] -> R11 = 100 / 11, R40 = 100 / 40
FP_R11, FP_R40 = 200 / 33, 5 / 3
CLEAN_R11, CLEAN_R40 = 100 / 11, 2.5
# one counted gt, hit: a single threshold, precision [1, 0, ...] -> R11 = 100 / 11, R40 = 0 (position 0 is not
# among R40's positions); with X a false positive above it: precision [1/2, 0, ...] -> R11 = 50 / 11
ONE_R11, ONE_HALF_R11 = 100 / 11, 50 / 11

A = dict(x=-4.0, z=20.0, bbox=box_2d(0))
B = dict(x=4.0, z=20.0, bbox=box_2d(1))
X = dict(x=0.0, z=40.0, bbox=box_2d(2))


def two_cars(gt_extra=(), x_det=True, b_gt=None, b_dt=None, x_kw=None):
    gts = [obj("Car", **A), obj("Car", **(b_gt or B))] + list(gt_extra)
    dts = [obj("Car", **A, score=0.8), obj("Car", **(b_dt or b_gt or B), score=0.7)]
    if x_det:
        dts.append(obj("Car", **{**X, **(x_kw or {})}, score=0.9))
    return [anno(gts)], [anno(dts)]


def values(results, cls="Car", metric="3d", suffix=""):
    """[R11, R40] of easy, moderate, hard, flat."""
    return [results[f"{cls}_{metric}_{d}_{r}{suffix}"] for d in DIFFS for r in ("R11", "R40")]


def approx(pairs):
    """pytest.approx of [(R11, R40) easy, moderate, hard] against :func:`values`."""
    return pytest.approx([v for pair in pairs for v in pair], abs=1e-9)


# ---------------------------------------------------------------------------------------------
# tests
# ---------------------------------------------------------------------------------------------
def perfect_frames(num_frames=45, seed=0):
    """Per frame: an easy Car, Pedestrian and Cyclist on a grid, a moderate-only Car (occluded 1), a hard-only
    Pedestrian (truncated 0.4), a Car too small for any difficulty, a Van, a Person_sitting and a DontCare
    region; detections: every object but the DontCare, exactly, with random scores."""
    rng = np.random.default_rng(seed)
    gts, dts = [], []
    for f in range(num_frames):
        z = 10.0 + f % 7
        objs = [
            obj("Car", -12.0, z, box_2d(0)), obj("Pedestrian", -6.0, z, box_2d(1), lhw=(0.8, 1.75, 0.6)),
            obj("Cyclist", 0.0, z, box_2d(2), lhw=(1.7, 1.7, 0.6), ry=0.3), obj("Car", 6.0, z, box_2d(3), occluded=1),
            obj("Pedestrian", 12.0, z, box_2d(4), lhw=(0.8, 1.75, 0.6), truncated=0.4),
            obj("Car", -12.0, z + 20, box_2d(5, height=20)), obj("Van", -6.0, z + 20, box_2d(6), lhw=(5, 2, 1.9)),
            obj("Person_sitting", 0.0, z + 20, box_2d(7), lhw=(0.8, 1.3, 0.6)),
        ]
        dc = obj("DontCare", -1000.0, -1000.0, box_2d(8), lhw=(-1, -1, -1), ry=-10.0, alpha=-10.0)
        gts.append(anno(objs + [dc]))
        dts.append(anno([{**o, "score": float(rng.random())} for o in objs]))
    return gts, dts


def test_perfect_detections_score_100_and_none_score_0():
    gts, dts = perfect_frames()
    text, results = kitti.evaluate(gts, dts)
    # 45 counted gts per class and difficulty (>= 41: one threshold per recall position)
    assert len(results) == 3 * 4 * 3 * 2 * 2
    bad = {k: v for k, v in results.items() if v != pytest.approx(100.0, abs=1e-9)}
    assert not bad, bad
    assert "Car AP@0.70, 0.70, 0.70:" in text and "Car AP_R40@0.70, 0.50, 0.50:" in text
    _, empty = kitti.evaluate(gts, [anno([]) for _ in gts])
    assert empty and all(v == 0.0 for v in empty.values())
    assert not any("_aos_" in k for k in empty)  # no detections: no alpha to judge AOS by
    # fewer than 41 counted gts: R40 = (T - 1) / 40 with T thresholds, even for perfect detections
    _, few = kitti.evaluate(gts[:20], dts[:20])
    assert few["Car_3d_easy_R40"] == pytest.approx(19 / 40 * 100) and few["Car_3d_easy_R11"] == pytest.approx(500 / 11)


def test_hand_built_precision_recall_curve():
    # 10 easy Cars; detections, by descending score: TP .95, TP .90, FP .85, TP .80, FP .75, TP .70, TP .60,
    # FP .55, TP .50, TP .40 (3 gts missed). N = 10: every matched score is a threshold (the rule skips i
    # only when r - c < c - l, but c = k / 40 stays below l = (i + 1) / 10 here).
    # precision at the 7 thresholds: 1/1, 2/2, 3/4, 4/6, 5/7, 6/9, 7/10
    # monotone (max over later):      1,   1,   3/4, 5/7, 5/7, 7/10, 7/10, then 0
    # R11 = (p0 + p4) / 11 * 100 = (1 + 5/7) / 11 * 100;  R40 = (p1 + ... + p6) / 40 * 100
    r11 = (1 + 5 / 7) / 11 * 100
    r40 = (1 + 3 / 4 + 5 / 7 + 5 / 7 + 7 / 10 + 7 / 10) / 40 * 100
    gts = [obj("Car", -20.0 + 4 * i, 25.0, box_2d(i), ry=0.1 * i) for i in range(10)]
    tp_scores = [0.95, 0.90, 0.80, 0.70, 0.60, 0.50, 0.40]
    dts = [obj("Car", -20.0 + 4 * i, 25.0, box_2d(i), ry=0.1 * i, score=s) for i, s in enumerate(tp_scores)]
    dts += [obj("Car", -20.0 + 4 * i, 60.0, box_2d(i, row=1), score=s) for i, s in enumerate([0.85, 0.75, 0.55])]
    _, results = kitti.evaluate([anno(gts)], [anno(dts)], classes=("Car",))
    for metric in ("bbox", "bev", "3d", "aos"):
        for suffix in ("", "_loose"):
            assert values(results, "Car", metric, suffix) == approx([(r11, r40)] * 3), metric

    # AOS: the hits at .90 and .70 have the right box but a heading off by pi (similarity (1 + cos pi) / 2 = 0)
    # similarity / (tp + fp) at the thresholds: 1/1, 1/2, 2/4, 2/6, 3/7, 4/9, 5/10 -> monotone 1, then 1/2 x 6
    flipped = [dict(d, rotation_y=d["rotation_y"] + math.pi, alpha=d["alpha"] + math.pi) if d["score"] in (0.9, 0.7)
               else d for d in dts]
    _, results = kitti.evaluate([anno(gts)], [anno(flipped)], classes=("Car",))
    assert values(results, "Car", "aos") == approx([(1.5 / 11 * 100, 3 / 40 * 100)] * 3)
    assert values(results, "Car", "3d") == approx([(r11, r40)] * 3)
    # every hit flipped: aos 0, the boxes still match
    all_flipped = [dict(d, rotation_y=d["rotation_y"] + math.pi, alpha=d["alpha"] + math.pi) for d in dts]
    _, results = kitti.evaluate([anno(gts)], [anno(all_flipped)], classes=("Car",))
    assert values(results, "Car", "aos") == approx([(0.0, 0.0)] * 3)
    assert values(results, "Car", "bev") == approx([(r11, r40)] * 3)


def test_false_positive_baseline():
    _, results = kitti.evaluate(*two_cars(), classes=("Car",))
    for metric in ("bbox", "bev", "3d"):
        assert values(results, "Car", metric) == approx([(FP_R11, FP_R40)] * 3)
    _, results = kitti.evaluate(*two_cars(x_det=False), classes=("Car",))
    assert values(results, "Car", "3d") == approx([(CLEAN_R11, CLEAN_R40)] * 3)


def test_dontcare_removes_false_positives_in_2d_only():
    region = obj("DontCare", -1000.0, -1000.0, (X["bbox"][0] - 5, X["bbox"][1] - 5, X["bbox"][2] + 5, X["bbox"][3] + 5),
                 lhw=(-1, -1, -1), ry=-10.0, alpha=-10.0)
    _, results = kitti.evaluate(*two_cars(gt_extra=[region]), classes=("Car",))
    assert values(results, "Car", "bbox") == approx([(CLEAN_R11, CLEAN_R40)] * 3)
    for metric in ("bev", "3d"):  # kitti_object_eval_python applies DontCare to the 2D metric only
        assert values(results, "Car", metric) == approx([(FP_R11, FP_R40)] * 3)
    # X half inside the region: intersection / X's area = 0.5 < 0.7, still a false positive
    x0, y0, x1, y1 = X["bbox"]
    half = dict(region, bbox=((x0 + x1) / 2, y0, x1 + 50, y1))
    _, results = kitti.evaluate(*two_cars(gt_extra=[half]), classes=("Car",))
    assert values(results, "Car", "bbox") == approx([(FP_R11, FP_R40)] * 3)


def test_neighbouring_and_other_classes():
    van = obj("Van", **X)
    # X on a Van: ignored for Car (neither a hit nor a false positive)
    _, results = kitti.evaluate(*two_cars(gt_extra=[van]), classes=("Car",))
    for metric in ("bbox", "bev", "3d"):
        assert values(results, "Car", metric) == approx([(CLEAN_R11, CLEAN_R40)] * 3)
    # the same box as a Truck (not Car's neighbour): X is a false positive
    _, results = kitti.evaluate(*two_cars(gt_extra=[obj("Truck", **X)]), classes=("Car",))
    assert values(results, "Car", "3d") == approx([(FP_R11, FP_R40)] * 3)
    # an unmatched Van is no miss; a detection called "Van" is not a Car detection
    gts, dts = two_cars(gt_extra=[van], x_det=False)
    gts_plain, _ = two_cars(x_det=False)
    dts_van = [anno([obj("Car", **A, score=0.8), obj("Car", **B, score=0.7), obj("Van", **X, score=0.9)])]
    _, with_van = kitti.evaluate(gts, dts_van, classes=("Car",))
    assert values(with_van, "Car", "3d") == approx([(CLEAN_R11, CLEAN_R40)] * 3)
    # ... but it is a Van detection: for the class Van, one Van gt hit, Cars not considered
    _, as_van = kitti.evaluate(gts, dts_van, classes=("Car", "Van"))
    assert values(as_van, "Van", "3d") == approx([(ONE_R11, 0.0)] * 3)
    # Person_sitting for Pedestrian: a Pedestrian detection on a sitting person is not a false positive
    ped = dict(lhw=(0.8, 1.75, 0.6))
    gts = [anno([obj("Pedestrian", **A, **ped), obj("Pedestrian", **B, **ped), obj("Person_sitting", **X, **ped)])]
    dts = [anno([obj("Pedestrian", **A, **ped, score=0.8), obj("Pedestrian", **B, **ped, score=0.7),
                 obj("Pedestrian", **X, **ped, score=0.9)])]
    _, results = kitti.evaluate(gts, dts, classes=("Pedestrian", "Cyclist"))
    assert values(results, "Pedestrian", "3d") == approx([(CLEAN_R11, CLEAN_R40)] * 3)
    assert values(results, "Cyclist", "3d") == approx([(0.0, 0.0)] * 3)
    # Pedestrians do not change the Car results
    gts, dts = two_cars()
    gts[0] = anno([obj("Car", **A), obj("Car", **B), obj("Pedestrian", 8.0, 30.0, box_2d(5), **ped)])
    dts[0] = anno([obj("Car", **A, score=0.8), obj("Car", **B, score=0.7), obj("Car", **X, score=0.9),
                   obj("Pedestrian", 8.0, 30.0, box_2d(5), **ped, score=0.95)])
    _, results = kitti.evaluate(gts, dts, classes=("Car",))
    assert values(results, "Car", "3d") == approx([(FP_R11, FP_R40)] * 3)


@pytest.mark.parametrize("b_gt, per_difficulty", [
    # B 30 px high (<= 40: not easy): at easy B is ignored and so is its detection (< 40 px): one counted gt
    (dict(B, bbox=box_2d(1, height=30)), [(ONE_HALF_R11, 0.0), (FP_R11, FP_R40), (FP_R11, FP_R40)]),
    # exactly 40 px: a gt needs > 40 to be easy
    (dict(B, bbox=box_2d(1, height=40)), [(ONE_HALF_R11, 0.0), (FP_R11, FP_R40), (FP_R11, FP_R40)]),
    # 20 px: ignored at every difficulty
    (dict(B, bbox=box_2d(1, height=20)), [(ONE_HALF_R11, 0.0)] * 3),
    (dict(B, occluded=1), [(ONE_HALF_R11, 0.0), (FP_R11, FP_R40), (FP_R11, FP_R40)]),
    (dict(B, occluded=2), [(ONE_HALF_R11, 0.0), (ONE_HALF_R11, 0.0), (FP_R11, FP_R40)]),
    (dict(B, occluded=3), [(ONE_HALF_R11, 0.0)] * 3),
    (dict(B, truncated=0.2), [(ONE_HALF_R11, 0.0), (FP_R11, FP_R40), (FP_R11, FP_R40)]),
    (dict(B, truncated=0.4), [(ONE_HALF_R11, 0.0), (ONE_HALF_R11, 0.0), (FP_R11, FP_R40)]),
    (dict(B, truncated=0.6), [(ONE_HALF_R11, 0.0)] * 3),
], ids=["height30", "height40", "height20", "occ1", "occ2", "occ3", "trunc0.2", "trunc0.4", "trunc0.6"])
def test_difficulty_filter_on_ground_truths(b_gt, per_difficulty):
    # X (0.9) is a false positive; B's detection (0.7, B's boxes) matches B. Where B is ignored, one gt
    # counts: one threshold (0.8), where A and X are in: precision 1/2 -> R11 = 50 / 11, R40 = 0.
    _, results = kitti.evaluate(*two_cars(b_gt=b_gt), classes=("Car",))
    for metric in ("bbox", "bev", "3d"):
        assert values(results, "Car", metric) == approx(per_difficulty), metric


def test_low_detections_are_ignored_not_false_positives():
    # X only 30 px high: ignored at easy (< 40 px), a false positive at moderate and hard (>= 25 px)
    _, results = kitti.evaluate(*two_cars(x_kw=dict(bbox=box_2d(2, height=30))), classes=("Car",))
    assert values(results, "Car", "3d") == approx([(CLEAN_R11, CLEAN_R40), (FP_R11, FP_R40), (FP_R11, FP_R40)])
    # ... whatever its class: the official clean_data marks every detection under the minimum height ignored.
    # A 30 px Pedestrian detection (0.9) on Car B: at easy the first pass gives B that ignored detection (the
    # highest-scoring one above the overlap), so B's Car detection (0.7) is no hit and there is one threshold
    # (0.8): R11 = 100 / 11, R40 = 0. At moderate (>= 25 px) it is a detection of another class, not
    # considered: two thresholds, precision 1 -> CLEAN. (2D: its 30 px box overlaps B's 60 px one by 0.5 only.)
    ped = obj("Pedestrian", B["x"], B["z"], (B["bbox"][0], B["bbox"][1], B["bbox"][2], B["bbox"][1] + 30), score=0.9)
    gts, dts = two_cars(x_det=False)
    dts = [anno([obj("Car", **A, score=0.8), obj("Car", **B, score=0.7), ped])]
    _, results = kitti.evaluate(gts, dts, classes=("Car",))
    for metric in ("bev", "3d"):
        assert values(results, "Car", metric) == approx([(ONE_R11, 0.0), (CLEAN_R11, CLEAN_R40),
                                                                (CLEAN_R11, CLEAN_R40)]), metric
    assert values(results, "Car", "bbox") == approx([(CLEAN_R11, CLEAN_R40)] * 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_float64_reference(seed):
    gts, dts = random_annos(25, seed=seed, num_gt=12, num_dt=15)
    if seed == 1:  # the first detection without an angle: no AOS
        dts[0]["alpha"][0] = -10.0
    classes = ("Car", "Pedestrian", "Cyclist") if seed != 2 else ("Car", "Pedestrian", "Cyclist", "Van")
    text, got = kitti.evaluate(gts, dts, classes=classes)
    want = ref_evaluate(gts, dts, classes)
    assert_results_equal(got, want)
    assert ("aos  AP:" in text) == (seed != 1)
    assert any(v > 0 for v in want.values()) and len({round(v, 6) for v in want.values()}) > 20


def test_matches_reference_with_custom_overlaps():
    gts, dts = random_annos(10, seed=7, num_gt=10, num_dt=12)
    custom = {"Car": ((0.6, 0.5, 0.4), (0.3, 0.2, 0.1))}
    _, got = kitti.evaluate(gts, dts, classes=("Car",), min_overlaps=custom)
    assert_results_equal(got, ref_evaluate(gts, dts, ("Car",), {"car": [[0.6, 0.5, 0.4], [0.3, 0.2, 0.1]]}))
    _, triple = kitti.evaluate(gts, dts, classes=("Car",), min_overlaps={"Car": (0.6, 0.5, 0.4)})
    assert_results_equal(triple, ref_evaluate(gts, dts, ("Car",), {"car": [[0.6, 0.5, 0.4]] * 2}))


def test_get_thresholds_equals_sequential_rule():
    rng = np.random.default_rng(0)
    for trial in range(60):
        n = int(rng.integers(0, 3000)) if trial % 10 else int(rng.integers(0, 5))
        num_gt = n + int(rng.integers(0 if n else 1, 2 * n + 3))
        scores = rng.random(n)
        if trial % 3 == 0:
            scores = np.round(scores, 2)  # ties
        got = kitti.get_thresholds(scores, num_gt)
        assert got.tolist() == ref_get_thresholds(scores, num_gt), (n, num_gt)
        assert len(got) <= 41


def test_subset_of_metrics_and_bad_metric():
    gts, dts = random_annos(4, seed=3)
    text, results = kitti.evaluate(gts, dts, classes=("Car",), metrics=("3d",))
    assert set(results) == {f"Car_3d_{d}_{r}{s}" for d in DIFFS for r in ("R11", "R40") for s in ("", "_loose")}
    assert "bbox AP" not in text and "3d   AP:" in text
    _, full = kitti.evaluate(gts, dts, classes=("Car",))
    assert all(results[k] == full[k] for k in results)
    # without image boxes: no bbox / aos metric
    strip = [{k: v for k, v in a.items() if k != "bbox"} for a in gts], [{k: v for k, v in a.items() if k != "bbox"}
                                                                         for a in dts]
    _, no_bbox = kitti.evaluate(*strip, classes=("Car",))
    assert {k.split("_")[1] for k in no_bbox} == {"bev", "3d"}
    with pytest.raises(ValueError, match="unknown metric"):
        kitti.evaluate(gts, dts, metrics=("bbox", "iou"))


# ---------------------------------------------------------------------------------------------
# annotation formats
# ---------------------------------------------------------------------------------------------
# KITTI's label format (devkit readme): type truncated occluded alpha left top right bottom h w l x y z rotation_y
LABEL_LINE = "Car 0.00 0 -1.20 300.00 160.00 420.00 230.00 1.50 1.60 4.00 -1.00 1.65 18.00 -1.25\n"
RESULT_LINE = LABEL_LINE.strip() + " 0.87\n"


def test_dimensions_order_l_h_w(tmp_path):
    (tmp_path / "label_2").mkdir()
    (tmp_path / "results").mkdir()
    (tmp_path / "label_2" / "000003.txt").write_text(LABEL_LINE + "DontCare -1 -1 -10 0.00 0.00 50.00 50.00 -1 -1 -1 "
                                                                  "-1000 -1000 -1000 -10\n")
    (tmp_path / "results" / "000003.txt").write_text(RESULT_LINE)
    gt = kitti.read_annos(tmp_path / "label_2", frame_ids=[3])
    dt = kitti.read_annos(tmp_path / "results")
    assert gt[0]["dimensions"][0].tolist() == [4.0, 1.5, 1.6] and dt[0]["score"].tolist() == pytest.approx([0.87])
    assert "score" not in gt[0] and gt[0]["name"].tolist() == ["Car", "DontCare"]
    # a prediction dict as OpenPCDet's generate_prediction_dicts makes it: dimensions l, h, w
    pred = anno([obj("Car", -1.0, 18.0, (300.0, 160.0, 420.0, 230.0), score=0.87, lhw=(4.0, 1.5, 1.6), ry=-1.25,
                     alpha=-1.2)])
    for dts in (dt, [pred]):
        _, results = kitti.evaluate(gt, dts, classes=("Car",))
        # one counted gt, hit: R11 = 100 / 11 (a mix-up of h, w, l gives IoU < 0.7 and 0)
        for metric in ("bev", "3d"):
            assert values(results, "Car", metric) == approx([(ONE_R11, 0.0)] * 3)
    # the same box from the LiDAR side: KittiLabels keep h, w, l, the annotations l, h, w
    labels = read_label(tmp_path / "label_2" / "000003.txt")
    assert labels.dimensions[0].tolist() == [1.5, 1.6, 4.0]
    assert kitti.annos_from_labels(labels)["dimensions"][0].tolist() == [4.0, 1.5, 1.6]
    calib = KittiCalib.default()
    lidar = camera_to_lidar_boxes(labels.location[:1], labels.dimensions[:1], labels.rotation_y[:1], calib)
    assert lidar[0, 3:6].tolist() == pytest.approx([4.0, 1.6, 1.5])  # dx, dy, dz = l, w, h
    det = kitti.detection_annos({"boxes": lidar, "scores": [0.87], "names": ["Car"]}, calib)
    assert det["dimensions"][0].tolist() == pytest.approx([4.0, 1.5, 1.6])
    assert det["location"][0].tolist() == pytest.approx(labels.location[0].tolist())


def test_evaluate_lidar_on_simulated_frames(tmp_path):
    source = SyntheticFrames("driving_city", num_frames=3, seed=5, object_counts={"Car": 80, "Pedestrian": 40,
                                                                               "Cyclist": 15})
    frames = [source[i] for i in range(3)]
    calib = KittiCalib.default()
    rng = np.random.default_rng(0)
    perfect, detections = [], []
    for i, f in enumerate(frames):
        keep = f.num_points_in_box >= 1
        scores = (rng.permutation(10000)[: int(keep.sum())] / 10000).astype(np.float32)
        perfect.append({"boxes": torch.from_numpy(f.boxes[keep]), "scores": torch.from_numpy(scores),
                        "labels": torch.from_numpy(f.labels[keep] + 1)})  # 1-based class ids
        # imperfect: some boxes dropped, some shifted half a length, false positives, class names
        boxes = f.boxes[keep].copy()
        boxes[::4, 0] += boxes[::4, 3] / 2
        fp = boxes[1::5].copy()
        fp[:, 1] += 3.0
        drop = rng.random(boxes.shape[0]) < 0.2
        names = np.array([CLASSES[j] for j in f.labels[keep]])
        detections.append({"boxes": np.concatenate([boxes[~drop], fp]),
                           "scores": np.concatenate([scores[~drop], scores[1::5] * 0.5]).round(4).astype(np.float32),
                           "names": np.concatenate([names[~drop], names[1::5]])})
        write_kitti_frame(tmp_path, f, frame_id=i, calib=calib)
        d = detections[-1]
        inside = kitti.detection_annos(d, calib)  # the kept boxes (centre in the image)
        fov = kitti_fov_mask(d["boxes"][:, :3], calib)
        write_label(tmp_path / "results" / f"{i:06d}.txt",
                    boxes_to_kitti_labels(d["boxes"][fov], d["names"][fov], calib, score=d["scores"][fov]))
        assert len(inside["name"]) == int(fov.sum())

    # gts as detections: the detection annotations are the gt annotations (same rows and fields)
    _, results = kitti.evaluate_lidar(frames, perfect, class_names=CLASSES)  # labels 1-based into CLASSES
    gt_annos = [kitti.frame_annos(f, calib) for f in frames]
    dt_annos = [kitti.detection_annos(p, calib, class_names=CLASSES) for p in perfect]
    for g, d in zip(gt_annos, dt_annos):
        for key in ("name", "bbox", "alpha", "dimensions", "location", "rotation_y"):
            assert np.array_equal(g[key], d[key]), key
    # 100 where a class and difficulty has >= 41 counted gts (precision 1 at every recall position)
    counts = kitti.count_difficulties(gt_annos)
    assert counts["Car"]["hard"] >= 41
    assert results["Car_3d_hard_R40"] == results["Car_bev_hard_R11"] == results["Car_aos_hard_R40_loose"] == 100.0
    # and the protocol everywhere (fewer gts; a low detection of another class can take a gt in 2D, as the
    # official clean_data ignores every low detection, whatever its class)
    assert_results_equal(results, ref_evaluate(gt_annos, dt_annos, ("Car", "Pedestrian", "Cyclist")))

    # the same through KITTI files (labels written by write_kitti_frame, results by write_label)
    _, direct = kitti.evaluate_lidar(frames, detections)
    _, files = kitti.evaluate(kitti.read_annos(tmp_path / "training" / "label_2"), kitti.read_annos(tmp_path / "results"))
    assert_results_equal(direct, files, tol=1e-6)
    assert 0 < direct["Car_3d_moderate_R40"] < 100


def test_count_difficulties():
    gts, _ = perfect_frames(num_frames=3)
    counts = kitti.count_difficulties(gts, classes=("Car", "Pedestrian", "Cyclist", "Van"))
    # per frame: Car easy + Car occluded 1 + small Car; Pedestrian easy + Pedestrian truncated 0.4; Cyclist easy
    assert counts["Car"] == {"labelled": 9, "easy": 3, "moderate": 6, "hard": 6}
    assert counts["Pedestrian"] == {"labelled": 6, "easy": 3, "moderate": 3, "hard": 6}
    assert counts["Cyclist"] == {"labelled": 3, "easy": 3, "moderate": 3, "hard": 3}
    assert counts["Van"] == {"labelled": 3, "easy": 3, "moderate": 3, "hard": 3}


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------
def test_bad_annotations():
    gts, dts = two_cars()
    with pytest.raises(ValueError, match="hold no frames"):
        kitti.evaluate([], [])
    with pytest.raises(ValueError, match="gt_annos has 1 frames but dt_annos has 2"):
        kitti.evaluate(gts, dts + dts)
    with pytest.raises(ValueError, match=r"dt_annos\[0\] has no 'score' field"):
        kitti.evaluate(gts, [{k: v for k, v in dts[0].items() if k != "score"}])
    with pytest.raises(ValueError, match=r"gt_annos\[1\]\['bbox'\] must have shape \(2, 4\)"):
        kitti.evaluate(gts + [dict(gts[0], bbox=np.zeros((2, 3)))], dts + dts)
    with pytest.raises(ValueError, match=r"dt_annos\[0\]\['location'\] contains NaN"):
        kitti.evaluate(gts, [dict(dts[0], location=np.full((3, 3), np.nan))])
    with pytest.raises(ValueError, match=r"gt_annos\[0\]\['dimensions'\] has negative sizes"):
        kitti.evaluate([dict(gts[0], dimensions=-gts[0]["dimensions"])], dts)
    with pytest.raises(ValueError, match=r"gt_annos\[0\] must be a dict"):
        kitti.evaluate([[1, 2]], dts)
    with pytest.raises(ValueError, match=r"dt_annos\[0\]\['name'\] must be a 1-D array of strings"):
        kitti.evaluate(gts, [dict(dts[0], name=np.zeros(3))])
    with pytest.raises(ValueError, match="sequences of per-frame dicts"):
        kitti.evaluate(gts[0], dts[0])
    with pytest.raises(ValueError, match=r"dt_annos\[1\] has no 'bbox' field but other frames have one"):
        kitti.evaluate(gts + gts, dts + [{k: v for k, v in dts[0].items() if k != "bbox"}])
    # DontCare fillers (-1 sizes) and objects of other classes are not checked for sizes
    region = obj("DontCare", -1000.0, -1000.0, box_2d(5), lhw=(-1, -1, -1), ry=-10.0, alpha=-10.0)
    kitti.evaluate(two_cars(gt_extra=[region])[0], dts)


def test_bad_options():
    gts, dts = two_cars()
    with pytest.raises(ValueError, match="no default minimum overlaps for class 'Tram'"):
        kitti.evaluate(gts, dts, classes=("Car", "Tram"))
    with pytest.raises(ValueError, match=r"min_overlaps\['Car'\] must be"):
        kitti.evaluate(gts, dts, min_overlaps={"Car": (0.7, 0.7)})
    with pytest.raises(ValueError, match="not evaluated"):
        kitti.evaluate(gts, dts, classes=("Car",), min_overlaps={"Pedestrian": (0.5, 0.5, 0.5)})
    with pytest.raises(ValueError, match="distinct"):
        kitti.evaluate(gts, dts, classes=("Car", "car"))
    _, results = kitti.evaluate(gts, dts, classes=("Tram",), min_overlaps={"Tram": (0.5, 0.5, 0.5)})
    assert results["Tram_3d_easy_R40"] == 0.0


def test_bad_lidar_input():
    frame = SyntheticFrames("driving_city", num_frames=1, seed=1, object_counts={"Car": 5})[0]
    good = {"boxes": frame.boxes, "scores": np.ones(frame.num_boxes), "labels": frame.labels + 1}
    with pytest.raises(ValueError, match="gt_frames has 1 frames but detections has 2"):
        kitti.evaluate_lidar([frame], [good, good])
    with pytest.raises(ValueError, match=r"gt_frames\[0\] must be a lidarops.data.Frame"):
        kitti.evaluate_lidar([{}], [good])
    with pytest.raises(ValueError, match=r"detections\[0\] has no 'scores'"):
        kitti.evaluate_lidar([frame], [{"boxes": frame.boxes, "labels": frame.labels}])
    with pytest.raises(ValueError, match=r"detections\[0\]\['boxes'\] must be \(K, 7\)"):
        kitti.evaluate_lidar([frame], [dict(good, boxes=frame.boxes[:, :6])])
    with pytest.raises(ValueError, match=r"detections\[0\]\['labels'\] must be integer class ids 1\.\.3"):
        kitti.evaluate_lidar([frame], [dict(good, labels=frame.labels + 1 + len(CLASSES))])
    with pytest.raises(ValueError, match=r"detections\[0\]\['labels'\] must be integer class ids"):
        kitti.evaluate_lidar([frame], [dict(good, labels=frame.labels)])  # 0-based: the padding id 0
    with pytest.raises(ValueError, match=r"needs 'labels'"):
        kitti.evaluate_lidar([frame], [{"boxes": frame.boxes, "scores": good["scores"]}])
    with pytest.raises(ValueError, match=r"detections\[0\]\['scores'\] must have"):
        kitti.evaluate_lidar([frame], [dict(good, scores=np.ones(frame.num_boxes + 1))])


# ---------------------------------------------------------------------------------------------
# the whole view: sensors that see beyond a camera's image (a drone's Avia)
# ---------------------------------------------------------------------------------------------
def _drone_frame(calib):
    """LiDAR boxes of drones: one in the camera's image, one high above it (38 degrees up), one beyond x = 80 m,
    and a DontCare row; annotations as the label file reads (visible: occlusion 0)."""
    boxes = np.array([[20.0, 1.0, 0.0, 0.7, 0.7, 0.3, 0.2], [10.0, -2.0, 8.0 * 0.98, 0.7, 0.7, 0.3, -0.4],
                      [90.0, 0.0, 1.0, 0.7, 0.7, 0.3, 0.0], [30.0, 5.0, 0.0, 2.0, 2.0, 2.0, 0.0]])
    names = ["Drone", "Drone", "Drone", "DontCare"]
    gt = kitti.annos_from_labels(boxes_to_kitti_labels(boxes, names, calib, visibility=np.ones(4)))
    return boxes, gt


def test_whole_view_annos_drop_the_image_and_what_lies_out_of_range():
    calib = KittiCalib.default()
    boxes, gt = _drone_frame(calib)
    assert not kitti_fov_mask(boxes[1:2, :3], calib).any() and gt["truncated"][1] > 0.5  # the camera loses it
    out = kitti.whole_view_annos(gt, calib, [0, -40, -8, 80, 40, 8])
    assert "bbox" not in out and "alpha" not in out
    assert out["name"].tolist() == ["Drone", "Drone"] and (out["truncated"] == 0).all()  # no DontCare, none at 90 m
    assert np.allclose(camera_to_lidar_boxes(out["location"], out["dimensions"][:, [1, 2, 0]], out["rotation_y"],
                                             calib), boxes[:2], atol=1e-5)
    assert kitti.whole_view_annos(gt, calib)["name"].tolist() == ["Drone"] * 3  # no range: every object
    dt = kitti.detection_annos({"boxes": boxes[:3], "scores": np.ones(3), "names": np.array(["Drone"] * 3)}, calib,
                               camera_fov_only=False)
    assert len(dt["name"]) == 3 and "bbox" not in dt and np.allclose(dt["location"], gt["location"][:3], atol=1e-5)


def test_whole_view_evaluator_counts_objects_beyond_the_image():
    """KittiEvaluator(camera=False) on 41 copies of the frame (R40 reaches 100 from 41 objects): the drone above
    the image counts (found: 100; missed: recall 1/2), the one out of the range does not, and only the BEV and 3D
    metrics are reported."""
    calib = KittiCalib.default()
    boxes, gt = _drone_frame(calib)
    rng = [0, -40, -8, 80, 40, 8]
    metas = [{"annos": gt, "calib": calib}] * 41

    def preds(rows, scores):
        return [{"boxes": torch.from_numpy(boxes[rows]), "scores": torch.tensor(scores) * (1 - i / 100),
                 "labels": torch.ones(len(rows))} for i in range(41)]

    whole = kitti.KittiEvaluator(["Drone"], camera=False, point_cloud_range=rng)
    found, _ = whole(preds([0, 1], [0.9, 0.8]), metas)
    assert found["Drone_3d_moderate_R40"] == found["Drone_bev_easy_R40"] == 100.0
    assert not any(k.startswith(("Drone_bbox", "Drone_aos")) for k in found)
    missed, _ = whole(preds([0], [0.9]), metas)  # recall 1/2 at precision 1: R40 positions 1..20 of 40
    assert missed["Drone_3d_moderate_R40"] == pytest.approx(50.0)
    spurious, _ = whole(preds([0, 1, 2], [0.9, 0.8, 0.95]), metas)  # a box on the drone at 90 m: a false positive
    assert spurious["Drone_3d_moderate_R40"] < 100.0
    unranged, _ = kitti.KittiEvaluator(["Drone"], camera=False)(preds([0, 1], [0.9, 0.8]), metas)
    assert unranged["Drone_3d_moderate_R40"] < 70  # without a range the far drone is a miss: recall 2/3
    # the camera's protocol: the drone above the image is neither detected nor labelled in a difficulty
    camera, _ = kitti.KittiEvaluator(["Drone"])(preds([0, 1], [0.9, 0.8]), metas)
    assert "Drone_bbox_moderate_R40" in camera
    for bad in ([0, 0, 0, 1, 1], [0, -40, -8, 0, 40, 8], [0, -40, float("nan"), 80, 40, 8]):
        with pytest.raises(ValueError, match="point_cloud_range"):
            kitti.KittiEvaluator(["Drone"], camera=False, point_cloud_range=bad)
