"""The detector on real LiDAR scans, and simulated against real statistics side by side: the yardstick of the
simulator's realism (issue 40).

    bash tools/sim2real/kitti_real_frames.sh                       # 6 real KITTI frames out of OpenPCDet's history
    python tools/sim2real/mmdet3d_demo_frame.py MMDET3D_GIT .peers/kitti_real   # mmdetection3d's frame 000008
    bash tools/sim2real/more_real_frames.sh /work/.mirror          # 8 more (000008 whole) from PointRCNN,
                                                                   # Open3D-ML and PointPillars
    python benchmarks/bm_sim2real.py --real .peers/kitti_real --realism none kitti --plot docs/img/sim2real.png --json

The real frames are KITTI's (non-commercial, share-alike licence): they are brought to the machine at run time
and never committed. For each ``--checkpoint`` (default: the shipped ``pointpillars_synth`` and
``pointpillars_synth_real``) and each real frame (points the camera sees, as the detector was trained):

* **found / labelled** per class: labelled objects matched one-to-one (greedy by score, same class) by a
  detection of 3D IoU >= each threshold (Car 0.5 and KITTI's 0.7; Pedestrian and Cyclist 0.25 and 0.5), and of
  bird's-eye IoU >= 0.5; and among the easy and moderate ones (KITTI's difficulty), at the first threshold;
* **taken for**: per labelled object, the class of the highest-scoring detection over it at bird's-eye IoU
  >= the class's first threshold (Car 0.5, Pedestrian and Cyclist 0.25), counted where it is another class or
  none (``Pedestrian_taken_for_Cyclist``...);
* **false positives per frame** above scores 0.3 and 0.5: detections whose bird's-eye IoU with every labelled
  box (any type: Van, Truck, Misc too; DontCare has no box) is below 0.1; and of those, the ones outside the
  frame's DontCare regions, as KITTI's evaluation counts them (a detection whose projected 2D box lies more than
  half inside a DontCare box is ignored; ``..._outside_dontcare``). ``--fp-list`` prints each false positive above
  0.5: its range, class, score, bottom, size, the returns in its footprint and their height span, its DontCare
  overlap;
* **errors of the found boxes** (bird's-eye IoU >= 0.5): centre height, bottom, top, length, width, height,
  detection minus label, in metres.

And the statistics of the real frames beside ``--sim-frames`` simulated ``driving_city`` frames (held-out seed,
the same camera view): intensity of all points and of points on cars, the share of car returns with intensity
0, points per car against range, the share of a car's returns in the bottom, middle and top third of its
height, the cars' halo (cars within 30 m: points within 0.5 m outside the box, more than 0.3 m above its
bottom, per point inside it), the share of pedestrians with another within 1.5 m (groups), the share of the
returns at 15-60 m in the 64 densest 0.05-degree bins of apparent elevation (``beam_line_share``: 1 when every beam
starts at the sensor's origin), the share of a pedestrian's points (10 or more) below half its height, and the far
clutter: clusters of 3-30 non-ground returns at 40-75 m outside every labelled box, per frame, with their median
height and footprint and the share on the road (|y| < 10.5 m), where far false positives stand.
* **by score threshold** (``curve_*``): the easy and moderate objects found and the false positives per frame
  when only the detections scoring at least 0.1, 0.2, ... 0.8 are kept, what a user picking a threshold sees;
  ``--curve-plot PNG`` draws them.

* **which way the cyclists ride** (``--aspects N``): what each checkpoint takes simulated cyclists for, riding along
  the road and across it, in their own frames and moved with their returns onto each real frame's road, and what it
  takes simulated pedestrians crossing in groups for (:func:`cyclist_aspects`).

``--json`` merges the rows into ``benchmarks/results/<device>.json`` under ``"sim2real"``.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import env_meta, print_table, write_results  # noqa: E402

CLASSES = ("Car", "Pedestrian", "Cyclist")
THRESHOLDS_3D = {"Car": (0.5, 0.7), "Pedestrian": (0.25, 0.5), "Cyclist": (0.25, 0.5)}
FP_SCORES = (0.3, 0.5)
CURVE_SCORES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)  # score_curve: the thresholds a user might pick
BANDS = ("bottom", "middle", "top")
GRADE_RANGE = (10.0, 45.0)  # object_grades: objects far enough for a grade to show, near enough to be labelled
LINES_RANGE, LINES_BINS = (15.0, 60.0), np.arange(-25.0, 3.0, 0.05)  # beam_line_share: the returns and the bins
HALO_RANGE, HALO_MARGIN = 30.0, 0.5  # the cars whose halo is counted (m), and its width around the box (m)
FAR_RANGE, FAR_POINTS = (40.0, 75.0), (3, 30)  # far_clusters: the range band (m) and the clusters' sizes counted


def greedy_match(iou: np.ndarray, scores: np.ndarray, thresh: float) -> np.ndarray:
    """One-to-one matches of detections (rows, taken by falling score) to labels (columns) with IoU >=
    ``thresh``; returns, per label, the matched detection's row or -1."""
    matched = np.full(iou.shape[1], -1, np.int64)
    for d in np.argsort(-scores, kind="stable"):
        if iou.shape[1] == 0:
            break
        free = np.where(matched < 0, iou[d], -1.0)
        j = int(np.argmax(free))
        if free[j] >= thresh:
            matched[j] = d
    return matched


