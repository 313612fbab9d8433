"""CounterNet as a count source of the frame index (lidarops.query.build.CounterSource, ``lidarops index build
--source counter``): the index holds the network's own counts and centres, frame by frame, beside the labels."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

from lidarops.cli import main  # noqa: E402
from lidarops.query import FrameIndex  # noqa: E402
from lidarops.query.build import CounterSource  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def _counternet(tmp_path):
    from lidarops.checkpoint import format_fields, save_checkpoint
    from lidarops.config import load_config
    from lidarops.models.counternet import CounterNet

    cfg = load_config(ROOT / "configs" / "counternet" / "counternet_synth.yaml")
    cfg["CLASS_NAMES"] = ["Car", "Pedestrian", "Cyclist"]
    cfg["MODEL"]["BACKBONE_2D"]["LAYER_NUMS"] = [1, 1, 1]
    cfg["MODEL"]["COUNT_HEAD"].update(SHARED_CHANNELS=8, HEAD_CHANNELS=8, THRESHOLD=0.05, OTSU=False)
    torch.manual_seed(0)
    model = CounterNet(cfg).eval()
    path = tmp_path / "counternet.pth"
    save_checkpoint({**format_fields(), "model_class": "CounterNet", "model_config": model.config.to_dict(),
                     "class_names": model.config.class_names, "model_state": model.state_dict()}, [path])
    return model, path


class _Frame:
    def __init__(self, points):
        self.points = points


def test_counter_source_reports_the_networks_counts_and_centres(tmp_path):
    model, _ = _counternet(tmp_path)
    g = torch.Generator().manual_seed(1)
    frames = [_Frame(torch.rand(3000, 4, generator=g) * torch.tensor([60.0, 70.0, 3.0, 1.0])
                     - torch.tensor([0.0, 35.0, 2.0, 0.0])) for _ in range(2)]
    out = CounterSource(model)(frames)
    batch = torch.cat([torch.cat([torch.full((3000, 1), float(i)), f.points], 1) for i, f in enumerate(frames)])
    want = model.predict({"points": batch, "batch_size": 2})
    for (counts, centres), w in zip(out, want):
        assert list(counts) == ["Car", "Pedestrian", "Cyclist"]
        assert list(counts.values()) == w["counts"].tolist() and sum(counts.values()) == len(centres)
        assert [c[0] for c in centres] == [["Car", "Pedestrian", "Cyclist"][int(k)] for k in w["centres"][:, 2]]
        np.testing.assert_allclose([c[1:] for c in centres], w["centres"][:, [0, 1, 3]].numpy(), rtol=1e-6)
    assert set(CounterSource(model).stage_seconds) == {"to_device", "predict", "read_back"}


@pytest.mark.slow  # simulates frames and runs the network on the CPU: seconds
def test_index_build_with_source_counter(tmp_path, capsys):
    model, ckpt = _counternet(tmp_path)
    out = tmp_path / "idx"
    args = ["index", "build", "--scenario", "driving_city", "--frames", "2", "--out", str(out), "--no-progress",
            "--workers", "0", "--device", "cpu"]
    assert main(args) == 0
    assert main(args + ["--source", "counter", "--checkpoint", str(ckpt)]) == 0
    idx = FrameIndex.open(out)
    assert set(idx.sources) == {"labels", "counter"}
    assert idx.frame_count("counter") == 2 and {"Car", "Pedestrian", "Cyclist"} <= set(idx.classes)


def test_source_counter_errors_are_one_line(tmp_path, capsys):
    _, ckpt = _counternet(tmp_path)
    base = ["index", "build", "--scenario", "driving_city", "--frames", "1", "--out", str(tmp_path / "i"),
            "--no-progress", "--device", "cpu", "--workers", "0"]
    assert main(base + ["--source", "counter"]) == 0  # the shipped CounterNet (seven classes): an index of its own
    capsys.readouterr()
    assert FrameIndex.open(tmp_path / "i").sources == ["counter"]
    assert main(base + ["--source", "detector", "--checkpoint", str(ckpt)]) == 2
    assert "holds a CounterNet" in capsys.readouterr().err
    assert main(base + ["--source", "counter", "--checkpoint", str(ROOT / "lidarops/weights/pointpillars_synth.pth")]) == 2
    assert "needs a CounterNet" in capsys.readouterr().err
