"""``lidarops data synth|show`` (lidarops/cli/data.py), run in-process, and ``lidarops data synth`` for training
sets (workers, scenarios, scene-disjoint splits, recipe)."""
from __future__ import annotations

import argparse
import importlib.util
import json

import numpy as np
import pytest

from lidarops.cli import data as data_cli
from lidarops.cli import main
from lidarops.data.detection import train_val_datasets
from lidarops.data.formats.kitti import write_image_sets
from .helpers import one_error_line

#: ``lidarops data show`` draws with matplotlib
needs_matplotlib = pytest.mark.skipif(importlib.util.find_spec("matplotlib") is None,
                                      reason="needs matplotlib (lidarops data show)")


def _is_png(path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


@needs_matplotlib
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


@needs_matplotlib
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


@needs_matplotlib
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


@needs_matplotlib
def test_cli_errors(tmp_path, capsys):
    assert main(["data", "show", str(tmp_path / "missing"), "--out", str(tmp_path / "x.png")]) == 2
    assert "missing not found: neither a file, a dataset folder nor a scenario" in \
        one_error_line(capsys.readouterr().err, "data show")
    assert main(["data", "show", "driving_cty", "--out", str(tmp_path / "x.png")]) == 2
    assert "did you mean the scenario driving_city?" in one_error_line(capsys.readouterr().err, "data show")
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


# ---------------------------------------------------------------------------------------------
# lidarops data synth for training sets
# ---------------------------------------------------------------------------------------------
def _files(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "recipe.json"}


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_synth_workers_scenarios_scene_split_recipe(tmp_path):
    common = ["data", "synth", "--scenario", "driving_city", "driving_highway", "--frames", "6", "3",
              "--frames-per-scene", "3", "--val-fraction", "0.5", "--seed", "7", "--no-progress",
              "--object-counts", '{"Car": 10, "Pedestrian": 4, "Cyclist": 2}']
    one, two = tmp_path / "w1", tmp_path / "w2"
    assert main(common + ["--out", str(one), "--workers", "1"]) == 0
    assert main(common + ["--out", str(two), "--workers", "2"]) == 0
    files = _files(one)
    assert len([f for f in files if f.startswith("training/velodyne/")]) == 9
    assert files == _files(two)  # bytes of every scan, label, calibration and id list
    sets = {name: (one / "ImageSets" / f"{name}.txt").read_text().split() for name in ("train", "val", "trainval")}
    assert sets["trainval"] == [f"{i:06d}" for i in range(9)] and sorted(sets["train"] + sets["val"]) == sets["trainval"]
    scene = {f"{i:06d}": (0, i // 3) if i < 6 else (1, (i - 6) // 3) for i in range(9)}
    val_scenes = {scene[i] for i in sets["val"]}
    assert len(val_scenes) == 2 and val_scenes.isdisjoint({scene[i] for i in sets["train"]})
    assert all(sum(scene[i] == s for i in sets["val"]) == 3 for s in val_scenes)  # whole scenes
    recipe = json.loads((one / "recipe.json").read_text())
    assert [(s["scenario"], s["frames"], s["seed"], s["first_id"], s["scenes"], s["sensor"]) for s in recipe["scenarios"]] \
        == [("driving_city", 6, 7, 0, 2, "hdl64"), ("driving_highway", 3, 1007, 6, 1, "hdl64")]
    assert recipe["frames_per_scene"] == 3 and recipe["val_fraction"] == 0.5 and recipe["lidarops_version"]
    assert recipe["command"].startswith("lidarops data synth --format kitti --scenario driving_city driving_highway")
    assert recipe["image_sets"] == {"trainval": 9, "train": len(sets["train"]), "val": len(sets["val"])}
    train, val = train_val_datasets(one)
    assert train.ids == sets["train"] and val.ids == sets["val"] and train.recipe == recipe
    # the two scenarios are different scenes: the highway frames are not the city ones
    assert files["training/velodyne/000006.bin"] != files["training/velodyne/000000.bin"]


def test_synth_plan_and_one_frame_scenes(tmp_path):
    args = argparse.Namespace(scenario=["driving_city", "driving_highway", "driving_city"], frames=[8], seed=2)
    plan = data_cli._scenario_plan(args)
    assert [(p["frames"], p["seed"], p["first_id"]) for p in plan] == [(3, 2, 0), (3, 1002, 3), (2, 2002, 6)]
    with pytest.raises(ValueError, match="one count per scenario"):
        data_cli._scenario_plan(argparse.Namespace(scenario=["driving_city"], frames=[1, 2], seed=0))
    # one frame per scene and one scenario: the validation ids write_image_sets has always picked
    data_cli._write_scene_image_sets(tmp_path / "a", [{"frames": 20, "first_id": 0}], 1, 0.2, 5)
    write_image_sets(tmp_path / "b", [f"{i:06d}" for i in range(20)], val_fraction=0.2, seed=5)
    for name in ("train", "val", "trainval"):
        assert (tmp_path / "a" / "ImageSets" / f"{name}.txt").read_text() == \
            (tmp_path / "b" / "ImageSets" / f"{name}.txt").read_text()
    assert len((tmp_path / "a" / "ImageSets" / "val.txt").read_text().split()) == 4
    assert data_cli._val_scene_counts([2, 1], 0.34) == [1, 0] and data_cli._val_scene_counts([5, 5], 0.3) == [2, 1]


def test_synth_labels_whole_view_for_drone_scenes(tmp_path, capsys):
    """The drone scenes' Avia sees far above a KITTI camera's image: by default their label files hold every drone
    (--labels all), the driving scenes' only the camera's view; --labels overrides either; the recipe says which."""
    from lidarops.data.formats.kitti import KittiCalib, camera_to_lidar_boxes, kitti_fov_mask, read_label
    from lidarops.data.synthetic import SyntheticFrames

    common = ["data", "synth", "--scenario", "drone_bridge", "--frames", "6", "--seed", "11", "--no-progress"]
    whole, camera = tmp_path / "whole", tmp_path / "camera"
    assert main(common + ["--out", str(whole)]) == 0
    assert main(common + ["--out", str(camera), "--labels", "camera"]) == 0
    frames = SyntheticFrames("drone_bridge", num_frames=6, seed=11)
    calib = KittiCalib.default()
    outside = 0
    for i in range(6):
        frame = frames[i]
        labelled = frame.boxes[frame.num_points_in_box >= 1]
        in_image = kitti_fov_mask(labelled[:, :3], calib)
        outside += int((~in_image).sum())
        for folder, want in ((whole, labelled), (camera, labelled[in_image])):
            rows = read_label(folder / "training" / "label_2" / f"{i:06d}.txt")
            got = camera_to_lidar_boxes(rows.location, rows.dimensions, rows.rotation_y, calib)
            assert got.shape == want.shape and np.allclose(got[:, :6], want[:, :6], atol=1e-4), (folder.name, i)
    assert outside >= 1  # drones above the image: the two folders differ
    recipe = json.loads((whole / "recipe.json").read_text())
    assert [s["labels"] for s in recipe["scenarios"]] == ["all"] and "--labels" not in recipe["command"]
    recipe = json.loads((camera / "recipe.json").read_text())
    assert [s["labels"] for s in recipe["scenarios"]] == ["camera"] and "--labels camera" in recipe["command"]
    plan = data_cli._scenario_plan(argparse.Namespace(scenario=["driving_city", "drone_lock"], frames=[2], seed=0))
    assert [p["labels"] for p in plan] == ["camera", "all"]
    assert main(["data", "synth", "--out", str(tmp_path / "p"), "--format", "pandaset", "--scenario", "drone_lock",
                 "--frames", "1", "--labels", "all", "--no-progress"]) == 2
    assert "--labels" in capsys.readouterr().err


def test_synth_errors(tmp_path, capsys):
    existing = tmp_path / "file.txt"
    existing.write_text("x")
    for extra in (["--out", str(existing)], ["--out", str(tmp_path / "o"), "--frames", "1", "2"],
                  ["--out", str(tmp_path / "o"), "--workers", "0"],
                  ["--out", str(tmp_path / "o"), "--format", "pandaset", "--scenario", "drone_lock", "drone_bridge"]):
        assert main(["data", "synth", "--no-progress", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("lidarops data synth: error:") and "\n" not in err
    assert main(["data", "synth", "--out", str(existing)]) == 2 and "existing file" in capsys.readouterr().err


def test_data_synth_takes_a_profile_with_fields_changed(tmp_path, run_cli, capsys):
    """``--realism kitti:crossing_groups=0.5`` makes the frames and the recipe records it as written; a field that
    is not one is refused naming it."""
    import json

    out = tmp_path / "synth"
    code, _, err = run_cli(["data", "synth", "--frames", "1", "--seed", "7", "--val-fraction", "0", "--out", out,
                            "--no-progress", "--realism", "kitti:crossing_groups=0.5"])
    assert code == 0, err
    assert json.loads((out / "recipe.json").read_text())["realism"] == "kitti:crossing_groups=0.5"
    with pytest.raises(SystemExit) as e:
        run_cli(["data", "synth", "--frames", "1", "--out", tmp_path / "bad", "--no-progress", "--realism",
                 "kitti:nope=1"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--realism" in err and "'nope' is not a Realism field" in err, err


def test_data_synth_takes_one_profile_per_scenario(tmp_path, run_cli, capsys):
    """``--scenario drone_lock drone_lock --realism avia none``: a mix of the profile's frames and ray-cast ones, each
    the simulator's frame of its scenario, seed and profile; the recipe records the profile of each entry; a count
    that fits neither one nor one per scenario is refused."""
    import json

    from lidarops.data.formats.kitti import read_velodyne
    from lidarops.data.synthetic import SyntheticFrames

    out = tmp_path / "mix"
    code, _, err = run_cli(["data", "synth", "--scenario", "drone_lock", "drone_lock", "--frames", "2", "2", "--seed",
                            "7", "--val-fraction", "0", "--out", out, "--no-progress", "--realism", "avia", "none"])
    assert code == 0, err
    recipe = json.loads((out / "recipe.json").read_text())
    assert recipe["realism"] == ["avia", None]
    assert [(e["seed"], e["realism"], e["first_id"]) for e in recipe["scenarios"]] == [(7, "avia", 0), (1007, None, 2)]
    assert "--realism avia none" in recipe["command"]
    for frame_id, seed, profile, index in ((1, 7, "avia", 1), (3, 1007, None, 1)):
        want = SyntheticFrames("drone_lock", num_frames=2, seed=seed, realism=profile)[index]
        got = read_velodyne(out / "training" / "velodyne" / f"{frame_id:06d}.bin")
        assert got.shape == want.points[:, :4].shape and np.allclose(got, want.points[:, :4], atol=1e-6)
    plain = SyntheticFrames("drone_lock", num_frames=2, seed=7)[1].points[:, :4]
    got = read_velodyne(out / "training" / "velodyne" / "000001.bin")
    assert plain.shape != got.shape or not np.allclose(plain, got)  # the profile's frame, not the ray-cast one
    code, _, err = run_cli(["data", "synth", "--scenario", "drone_lock", "drone_bridge", "driving_city", "--frames", "1",
                            "--out", tmp_path / "bad", "--no-progress", "--realism", "avia", "none"])
    assert code == 2 and "--realism takes one profile or one per --scenario (3), got 2: avia none" in err, err