def frame_figures(gt_boxes: np.ndarray, gt_names: list[str], det_boxes: np.ndarray, det_scores: np.ndarray,
                  det_names: list[str], difficulty: np.ndarray | None = None,
                  det_dontcare: np.ndarray | None = None) -> dict:
    """One frame's counts: ``found[(class, kind, thresh)]``, ``labelled[class]``, ``fp[score]`` and the
    errors of the boxes found at bird's-eye IoU 0.5, ``errors[class]`` (rows of centre-z, bottom, top, dx, dy,
    dz differences). With the labels' KITTI ``difficulty``, also the easy and moderate ones (0 or 1) found at
    the class's first 3D threshold, ``found_em[class]`` of ``labelled_em[class]``. With each detection's
    largest DontCare overlap (:func:`dontcare_overlap`), also ``fp_outside_dontcare[score]``: the false
    positives KITTI's evaluation counts (overlap at most 0.5)."""
    from lidarops import box_iou_3d, box_iou_bev

    t = lambda a: torch.as_tensor(np.asarray(a, np.float64).reshape(-1, 7))  # noqa: E731
    out: dict = {"found": {}, "labelled": {}, "fp": {}, "errors": {}, "found_em": {}, "labelled_em": {}}
    for cls in CLASSES:
        g = [i for i, n in enumerate(gt_names) if n == cls]
        d = [i for i, n in enumerate(det_names) if n == cls]
        out["labelled"][cls] = len(g)
        gb, db, ds = gt_boxes[g], det_boxes[d], det_scores[d]
        iou3 = box_iou_3d(t(db), t(gb)).numpy() if len(g) and len(d) else np.zeros((len(d), len(g)))
        bev = box_iou_bev(t(db), t(gb)).numpy() if len(g) and len(d) else np.zeros((len(d), len(g)))
        for th in THRESHOLDS_3D[cls]:
            out["found"][(cls, "3d", th)] = int((greedy_match(iou3, ds, th) >= 0).sum())
        if difficulty is not None:
            em = (difficulty[g] >= 0) & (difficulty[g] <= 1)
            out["labelled_em"][cls] = int(em.sum())
            out["found_em"][cls] = int(((greedy_match(iou3, ds, THRESHOLDS_3D[cls][0]) >= 0) & em).sum())
        m = greedy_match(bev, ds, 0.5)
        out["found"][(cls, "bev", 0.5)] = int((m >= 0).sum())
        rows = []
        for j, k in enumerate(m):
            if k >= 0:
                a, b = db[k], gb[j]
                rows.append([a[2] - b[2], (a[2] - a[5] / 2) - (b[2] - b[5] / 2), (a[2] + a[5] / 2) - (b[2] + b[5] / 2),
                             a[3] - b[3], a[4] - b[4], a[5] - b[5]])
        out["errors"][cls] = np.asarray(rows, np.float64).reshape(-1, 6)
    any_bev = box_iou_bev(t(det_boxes), t(gt_boxes)).numpy() if len(gt_boxes) and len(det_boxes) else \
        np.zeros((len(det_boxes), len(gt_boxes)))
    alone = any_bev.max(axis=1) < 0.1 if any_bev.shape[1] else np.ones(len(det_boxes), bool)
    for s in FP_SCORES:
        out["fp"][s] = int((alone & (det_scores >= s)).sum())
    if det_dontcare is not None:
        out["fp_outside_dontcare"] = {s: int((alone & (det_scores >= s) & (det_dontcare <= 0.5)).sum())
                                      for s in FP_SCORES}
    out["alone"] = alone
    # what each labelled Car / Pedestrian / Cyclist is taken for: the class of the highest-scoring detection of
    # any class over it at bird's-eye IoU >= the class's first threshold ("none" when there is none)
    out["taken_for"] = {}
    for j, name in enumerate(gt_names):
        if name in CLASSES:
            over = np.flatnonzero(any_bev[:, j] >= THRESHOLDS_3D[name][0]) if any_bev.size else np.zeros(0, np.int64)
            got = det_names[over[np.argmax(det_scores[over])]] if over.size else "none"
            out["taken_for"][(name, got)] = out["taken_for"].get((name, got), 0) + 1
    return out


def score_curve(frames: list[tuple], scores: tuple[float, ...] = CURVE_SCORES) -> dict:
    """What a user who keeps the detections scoring at least ``s`` sees, for each ``s`` in ``scores``: per class the
    easy and moderate labelled objects found at the class's first 3D threshold, and the false positives per frame
    (and those outside DontCare regions). ``frames``: per frame ``(gt_boxes, gt_names, difficulty, det_boxes,
    det_scores, det_names, det_dontcare)``. Returns lists over ``scores``: ``found_em[class]``, ``labelled_em[class]``
    (one number), ``fp_per_frame``, ``fp_per_frame_outside_dontcare``."""
    out = {"scores": list(scores), "found_em": {c: [] for c in CLASSES}, "labelled_em": {c: 0 for c in CLASSES},
           "fp_per_frame": [], "fp_per_frame_outside_dontcare": []}
    n = max(len(frames), 1)
    for k, s in enumerate(scores):
        found, fp, fp_out = dict.fromkeys(CLASSES, 0), 0, 0
        for gt, names, difficulty, db, ds, dn, overlap in frames:
            keep = ds >= s
            f = frame_figures(gt, names, db[keep], ds[keep], [d for d, kk in zip(dn, keep) if kk], difficulty)
            for c in CLASSES:
                found[c] += f["found_em"][c]
                if k == 0:
                    out["labelled_em"][c] += f["labelled_em"][c]
            fp += int(f["alone"].sum())
            fp_out += int((f["alone"] & (overlap[keep] <= 0.5)).sum())
        for c in CLASSES:
            out["found_em"][c].append(found[c])
        out["fp_per_frame"].append(round(fp / n, 2))
        out["fp_per_frame_outside_dontcare"].append(round(fp_out / n, 2))
    return out


