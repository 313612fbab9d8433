"""``lidarops data synth|show`` (lidarops/cli/data.py), run in-process."""
from __future__ import annotations

import numpy as np
import pytest

from lidarops.cli import main
from .helpers import one_error_line

pytest.importorskip("matplotlib")


def _is_png(path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_synth_kitti_and_show(tmp_path, capsys):
    out = tmp_path / "kitti"
    assert main(["data", "synth", "--scenario", "driving_city", "--frames", "2", "--format", "kitti",
                 "--out", str(out), "--no-progress", "--object-counts", '{"Car": 12, "Pedestrian": [2, 4]}']) == 0
    split = out / "training"
    assert sorted(p.name for p in (split / "velodyne").iterdir()) == ["000000.bin", "000001.bin"]
    assert (split / "label_2" / "000001.txt").is_file() and (split / "calib" / "000001.txt").is_file()
    ids = (out / "ImageSets" / "trainval.txt").read_text().split()
    assert ids == ["000000", "000001"]
    from lidarops.data.formats import KittiDataset

    frame = KittiDataset(out)[1]
    assert frame.num_points > 50_000 and frame.num_boxes > 0
    png = tmp_path / "bev.png"
    assert main(["data", "show", str(out), "--index", "1", "--out", str(png)]) == 0
    assert _is_png(png)
    png2 = tmp_path / "bin.png"
    assert main(["data", "show", str(split / "velodyne" / "000000.bin"), "--out", str(png2), "--fov", "90"]) == 0
    assert _is_png(png2)
    assert "wrote" in capsys.readouterr().out


def test_synth_pandaset_and_show(tmp_path):
    pytest.importorskip("pandas")
    out = tmp_path / "pandaset"
    assert main(["data", "synth", "--scenario", "drone_lock", "--frames", "2", "--format", "pandaset",
                 "--out", str(out), "--no-progress"]) == 0
    seq = out / "001"
    assert (seq / "lidar" / "01.pkl.gz").is_file() and (seq / "lidar" / "poses.json").is_file()
    from lidarops.data.formats import PandaSetSequence

    frames = PandaSetSequence(seq)
    assert len(frames) == 2
    t = frames[1].t
    assert np.all(np.diff(t) >= 0) and 0.1 <= t.min() and t.max() < 0.2
    for path in (out, seq, seq / "lidar" / "00.pkl.gz"):
        png = tmp_path / f"{path.name}.png"
        assert main(["data", "show", str(path), "--out", str(png)]) == 0
        assert _is_png(png)


def test_show_scenario_nuscenes_and_modelnet(tmp_path):
    png = tmp_path / "scenario.png"
    assert main(["data", "show", "drone_bridge", "--out", str(png), "--index", "1"]) == 0
    assert _is_png(png)
    from lidarops.data.formats import write_nuscenes_bin

    rng = np.random.default_rng(0)
    nus = write_nuscenes_bin(tmp_path / "x__LIDAR_TOP__1533151603547590.pcd.bin",
                             np.concatenate([rng.normal(0, 15, (3000, 3)), rng.uniform(0, 255, (3000, 1))], 1))
    assert main(["data", "show", str(nus), "--out", str(tmp_path / "nus.png"), "--color-by", "intensity"]) == 0
    assert _is_png(tmp_path / "nus.png")
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "ply_data_test0.h5", "w") as f:
        f.create_dataset("data", data=rng.normal(size=(2, 256, 3)).astype(np.float32))
        f.create_dataset("label", data=np.array([[7], [0]], np.uint8))
    assert main(["data", "show", str(tmp_path / "ply_data_test0.h5"), "--index", "1", "--out", str(tmp_path / "mn.png")]) == 0
    assert _is_png(tmp_path / "mn.png")


def test_cli_errors(tmp_path, capsys):
    assert main(["data", "show", str(tmp_path / "missing"), "--out", str(tmp_path / "x.png")]) == 2
    assert "no such file" in one_error_line(capsys.readouterr().err, "data show")
    (tmp_path / "broken.bin").write_bytes(b"\x00" * 7)
    assert main(["data", "show", str(tmp_path / "broken.bin"), "--out", str(tmp_path / "x.png")]) == 2
    assert "broken.bin" in one_error_line(capsys.readouterr().err, "data show")
    assert main(["data", "show", "driving_city", "--index", "-1"]) == 2
    assert "--index must be >= 0" in one_error_line(capsys.readouterr().err, "data show")
    kitti = tmp_path / "kitti"
    assert main(["data", "synth", "--frames", "1", "--out", str(kitti), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["data", "show", str(kitti), "--index", "5", "--out", str(tmp_path / "x.png")]) == 2  # 1 frame
    assert "out of range" in one_error_line(capsys.readouterr().err, "data show")
    assert main(["data", "synth", "--out", str(tmp_path / "o"), "--frames", "1", "--object-counts", "{oops"]) == 2
    assert "--object-counts" in one_error_line(capsys.readouterr().err, "data synth")
    assert main(["data", "synth", "--frames", "0", "--out", str(tmp_path / "none")]) == 2
    assert "at least 1 in all" in one_error_line(capsys.readouterr().err, "data synth")
    assert main(["data"]) == 2
    with pytest.raises(SystemExit):
        main(["data", "synth", "--scenario", "mars", "--out", str(tmp_path)])
