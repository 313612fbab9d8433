"""lidarops.data.viz: the bird's-eye view carries a key of what its colours show and takes the drawn area's
shape."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")


@pytest.mark.parametrize("color_by, key", [("z", "height z (m)"), ("intensity", "intensity"), ("range", "range (m)")])
def test_save_bev_has_a_colour_key_and_fits_a_wide_view(tmp_path, monkeypatch, color_by, key):
    from lidarops.data import viz
    from lidarops.data.frame import Frame

    figures, new_figure = [], viz.new_figure
    monkeypatch.setattr(viz, "new_figure", lambda *a, **k: figures.append(new_figure(*a, **k)) or figures[-1])
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform([-60, -10, -2, 0], [60, 10, 1, 1], (2000, 4))]).astype(np.float32)
    frame = Frame(points=points, boxes=np.zeros((0, 7), np.float32), labels=np.zeros(0, np.int64))
    viz.save_bev(frame, tmp_path / "bev.png", color_by=color_by)
    fig = figures[0]
    ax, bar = fig.axes
    assert bar.get_ylabel() == key
    w, h = fig.get_size_inches()
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert (x1 - x0) > 4 * (y1 - y0) and h / w < 0.5  # a 120 x 20 m view is not drawn in a square figure
    assert (tmp_path / "bev.png").read_bytes()[:4] == b"\x89PNG"