def plot_curves(curves: dict, path: Path) -> None:
    """Per class, the share of the easy and moderate labelled objects found against the false positives per frame,
    one line per checkpoint, each point a score threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CLASSES), figsize=(5 * len(CLASSES), 4.2))
    for ax, c in zip(axes, CLASSES):
        for name, cv in curves.items():
            share = np.asarray(cv["found_em"][c], np.float64) / max(cv["labelled_em"][c], 1)
            ax.plot(cv["fp_per_frame"], share, "o-", label=name)
            for s, x, y in zip(cv["scores"], cv["fp_per_frame"], share):
                if s in (0.3, 0.5, 0.7):
                    ax.annotate(f"{s:g}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_title(f"{c}: found (easy and moderate, 3D IoU >= {THRESHOLDS_3D[c][0]})")
        ax.set_xscale("symlog", linthresh=1.0)  # the low thresholds' tens of false positives would squash the rest
        ax.set_xlabel("false positives per frame (all classes; linear to 1, then log)")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("share found at score >= threshold (labels: thresholds)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    print(f"plot: {path}")


def object_stats(points: np.ndarray, boxes: np.ndarray, names: list[str]) -> dict:
    """Per car: range, points, their intensities and the share in each height band; and the halo of the cars
    within ``HALO_RANGE``: their points and the points just outside their boxes (within ``HALO_MARGIN`` in plan,
    more than 0.3 m above the bottom: mixed pixels, parts the label leaves out)."""
    from lidarops import points_in_boxes

    cars = [i for i, n in enumerate(names) if n == "Car"]
    if not cars or not len(points):
        return {"range": [], "points": [], "intensity": np.zeros(0), "bands": np.zeros((0, 3)), "halo": (0, 0)}
    xyz = torch.as_tensor(points[:, :3], dtype=torch.float64)
    idx = points_in_boxes(xyz, torch.as_tensor(boxes[cars], dtype=torch.float64)).numpy()
    near = [k for k, i in enumerate(cars) if np.hypot(boxes[i, 0], boxes[i, 1]) < HALO_RANGE]
    grown = boxes[cars].copy()
    grown[:, 3:5] += 2 * HALO_MARGIN
    around = points_in_boxes(xyz, torch.as_tensor(grown, dtype=torch.float64)).numpy()
    lifted = points[:, 2] > (grown[:, 2] - grown[:, 5] / 2)[np.maximum(around, 0)] + 0.3
    halo = (int(np.isin(idx, near).sum()), int((np.isin(around, near) & (idx < 0) & lifted).sum()))
    rng, npts, inten, bands = [], [], [], []
    for k, i in enumerate(cars):
        p = points[idx == k]
        b = boxes[i]
        rng.append(float(np.hypot(b[0], b[1])))
        npts.append(len(p))
        inten.append(p[:, 3])
        if len(p):
            h = np.clip((p[:, 2] - (b[2] - b[5] / 2)) / b[5], 0, 0.999)
            bands.append(np.bincount((h * 3).astype(int), minlength=3) / len(p))
    return {"range": rng, "points": npts, "intensity": np.concatenate(inten) if inten else np.zeros(0),
            "bands": np.asarray(bands).reshape(-1, 3), "halo": halo}


def real_frames(root: Path):
    """(frame id, points, boxes, KITTI type names, KITTI difficulty, calibration, DontCare 2D boxes (D, 4)) of
    each real frame."""
    from lidarops.data.formats.kitti import KittiDataset, kitti_difficulty, read_label

    ds = KittiDataset(root, image_set="val", unknown="keep", fov="camera")
    for i in range(len(ds)):
        f = ds[i]
        labels = f.meta.get("kitti")
        names = list(labels.names) if labels is not None else []  # KITTI's types: Van, Truck, Misc too
        difficulty = kitti_difficulty(labels) if labels is not None else np.zeros(0, np.int64)
        path = ds.split_dir / "label_2" / f"{f.meta['frame_id']}.txt"
        every = read_label(path) if path.is_file() else None  # the dataset leaves the DontCare rows out
        dontcare = np.zeros((0, 4)) if every is None else \
            np.asarray(every.bbox, np.float64).reshape(-1, 4)[np.asarray(every.names) == "DontCare"]
        yield f.meta["frame_id"], f.points, f.boxes, names, difficulty, f.meta.get("calib"), dontcare


def dontcare_overlap(det_boxes: np.ndarray, calib, dontcare: np.ndarray) -> np.ndarray:
    """Each detection's largest overlap with the DontCare regions, KITTI's measure: the intersection of its 2D box
    (its corners projected with ``P2``, clipped to the image) with a DontCare box, over its own 2D box's area."""
    from lidarops.data.formats.kitti import KITTI_IMAGE_SIZE, KittiCalib, _image_boxes
    from lidarops.eval.kitti import _image_iou

    k = len(det_boxes)
    if k == 0 or len(dontcare) == 0:
        return np.zeros(k)
    bbox, _ = _image_boxes(np.asarray(det_boxes, np.float64).reshape(-1, 7), calib or KittiCalib.default(),
                           KITTI_IMAGE_SIZE)
    d, c = np.repeat(np.arange(k), len(dontcare)), np.tile(np.arange(len(dontcare)), k)
    return _image_iou(bbox.astype(np.float64)[d], dontcare[c], False).reshape(k, len(dontcare)).max(1)


def fp_rows(fid: str, points: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray, det_names: list[str],
            alone: np.ndarray, overlap: np.ndarray, least: float = 0.5) -> list[dict]:
    """The false positives scoring at least ``least``: where they stand and what is under them (the returns within
    the box's footprint, ignoring its heading and height, and their height span)."""
    rows = []
    for k in np.flatnonzero(alone & (det_scores >= least)):
        b = det_boxes[k]
        under = points[np.abs(points[:, :2] - b[:2]).max(1) <= max(b[3], b[4]) / 2, 2]
        rows.append({"frame": fid, "class": det_names[k], "score": round(float(det_scores[k]), 2),
                     "range_m": round(float(np.hypot(b[0], b[1])), 1), "bottom_m": round(float(b[2] - b[5] / 2), 2),
                     "size_m": " x ".join(f"{v:.2f}" for v in b[3:6]), "returns": int(under.size),
                     "height_span_m": round(float(np.ptp(under)), 2) if under.size else 0.0,
                     "dontcare": round(float(overlap[k]), 2)})
    return rows


def parse_profile(text: str | None):
    """``None``/``"none"`` (as cast), a profile name, or ``name:field=value,...``: the profile with those fields
    changed (``kitti:roadside_structures=0.7``; :func:`lidarops.data.realism.make_realism` reads it)."""
    from lidarops.data.realism import make_realism

    if text in (None, "none"):
        return None
    return text if ":" not in text else make_realism(text)


