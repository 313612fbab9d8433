"""Random KITTI-style annotations for the evaluation tests (tests/eval/) and benchmarks/bm_kitti_eval.py.

Frames hold Cars, Pedestrians, Cyclists, Vans, Persons sitting, Trucks and DontCare regions in front of the
camera, with 2D boxes projected with KITTI's default P2 and clipped to the image, random truncation and
occlusion levels; detections are jittered copies of most objects (some with the wrong class or a flipped
heading) and, scoring lower on the whole, false positives anywhere, some inside DontCare regions. Fields as OpenPCDet holds them
(``dimensions`` l, h, w).
"""
from __future__ import annotations

import numpy as np

from lidarops.data.formats.kitti import KITTI_IMAGE_SIZE, KittiCalib

GT_CLASSES = ("Car", "Pedestrian", "Cyclist", "Van", "Person_sitting", "Truck")
GT_WEIGHTS = (0.5, 0.2, 0.1, 0.1, 0.04, 0.06)
MEAN_LHW = {"Car": (3.9, 1.55, 1.6), "Pedestrian": (0.8, 1.75, 0.6), "Cyclist": (1.75, 1.7, 0.6),
            "Van": (5.0, 2.1, 1.9), "Person_sitting": (0.8, 1.3, 0.6), "Truck": (10.0, 3.2, 2.6)}
_P2 = KittiCalib.default().P2


def image_boxes(location: np.ndarray, lhw: np.ndarray, rotation_y: np.ndarray,
                image_size: tuple[int, int] = KITTI_IMAGE_SIZE) -> np.ndarray:
    """(K, 4) 2D boxes of camera boxes: corners projected with P2, clipped to the image."""
    k = location.shape[0]
    if k == 0:
        return np.zeros((0, 4))
    sx = np.array([1, 1, -1, -1, 1, 1, -1, -1]) / 2
    sy = np.array([0, 0, 0, 0, -1, -1, -1, -1])
    sz = np.array([1, -1, -1, 1, 1, -1, -1, 1]) / 2
    lx, ly, lz = lhw[:, :1] * sx, lhw[:, 1:2] * sy, lhw[:, 2:3] * sz
    c, s = np.cos(rotation_y)[:, None], np.sin(rotation_y)[:, None]
    pts = np.stack([c * lx + s * lz, ly, -s * lx + c * lz], -1) + location[:, None, :]
    h = pts @ _P2[:, :3].T + _P2[:, 3]
    depth = np.maximum(h[..., 2], 0.1)
    u, v = h[..., 0] / depth, h[..., 1] / depth
    w, hh = image_size
    return np.stack([np.clip(u.min(1), 0, w - 1), np.clip(v.min(1), 0, hh - 1), np.clip(u.max(1), 0, w - 1),
                     np.clip(v.max(1), 0, hh - 1)], 1)


