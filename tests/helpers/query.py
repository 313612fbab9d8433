"""Random object centres for frame-index tests: one row per counted object of a counts table."""
from __future__ import annotations

import numpy as np


def centres_of(rng: np.random.Generator, counts: dict, classes, x=(-5.0, 40.0), y=(-20.0, 20.0),
               ties: float = 0.0) -> dict:
    """Centres of ``counts[c][i]`` objects of each class ``c`` in each frame, uniform in ``x`` by ``y``
    metres; a share ``ties`` of them sits exactly on x = 0, 10 or 20 (region bounds in the tests)."""
    rows = {"frame_id": [], "class": [], "x": [], "y": [], "score": []}
    for i, fid in enumerate(counts["frame_id"]):
        for c in classes:
            for _ in range(int(counts[c][i])):
                rows["frame_id"].append(int(fid))
                rows["class"].append(c)
                rows["x"].append(float(rng.choice([0.0, 10.0, 20.0]) if rng.random() < ties else rng.uniform(*x)))
                rows["y"].append(float(rng.uniform(*y)))
                rows["score"].append(float(rng.uniform(0.3, 1)))
    return rows