def sim_frames(n: int, realism: str | None = None):
    from lidarops.conventions import HELD_OUT_SEED
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import SyntheticFrames

    sim = SyntheticFrames("driving_city", num_frames=n, seed=HELD_OUT_SEED + 4242, realism=parse_profile(realism))
    calib = KittiCalib.default()
    for i in range(n):
        f = sim[i]
        keep = kitti_fov_mask(f.points, calib)
        names = [f.class_names[k] if k >= 0 else "Other" for k in f.labels]
        yield f"sim{i}", f.points[keep], f.boxes, names


def seen_labels(points: np.ndarray, boxes: np.ndarray, names: list[str]) -> tuple[np.ndarray, list[str]]:
    """A simulated frame's labels as KITTI's would be: the objects with a return among ``points`` (the camera's view;
    the simulator labels every object of the scene, behind the car and hidden ones too)."""
    from lidarops import points_in_boxes

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    idx = points_in_boxes(torch.as_tensor(points[:, :3], dtype=torch.float64), torch.as_tensor(boxes)).numpy()
    keep = np.bincount(idx[idx >= 0], minlength=len(boxes)) > 0
    return boxes[keep], [n for n, k in zip(names, keep) if k]


def detections(model, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    names = list(model.config.class_names)
    pts = torch.as_tensor(points[:, :4], dtype=torch.float32)
    with torch.no_grad():
        det = model.predict({"points": torch.nn.functional.pad(pts, (1, 0)), "batch_size": 1})[0]
    return (det["boxes"].double().numpy(), det["scores"].double().numpy(),
            [names[k - 1] for k in det["labels"].tolist()])


def aspect_deg(box) -> float:
    """The angle between a box's heading and the ray from the sensor to its centre, folded to [0, 90] degrees: 0
    for an object moving along the ray (seen from behind or ahead), 90 for one crossing it (seen broadside)."""
    a = abs((float(box[6]) - math.atan2(float(box[1]), float(box[0])) + math.pi / 2) % math.pi - math.pi / 2)
    return math.degrees(a)


def to_box_frame(points: np.ndarray, box) -> np.ndarray:
    """Points (N, >= 3) in a box's frame: x along its heading, z up from its bottom centre (other columns kept)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    d = points[:, :3] - np.array([box[0], box[1], box[2] - box[5] / 2])
    return np.c_[d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c, d[:, 2], points[:, 3:]]


def from_box_frame(points: np.ndarray, box) -> np.ndarray:
    """The inverse of :func:`to_box_frame`."""
    c, s = math.cos(box[6]), math.sin(box[6])
    return np.c_[points[:, 0] * c - points[:, 1] * s + box[0], points[:, 0] * s + points[:, 1] * c + box[1],
                 points[:, 2] + box[2] - box[5] / 2, points[:, 3:]].astype(np.float32)


def _in_box(points: np.ndarray, box, grow: float = 0.0) -> np.ndarray:
    from lidarops import points_in_boxes

    b = np.asarray(box, np.float64).copy()
    b[3:6] += 2 * grow
    return points_in_boxes(torch.as_tensor(points[:, :3], dtype=torch.float64), torch.as_tensor(b[None])).numpy() >= 0


def taken_as(model, points: np.ndarray, box) -> str:
    """The class the detector gives an object: of its detections at 3D IoU >= 0.25 with ``box``, a cyclist if there
    is one, else the highest-scoring one's class; ``"none"`` without any."""
    from lidarops import box_iou_3d

    db, ds, dn = detections(model, points)
    if not len(db):
        return "none"
    iou = box_iou_3d(torch.as_tensor(db), torch.as_tensor(np.asarray(box, np.float64)[None])).numpy()[:, 0]
    over = [dn[i] for i in np.argsort(-ds) if iou[i] >= 0.25]
    return "Cyclist" if "Cyclist" in over else (over[0] if over else "none")


# cyclist_aspects: simulated frames with cyclists riding across the road and pedestrians crossing it in groups
ASPECT_PROFILE = "kitti:crossing_cyclists=1.0,crossing_pedestrians=1.0,crossing_groups=1.0"
BROADSIDE = 45.0  # degrees: a cyclist at this aspect or more is seen broadside (crossing), below it along the road
ROAD_SPOTS = ((20.0, -3.0), (25.0, 3.0))  # cyclist_aspects: where simulated cyclists are put on each real frame


def cyclist_aspects(model, sim: list, real: list, per_spot: int = 3) -> dict:
    """What the detector takes cyclists for, along the road (aspect below :data:`BROADSIDE`) and broadside: the
    simulated cyclists with 15 or more returns in ``sim`` (frames of :data:`ASPECT_PROFILE`), each in its own frame;
    and, on each real frame, simulated cyclists put at :data:`ROAD_SPOTS` (skipping a spot with a label within
    2.5 m) on the local ground, riding along the road and across it: for each, in turn, the ``per_spot``
    simulated cyclists nearest in range and aspect (one cyclist would make the count hang on which one it is), its
    returns moved with it (the sensor sees the same side), the real points in its box removed. Separates what a real cyclist looks like from where it is and which way it rides. And the
    other side of the trade a training with cyclists riding across makes: what the simulated pedestrians (10 or
    more returns) are taken for, those with another within 1.5 m (crossing in groups, as the real ones do) and the
    others."""
    cyclists = [(pts, np.asarray(b, np.float64)) for _, pts, boxes, names in sim for b, n in zip(boxes, names)
                if n == "Cyclist" and np.hypot(b[0], b[1]) < 45]
    cyclists = [(pts, b) for pts, b in cyclists if _in_box(pts, b).sum() >= 15]
    out: dict = {}
    for pts, b in cyclists:
        key = f"sim_{'broadside' if aspect_deg(b) >= BROADSIDE else 'along'}"
        out.setdefault(key, []).append(taken_as(model, pts, b))
    for _, pts, boxes, names in sim:
        peds = np.array([b for b, n in zip(boxes, names) if n == "Pedestrian"], np.float64).reshape(-1, 7)
        for i, b in enumerate(peds):
            if np.hypot(b[0], b[1]) >= 45 or _in_box(pts, b).sum() < 10:
                continue
            near = np.hypot(peds[:, 0] - b[0], peds[:, 1] - b[1])
            near[i] = np.inf
            key = "sim_pedestrian_in_group" if near.min(initial=np.inf) < 1.5 else "sim_pedestrian_alone"
            out.setdefault(key, []).append(taken_as(model, pts, b))
    for fid, points, boxes, names, *_ in real if cyclists else ():
        labels = np.asarray(boxes, np.float64).reshape(-1, 7)
        for x, y in ROAD_SPOTS:
            if len(labels) and np.hypot(labels[:, 0] - x, labels[:, 1] - y).min() < 2.5:
                continue
            ring = np.hypot(points[:, 0] - x, points[:, 1] - y)
            ground = points[(ring > 0.5) & (ring < 2.0), 2]
            if not len(ground):
                continue
            for kind, want in (("along", 10.0), ("broadside", 75.0)):
                r = math.hypot(x, y)
                nearest = sorted(cyclists, key=lambda c: abs(math.hypot(c[1][0], c[1][1]) - r) / 5
                                 + abs(aspect_deg(c[1]) - want) / 30)
                for pts, b in nearest[:per_spot]:
                    obj = to_box_frame(pts[_in_box(pts, b)], b)
                    box = b.copy()
                    box[0], box[1] = x, y
                    box[6] = math.atan2(y, x) + b[6] - math.atan2(b[1], b[0])  # the same aspect from the sensor
                    box[2] = np.percentile(ground, 10) + box[5] / 2
                    placed = np.r_[points[~_in_box(points, box, 0.3)][:, :4], from_box_frame(obj, box)[:, :4]]
                    out.setdefault(f"placed_real_{kind}", []).append(taken_as(model, placed, box))
    return {k: {c: v.count(c) for c in (*CLASSES, "none")} for k, v in out.items()}


def summarize(figs: list[dict]) -> dict:
    row: dict = {"frames": len(figs)}
    for cls in CLASSES:
        n = sum(f["labelled"][cls] for f in figs)
        row[f"{cls}_labelled"] = n
        if figs and cls in figs[0]["labelled_em"]:
            row[f"{cls}_labelled_easy_moderate"] = sum(f["labelled_em"][cls] for f in figs)
            row[f"{cls}_found_3d{THRESHOLDS_3D[cls][0]}_easy_moderate"] = sum(f["found_em"][cls] for f in figs)
        for key in [k for k in figs[0]["found"] if k[0] == cls]:
            found = sum(f["found"][key] for f in figs)
            row[f"{cls}_found_{key[1]}{key[2]}"] = found
        for other in (*CLASSES, "none"):
            if other != cls:
                row[f"{cls}_taken_for_{other}"] = sum(f["taken_for"].get((cls, other), 0) for f in figs)
        errs = np.concatenate([f["errors"][cls] for f in figs]) if figs else np.zeros((0, 6))
        if len(errs):
            for j, name in enumerate(("z_centre", "bottom", "top", "dx", "dy", "dz")):
                row[f"{cls}_err_{name}_m"] = round(float(errs[:, j].mean()), 3)
    for s in FP_SCORES:
        row[f"fp_per_frame_above_{s}"] = round(sum(f["fp"][s] for f in figs) / max(len(figs), 1), 2)
        if figs and "fp_outside_dontcare" in figs[0]:
            row[f"fp_per_frame_above_{s}_outside_dontcare"] = round(
                sum(f["fp_outside_dontcare"][s] for f in figs) / len(figs), 2)
    return row


def grouped_pedestrians(boxes: np.ndarray, names: list[str], within: float = 1.5) -> tuple[int, int]:
    """(pedestrians, those with another pedestrian within ``within`` m in bird's-eye view)."""
    xy = np.array([b[:2] for b, n in zip(boxes, names) if n == "Pedestrian"]).reshape(-1, 2)
    if len(xy) < 2:
        return len(xy), 0
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return len(xy), int((d.min(1) < within).sum())


def _returns_of(points: np.ndarray, boxes: np.ndarray, names: list[str], cls: str, least: int):
    """(label index, its returns [n, 3] in float64) for each object of class ``cls`` with at least ``least``."""
    from lidarops import points_in_boxes

    chosen = [i for i, n in enumerate(names) if n == cls]
    if not chosen or not len(points):
        return []
    idx = points_in_boxes(torch.as_tensor(points[:, :3], dtype=torch.float64),
                          torch.as_tensor(boxes[chosen], dtype=torch.float64)).numpy()
    found = [(i, np.asarray(points[idx == k, :3], np.float64)) for k, i in enumerate(chosen)]
    return [(i, q) for i, q in found if len(q) >= least]


def pedestrian_lower_half(points: np.ndarray, boxes: np.ndarray, names: list[str], least: int = 10) -> list[float]:
    """Per pedestrian with at least ``least`` points in its box: the share of them below half its height (legs,
    a coat's hem: about half in real scans)."""
    return [float(((q[:, 2] - (boxes[i, 2] - boxes[i, 5] / 2)) < boxes[i, 5] / 2).mean())
            for i, q in _returns_of(points, boxes, names, "Pedestrian", least)]


def cyclist_head_offset(points: np.ndarray, boxes: np.ndarray, names: list[str], least: int = 15) -> list[float]:
    """Per cyclist with at least ``least`` points in its box: where its highest returns (the top fifth of their
    height span: the rider's head and shoulders) lie along its heading, as a share of half its length (positive:
    ahead of the box's centre). A rider sitting upright over the saddle is behind the centre, one leaning to low
    handlebars ahead of it."""
    out = []
    for i, q in _returns_of(points, boxes, names, "Cyclist", least):
        b = boxes[i]
        along = (q[:, 0] - b[0]) * np.cos(b[6]) + (q[:, 1] - b[1]) * np.sin(b[6])
        top = q[:, 2] >= q[:, 2].max() - 0.2 * np.ptp(q[:, 2])
        out.append(float(along[top].mean() / (b[3] / 2)))
    return out


def object_grades(points: np.ndarray, boxes: np.ndarray, names: list[str], lo: float = GRADE_RANGE[0],
                  hi: float = GRADE_RANGE[1]) -> list[float]:
    """Per labelled Car, Pedestrian and Cyclist ahead (x > 0, as KITTI labels only what its camera sees) at
    ``lo``-``hi`` m: how far its label's bottom stands above the ground under the sensor (the 5th percentile of the
    heights of the returns within 8 m), as a share of its range: the grade of the road between them as the level
    sensor sees it."""
    near = points[np.hypot(points[:, 0], points[:, 1]) < 8.0]
    if len(near) < 20:
        return []
    ground = float(np.percentile(near[:, 2], 5))
    out = []
    for b, n in zip(np.asarray(boxes, np.float64).reshape(-1, 7), names):
        r = float(np.hypot(b[0], b[1]))
        if n in CLASSES and lo <= r <= hi and b[0] > 0:
            out.append((b[2] - b[5] / 2 - ground) / r)
    return out


def elevations(points: np.ndarray, lo: float = LINES_RANGE[0], hi: float = LINES_RANGE[1]) -> np.ndarray:
    """Apparent elevation (degrees, seen from the sensor's origin) of the returns between ``lo`` and ``hi`` m."""
    xyz = points[:, :3].astype(np.float64)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    m = (r > lo) & (r < hi)
    return np.degrees(np.arctan2(xyz[m, 2], r[m]))


def beam_line_share(points: np.ndarray) -> float | None:
    """Share of a frame's returns at 15-60 m in the 64 densest 0.05-degree bins of apparent elevation: about 1 when
    every beam starts at the sensor's origin (each beam's returns lie on one cone), lower when the lasers sit apart
    from it (a beam's apparent elevation then changes with range)."""
    el = elevations(points)
    if el.size == 0:
        return None
    h, _ = np.histogram(el, bins=LINES_BINS)
    return float(np.sort(h)[::-1][:64].sum() / max(h.sum(), 1))


def far_clusters(points: np.ndarray, boxes: np.ndarray, lo: float = FAR_RANGE[0], hi: float = FAR_RANGE[1],
                 cell: float = 4.0, above: float = 0.25, link: float = 0.6) -> np.ndarray:
    """The clusters of non-ground returns at ``lo``-``hi`` m outside every labelled box (grown by 0.3 m a side):
    returns more than ``above`` over their ``cell``-metre cell's ground (its 5th percentile of z), linked within
    ``link`` m. Rows of (points, height, footprint (the larger extent in x or y), |y| of the centre)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from lidarops import points_in_boxes

    xyz = np.asarray(points[:, :3], np.float64)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    p = xyz[(r > lo - 2 * cell) & (r < hi + 2 * cell)]
    if not len(p):
        return np.zeros((0, 4))
    key = np.floor(p[:, :2] / cell).astype(np.int64)
    _, cell_of, per_cell = np.unique(key[:, 0] * 1_000_003 + key[:, 1], return_inverse=True, return_counts=True)
    by_cell = np.split(p[np.argsort(cell_of, kind="stable"), 2], np.cumsum(per_cell)[:-1])
    ground = np.array([np.percentile(z, 5) for z in by_cell])
    rp = np.hypot(p[:, 0], p[:, 1])
    q = p[(rp >= lo) & (rp < hi) & (p[:, 2] > ground[cell_of] + above)]
    if len(boxes) and len(q):
        b = torch.as_tensor(np.asarray(boxes, np.float64)[:, :7].copy())
        b[:, 3:6] += 0.6
        q = q[points_in_boxes(torch.as_tensor(q), b).numpy() < 0]
    if len(q) < 2:
        return np.zeros((0, 4))
    pairs = cKDTree(q).query_pairs(link, output_type="ndarray")
    n, label = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(q),) * 2),
                                    directed=False)
    out = []
    for c in range(n):
        s_ = q[label == c]
        out.append((len(s_), np.ptp(s_[:, 2]), np.ptp(s_[:, :2], axis=0).max(), abs(s_[:, 1].mean())))
    return np.asarray(out, np.float64)


def data_stats(frames) -> dict:
    allint, cars, peds, lines, elev, legs, heads = [], [], np.zeros(2, np.int64), [], [], [], []
    far, far_counts, grades = [], [], []
    for _, points, boxes, names, *_ in frames:
        grades += object_grades(points, boxes, names)
        clusters = far_clusters(points, boxes)
        small = clusters[(clusters[:, 0] >= FAR_POINTS[0]) & (clusters[:, 0] <= FAR_POINTS[1])]
        far.append(small)
        far_counts.append(len(small))
        allint.append(points[:, 3])
        cars.append(object_stats(points, boxes, names))
        peds += grouped_pedestrians(boxes, names)
        legs += pedestrian_lower_half(points, np.asarray(boxes, np.float64), names)
        heads += cyclist_head_offset(points, np.asarray(boxes, np.float64), names)
        share = beam_line_share(points)
        if share is not None:
            lines.append(share)
        elev.append(elevations(points))
    inten = np.concatenate(allint)
    far = np.concatenate(far) if far else np.zeros((0, 4))
    car_int = np.concatenate([c["intensity"] for c in cars])
    bands = np.concatenate([c["bands"] for c in cars])
    inside, halo = (sum(c["halo"][k] for c in cars) for k in (0, 1))
    return {"intensity": inten, "car_intensity": car_int, "range": sum((c["range"] for c in cars), []),
            "points": sum((c["points"] for c in cars), []), "bands": bands, "elevation": np.concatenate(elev),
            "row": {"points": int(len(inten)), "median_intensity": round(float(np.median(inten)), 3),
                    "zero_intensity_share": round(float((inten == 0).mean()), 3),
                    "car_points": int(len(car_int)),
                    "car_median_intensity": round(float(np.median(car_int)), 3) if len(car_int) else None,
                    "car_zero_intensity_share": round(float((car_int == 0).mean()), 3) if len(car_int) else None,
                    **{f"car_share_{b}": round(float(bands[:, k].mean()), 3) if len(bands) else None
                       for k, b in enumerate(BANDS)},
                    "car_halo_share": round(halo / inside, 3) if inside else None,
                    "pedestrians": int(peds[0]),
                    "pedestrians_in_groups_share": round(float(peds[1] / peds[0]), 3) if peds[0] else None,
                    "beam_line_share": round(float(np.median(lines)), 3) if lines else None,
                    "pedestrian_lower_half_share": round(float(np.mean(legs)), 3) if legs else None,
                    "cyclist_head_offset": round(float(np.mean(heads)), 3) if heads else None,
                    "far_clusters_per_frame": round(float(np.mean(far_counts)), 1) if far_counts else None,
                    "far_cluster_height": round(float(np.median(far[:, 1])), 2) if len(far) else None,
                    "far_cluster_footprint": round(float(np.median(far[:, 2])), 2) if len(far) else None,
                    "far_cluster_share_on_road": round(float((far[:, 3] < 10.5).mean()), 2) if len(far) else None,
                    "object_grade_median": round(float(np.median(grades)), 4) if grades else None,
                    "object_grade_p90": round(float(np.percentile(grades, 90)), 4) if grades else None}}


def _sim_name(profile: str | None) -> str:
    return "simulated" + (f", realism {profile}" if profile else "")


def plot(real: dict, sims: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(15, 7.5))
    bins = np.linspace(0, 1, 41)
    for a, key, title in ((ax[0, 0], "intensity", "intensity, all points the camera sees"),
                          (ax[0, 1], "car_intensity", "intensity of the returns on cars")):
        for d, name in ((real, "real KITTI"), *((v, _sim_name(k)) for k, v in sims.items())):
            if len(d[key]):
                a.hist(d[key], bins=bins, density=True, histtype="step", lw=1.5,
                       label=f"{name} (median {np.median(d[key]):.2f}, {100 * (d[key] == 0).mean():.0f} % zero)")
        a.set(title=title, xlabel="intensity", ylabel="density")
        a.legend(fontsize=8)
    for (d, name), m in zip(((real, "real KITTI"), *((v, _sim_name(k)) for k, v in sims.items())), "ox+^"):
        ax[1, 0].scatter(d["range"], d["points"], marker=m, s=18, label=name)
    ax[1, 0].set(title="points per car against range", xlabel="range (m)", ylabel="points in the box", yscale="log")
    ax[1, 0].legend(fontsize=8)
    x = np.arange(3)
    series = ((real, "real KITTI"), *((v, _sim_name(k)) for k, v in sims.items()))
    w = 0.8 / len(series)
    for k, (d, name) in enumerate(series):
        if len(d["bands"]):
            ax[1, 1].bar(x + w * k, d["bands"].mean(0), width=w, label=name)
    ax[1, 1].set_xticks(x + 0.4 - w / 2, BANDS)
    ax[1, 1].set(title="share of a car's returns by height third", ylabel="share")
    ax[1, 1].legend(fontsize=8)
    for d, name in series:
        ax[0, 2].hist(d["elevation"], bins=LINES_BINS[LINES_BINS >= -9.0], density=True, histtype="step", lw=1,
                      label=f"{name} (64 densest bins: {100 * d['row']['beam_line_share']:.0f} %)")
    ax[0, 2].set(title="elevation of the returns at 15-60 m", xlabel="degrees, seen from the origin (0.05 deg bins)",
                 ylabel="density")
    ax[0, 2].legend(fontsize=7, loc="upper left")
    ax[1, 2].axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    print(f"plot: {path}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--real", type=Path, default=ROOT / ".peers" / "kitti_real",
                   help="KITTI folder of real frames (ImageSets/val.txt, training/velodyne, calib, label_2)")
    p.add_argument("--checkpoint", nargs="+", default=["pointpillars_synth", "pointpillars_synth_real"],
                   help="detectors: files or shipped names")
    p.add_argument("--sim-frames", type=int, default=40, help="simulated frames per profile (0: the real-scan "
                                                                   "figures alone)")
    p.add_argument("--realism", nargs="*", default=[None], help="the simulator's realism profiles to compare "
                                                                   "(none: as cast; kitti; kitti_dr; a profile with "
                                                                   "fields changed: kitti:roadside_structures=0.7)")
    p.add_argument("--sim-detect", action="store_true", help="also run each checkpoint on each profile's simulated "
                                                             "frames: found and false positives against their labels")
    p.add_argument("--plot", type=Path, default=None)
    p.add_argument("--json", action="store_true")
    p.add_argument("--fp-list", action="store_true", help="print each false positive above 0.5 on the real frames")
    p.add_argument("--aspects", type=int, default=0, metavar="N",
                   help="cyclists along the road and broadside, pedestrians in groups and alone: what each checkpoint "
                        f"takes them for, in N simulated frames of {ASPECT_PROFILE}, the cyclists also put on the real "
                        "frames' road (0: not measured)")
    p.add_argument("--curve-plot", type=Path, default=None,
                   help="plot each checkpoint's found share against false positives per frame by score threshold")
    args = p.parse_args(argv)
    use_real = str(args.real) != "none"
    if use_real and not (args.real / "ImageSets" / "val.txt").is_file():
        p.error(f"--real {args.real}: no ImageSets/val.txt; bring the real frames with "
                "tools/sim2real/kitti_real_frames.sh (they are not in git), or --real none for the simulated "
                "frames alone")
    if not use_real and not (args.sim_detect and args.sim_frames > 0):
        p.error("--real none needs --sim-detect and --sim-frames > 0 (there is nothing else to measure)")
    for profile in args.realism:
        try:
            parse_profile(profile)
        except (ValueError, TypeError) as e:
            p.error(f"--realism {profile!r}: {e}")
    from lidarops.models import load_model, weights

    real = list(real_frames(args.real)) if use_real else []
    rows = []
    models = {ck: load_model(weights.path(ck) if ck in weights.available() else ck).eval() for ck in args.checkpoint}
    curves = {}
    for ck, model in models.items() if use_real else ():
        figs, top, fps, kept = [], 0.0, [], []
        for fid, points, boxes, names, difficulty, calib, dontcare in real:
            db, ds, dn = detections(model, points)
            overlap = dontcare_overlap(db, calib, dontcare)
            gt = boxes.astype(np.float64)
            figs.append(frame_figures(gt, names, db, ds, dn, difficulty, overlap))
            kept.append((gt, names, difficulty, db, ds, dn, overlap))
            fps += fp_rows(fid, points, db, ds, dn, figs[-1]["alone"], overlap)
            top = max([top, *ds.tolist()])
        cv = curves[Path(str(ck)).name] = score_curve(kept)
        row = {"op": "sim2real", "case": f"real_kitti:{Path(str(ck)).name}", "checkpoint": str(ck), **summarize(figs),
               "max_score": round(top, 3), "curve_scores": cv["scores"],
               **{f"curve_{c}_found_easy_moderate": cv["found_em"][c] for c in CLASSES},
               "curve_fp_per_frame": cv["fp_per_frame"],
               "curve_fp_per_frame_outside_dontcare": cv["fp_per_frame_outside_dontcare"]}
        rows.append(row)
        print(f"{ck}: " + ", ".join(f"{c} {row[f'{c}_found_3d{THRESHOLDS_3D[c][0]}']}/{row[f'{c}_labelled']} at 3D "
                                    f"{THRESHOLDS_3D[c][0]} (easy and moderate: "
                                    f"{row[f'{c}_found_3d{THRESHOLDS_3D[c][0]}_easy_moderate']}/"
                                    f"{row[f'{c}_labelled_easy_moderate']})" for c in CLASSES)
              + f"; false positives per frame above 0.5: {row['fp_per_frame_above_0.5']} "
              f"({row['fp_per_frame_above_0.5_outside_dontcare']} outside DontCare regions)", flush=True)
        print_table(f"{Path(str(ck)).name}: kept at score >= s, easy and moderate found / labelled",
                    ["score >=", *CLASSES, "FP / frame", "outside DontCare"],
                    [[s, *(f"{cv['found_em'][c][k]} / {cv['labelled_em'][c]}" for c in CLASSES),
                      cv["fp_per_frame"][k], cv["fp_per_frame_outside_dontcare"][k]] for k, s in enumerate(cv["scores"])],
                    right=range(0, 6))
        if args.fp_list and fps:
            keys = list(fps[0])
            print_table(f"{Path(str(ck)).name}: false positives above 0.5, nearest first", keys,
                        [[r[k] for k in keys] for r in sorted(fps, key=lambda r: r["range_m"])],
                        right=range(2, len(keys)))
    if args.sim_detect and args.sim_frames > 0:
        for profile in [None if r in (None, "none") else r for r in args.realism]:
            frames = list(sim_frames(args.sim_frames, profile))
            for ck, model in models.items():
                figs = [frame_figures(*seen_labels(points, boxes, names), *detections(model, points))
                        for _, points, boxes, names in frames]
                row = {"op": "sim2real", "case": f"sim:{profile or 'none'}:{Path(str(ck)).name}", "checkpoint": str(ck),
                       "realism": profile, **summarize(figs)}
                rows.append(row)
                print(f"{ck} on {args.sim_frames} simulated frames ({profile or 'as cast'}): "
                      + ", ".join(f"{c} {row[f'{c}_found_3d{THRESHOLDS_3D[c][0]}']}/{row[f'{c}_labelled']}"
                                  for c in CLASSES)
                      + f"; false positives per frame above 0.3 / 0.5: {row['fp_per_frame_above_0.3']} / "
                      f"{row['fp_per_frame_above_0.5']}", flush=True)
    if args.aspects > 0:
        frames = list(sim_frames(args.aspects, ASPECT_PROFILE))
        table = []
        for ck, model in models.items():
            got = cyclist_aspects(model, frames, real)
            rows.append({"op": "sim2real", "case": f"cyclist_aspects:{Path(str(ck)).name}", "checkpoint": str(ck),
                         "frames": args.aspects, "realism": ASPECT_PROFILE,
                         **{f"{k}_as_{c.lower()}": n for k, counts in got.items() for c, n in counts.items()}})
            table += [[Path(str(ck)).name, k, sum(counts.values()), *counts.values()] for k, counts in got.items()]
        print_table(f"what cyclists and pedestrians are taken for (a cyclist if any detection at 3D IoU >= 0.25 is "
                    f"one, else the best; broadside: aspect >= {BROADSIDE:g} degrees)",
                    ["checkpoint", "objects", "n", *CLASSES, "none"], table, right=range(2, 7))
    sims = {}
    stat_rows = []
    if use_real:
        rstats = data_stats(real)
        stat_rows.append({"op": "sim2real", "case": "stats:real_kitti", "frames": len(real), **rstats["row"]})
    for profile in [None if r in (None, "none") else r for r in args.realism] if args.sim_frames > 0 else []:
        sims[profile] = data_stats(sim_frames(args.sim_frames, profile))
        stat_rows.append({"op": "sim2real", "case": "stats:simulated_driving_city" + (f":{profile}" if profile else ""),
                          "frames": args.sim_frames, "realism": profile, **sims[profile]["row"]})
    rows += stat_rows
    keys = ["case", "median_intensity", "zero_intensity_share", "car_median_intensity", "car_zero_intensity_share",
            "car_share_bottom", "car_share_middle", "car_share_top", "car_halo_share", "pedestrians_in_groups_share",
            "beam_line_share", "pedestrian_lower_half_share", "cyclist_head_offset", "far_clusters_per_frame",
            "far_cluster_height", "far_cluster_footprint", "far_cluster_share_on_road", "object_grade_median",
            "object_grade_p90"]
    print_table("real against simulated" if use_real else "simulated", keys,
                [[r.get(k, "") for k in keys] for r in stat_rows], right=range(1, len(keys)))
    if args.plot and use_real:
        plot(rstats, sims, args.plot)
    if args.curve_plot and curves:
        plot_curves(curves, args.curve_plot)
    if args.json:
        print("results:", write_results("sim2real", "cpu", rows, env_meta("cpu"), replace_by="case"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