def _alpha(location: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    return (rotation_y - np.arctan2(location[:, 0], location[:, 2]) + np.pi) % (2 * np.pi) - np.pi


def _objects(rng: np.random.Generator, names: np.ndarray) -> dict:
    k = names.shape[0]
    lhw = np.array([MEAN_LHW[n] for n in names]).reshape(k, 3) * rng.uniform(0.85, 1.15, (k, 3))
    location = np.stack([rng.uniform(-15, 15, k), rng.normal(1.65, 0.1, k), rng.uniform(4, 55, k)], 1)
    rotation_y = rng.uniform(-np.pi, np.pi, k)
    return {"name": names, "dimensions": lhw, "location": location, "rotation_y": rotation_y}


def random_frame(rng: np.random.Generator, num_gt: int = 15, num_dt: int = 20) -> tuple[dict, dict]:
    """One frame's (gt, dt) annotation dicts."""
    num_dc = int(rng.integers(0, 3))
    gt = _objects(rng, rng.choice(GT_CLASSES, size=max(num_gt - num_dc, 0), p=GT_WEIGHTS))
    k = gt["name"].shape[0]
    gt["bbox"] = image_boxes(gt["location"], gt["dimensions"], gt["rotation_y"])
    gt["alpha"] = _alpha(gt["location"], gt["rotation_y"])
    gt["truncated"] = rng.choice([0.0, 0.0, 0.0, 0.1, 0.2, 0.4, 0.6], k)
    gt["occluded"] = rng.choice([0, 0, 0, 1, 2, 3], k)
    # DontCare regions, as KITTI writes them (-1 / -1000 / -10 fillers)
    dc_lt = rng.uniform([0, 100], [1100, 250], (num_dc, 2))
    dc_box = np.concatenate([dc_lt, dc_lt + rng.uniform(20, 140, (num_dc, 2))], 1)
    gt = {
        "name": np.concatenate([gt["name"], np.full(num_dc, "DontCare")]),
        "truncated": np.concatenate([gt["truncated"], np.full(num_dc, -1.0)]),
        "occluded": np.concatenate([gt["occluded"], np.full(num_dc, -1)]),
        "alpha": np.concatenate([gt["alpha"], np.full(num_dc, -10.0)]),
        "bbox": np.concatenate([gt["bbox"], dc_box]),
        "dimensions": np.concatenate([gt["dimensions"], np.full((num_dc, 3), -1.0)]),
        "location": np.concatenate([gt["location"], np.full((num_dc, 3), -1000.0)]),
        "rotation_y": np.concatenate([gt["rotation_y"], np.full(num_dc, -10.0)]),
    }
    # detections: jittered copies of ~75% of the objects, the rest false positives
    copies = np.flatnonzero(rng.random(k) < 0.75)[:num_dt]
    names = gt["name"][copies].copy()
    confused = rng.random(copies.shape[0]) < 0.05
    names[confused] = rng.choice(["Car", "Pedestrian", "Cyclist"], int(confused.sum()))
    scale = gt["dimensions"][copies]
    dt = {
        "name": names,
        "dimensions": scale * rng.normal(1.0, 0.05, scale.shape),
        "location": gt["location"][copies] + rng.normal(0, 0.04, (copies.shape[0], 3)) * scale[:, [0, 1, 0]],
        "rotation_y": gt["rotation_y"][copies] + rng.normal(0, 0.1, copies.shape[0])
        + np.pi * (rng.random(copies.shape[0]) < 0.1),
    }
    fp = _objects(rng, rng.choice(["Car", "Pedestrian", "Cyclist"], size=num_dt - copies.shape[0]))
    dt = {key: np.concatenate([dt[key], fp[key]]) for key in dt}
    dt["bbox"] = image_boxes(dt["location"], dt["dimensions"], dt["rotation_y"])
    # a few false positives inside DontCare regions (2D box only)
    for j, d in enumerate(range(copies.shape[0], min(copies.shape[0] + num_dc, num_dt))):
        box = dc_box[j]
        dt["bbox"][d] = box + np.array([0.1, 0.1, -0.1, -0.1]) * (box[2:] - box[:2]).repeat(2)[[0, 2, 1, 3]]
    dt["alpha"] = _alpha(dt["location"], dt["rotation_y"])
    # copies mostly outscore the false positives, as a trained detector's do
    dt["score"] = np.concatenate([rng.uniform(0.2, 1.0, copies.shape[0]), rng.uniform(0.0, 0.6, num_dt - copies.shape[0])])
    return gt, dt


def random_annos(num_frames: int, seed: int = 0, num_gt: int = 15, num_dt: int = 20) -> tuple[list, list]:
    """(gt_annos, dt_annos) of ``num_frames`` random frames; ``num_gt`` / ``num_dt`` objects per frame on
    average (each frame draws its counts around them)."""
    rng = np.random.default_rng(seed)
    gts, dts = [], []
    for _ in range(num_frames):
        gt, dt = random_frame(rng, int(rng.integers(num_gt // 2, num_gt * 3 // 2 + 1)),
                              int(rng.integers(num_dt // 2, num_dt * 3 // 2 + 1)))
        gts.append(gt)
        dts.append(dt)
    return gts, dts
