"""tools/casnet/ship_detection.py: a trained detection CAS-Net written as a shipped file, with the rows of its own
run picked out of the evaluation tables."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


def _tool():
    spec = importlib.util.spec_from_file_location("ship_detection", ROOT / "tools/casnet/ship_detection.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(method, ratio, map3d, checkpoint=None):
    return {"method": method, "ratio": ratio, "checkpoint": checkpoint, "mAP_3d_moderate_R40": map3d,
            "mAP_3d_moderate_R11": map3d + 1, "mAP_bev_moderate_R40": map3d + 2,
            "3d_moderate_R40": {"Car": map3d}, "points_kept_mean": 100.0, "distinct_kept_mean": 99.0,
            "sample_ms_median": 1.5, "frames": 3}


def _table(path, frames, data, rows):
    path.write_text(json.dumps({"frames": frames, "data": data, "detector": "pointpillars_synth_real",
                                "device": "cpu", "command": "detection_table.py ...", "rows": rows}))
    return path


@pytest.fixture
def run(tmp_path):
    from lidarops.models.casnet import CASNet

    torch.manual_seed(0)
    model = CASNet(num_out=64, k=4, head="anchored").eval()
    src = model.save(tmp_path / "casnet_det_a.pth", task="pointpillars_synth_real",
                     model_config_of_run={"ratio": 8, "segment_points": 512}, train_command="lidarops train ...", it=7)
    # two CAS-Nets in the tables: only the row of the file named like the run's may be taken
    rows = [_row("all points", 1, 70.0), _row("random", 2, 60.0), _row("random", 8, 35.0), _row("fps", 8, 55.0),
            _row("casnet (casnet_det_b)", 8, 40.0, "/x/casnet_det_b.pth"),
            _row("casnet (casnet_det_a)", 8, 56.0, "/x/casnet_det_a.pth")]
    real = [_row("all points", 1, 12.8), _row("random", 8, 4.6), _row("fps", 8, 1.1),
            _row("casnet", 8, 1.4, "/y/casnet_det_a.pth")]
    return (src, _table(tmp_path / "sim.json", 100, "/tmp/val", rows),
            _table(tmp_path / "real.json", 14, ".peers/kitti_real", real), model)


def _ship(tool, src, table, dst, *extra):
    return tool.main([str(src), str(dst), "--table", str(table), "--train-data", "lidarops data synth ... --realism kitti",
                      "--session", "REALISM=kitti ... detect", "--commit", "abc1234", *extra])


def test_ship_detection_writes_the_sampler_with_its_own_rows(run, tmp_path):
    from lidarops.models.casnet import load_casnet

    src, sim, real, model = run
    dst = tmp_path / "weights" / "casnet_test_d8.pth"
    assert _ship(_tool(), src, sim, dst, "--real-table", str(real)) == 0
    shipped = load_casnet(dst)
    assert shipped.dedup and not model.dedup  # the shipped sampler keeps distinct points
    for a, b in zip(shipped.state_dict().values(), model.state_dict().values()):
        assert torch.equal(a, b)
    ck = torch.load(dst, map_location="cpu", weights_only=False)
    assert ck["task"] == "pointpillars_synth_real" and ck["ratio"] == 8 and ck["it"] == 7
    assert ck["model_config_of_run"]["segment_points"] == 512
    ev = ck["evaluation"]
    assert ev["casnet_whole_cloud"]["mAP_3d_moderate_R40"] == 56.0  # its own row, not casnet_det_b's
    assert (ev["fps"]["mAP_3d_moderate_R40"], ev["random"]["mAP_3d_moderate_R40"]) == (55.0, 35.0)  # D = 8, not 2
    assert ev["all_points"]["mAP_3d_moderate_R40"] == 70.0
    assert ev["real_frames"]["casnet_whole_cloud"]["mAP_3d_moderate_R40"] == 1.4
    assert "14 real KITTI frames" in ev["real_frames"]["protocol"]
    assert ck["data_recipe"]["commit"] == "abc1234" and "--realism kitti" in ck["data_recipe"]["train_data"]
    assert ck["usage"] == "CASNetSampler(load_casnet('casnet_test_d8'), whole=True)(points, n // 8)"


def test_ship_detection_refuses_a_table_without_the_run(run, tmp_path):
    src, sim, _, _ = run
    with pytest.raises(SystemExit, match="no row of a CAS-Net file named casnet_det_c"):
        _ship(_tool(), src, sim, tmp_path / "out.pth", "--stem", "casnet_det_c")
    assert not (tmp_path / "out.pth").exists()


def test_ship_detection_refuses_a_run_without_its_ratio(run, tmp_path):
    from lidarops.models.casnet import CASNet

    _, sim, _, _ = run
    bare = CASNet(num_out=64, k=4, head="anchored").save(tmp_path / "casnet_det_a.pth", task="pointpillars_synth")
    with pytest.raises(SystemExit, match="records no sampling ratio"):
        _ship(_tool(), bare, sim, tmp_path / "out.pth")


# ------------------------------------------------------------------------ tools/casnet/ship_classification.py
def _classification_tool():
    spec = importlib.util.spec_from_file_location("ship_classification", ROOT / "tools/casnet/ship_classification.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def classification_run(tmp_path):
    """A trained-looking CAS-Net (its own file) and PointNet (another), a table of the runs and a config whose
    object set has a known key: what device_session.sh classify brings back."""
    import yaml

    from lidarops.config import load_config
    from lidarops.data.object_sets import ObjectSetRecipe
    from lidarops.models.casnet_pointnet import CASNetPointNet

    torch.manual_seed(0)
    model = CASNetPointNet({"num_points": 64, "ratio": 8, "variant": "fast", "head": "anchored",
                            "task": {"mlp": [16, 32], "fc": [16]}}).eval()
    for p in model.parameters():  # no two files of the test hold the same numbers by chance
        p.data.normal_()
    cas = model.casnet.save(tmp_path / "cas_d8_fast.pth", task="pointnet_objects",
                            model_config_of_run=model.config.to_dict(), train_command="lidarops train ... RATIO 8", it=9)
    pointnet = model.task.save(tmp_path / "pointnet_objects.pth", train_command="lidarops train --config pointnet")
    cfg = load_config(ROOT / "configs/casnet/pointnet_objects.yaml")
    cfg["DATA_CONFIG"]["OBJECT_SET"]["SCENES"] = {"driving_highway": 2, "drone_lock": 3}
    config = tmp_path / "objects.yaml"
    config.write_text(yaml.safe_dump(cfg))
    key = ObjectSetRecipe.from_openpcdet(cfg["DATA_CONFIG"]["OBJECT_SET"]).key()
    rows = [{"method": m, "ratio": d, "checkpoint": None, "accuracy": a, "mean_class_accuracy": a - 5}
            for m, d, a in (("random", 8, 90.0), ("fps", 8, 91.0), ("casnet-fast-anchored", 8, 92.0),
                            ("fps", 16, 80.0))]
    table = tmp_path / "table.json"
    table.write_text(json.dumps({"device": "NVIDIA H200", "objects": 12, "num_points": 64, "rows": rows,
                                 "full_density": {"accuracy": 93.0, "mean_class_accuracy": 88.0}}))
    return model, cas, pointnet, config, key, table


def test_ship_classification_holds_the_sampler_its_pointnet_and_its_rows(classification_run, tmp_path):
    from lidarops.checkpoint import read_checkpoint
    from lidarops.models import load_model

    model, cas, pointnet, config, key, table = classification_run
    out = tmp_path / "casnet_pointnet_d8.pth"
    assert _classification_tool().main([str(cas), str(pointnet), str(out), "--table", str(table), "--config",
                                        str(config), "--data", str(tmp_path / "objects"), "--key", key,
                                        "--commit", "abc1234"]) == 0
    shipped = load_model(out).eval()
    assert type(shipped).__name__ == "CASNetPointNet"
    for name, value in model.state_dict().items():  # both parts, from their own files
        assert torch.equal(shipped.state_dict()[name], value), name
    objects = torch.randn(3, 64, 3)
    assert torch.equal(shipped({"points": objects}), model({"points": objects}))
    record = read_checkpoint(out)
    assert record["train_command"] == "lidarops train ... RATIO 8" and record["it"] == 9
    assert record["task_train_command"] == "lidarops train --config pointnet"
    assert record["data_recipe"]["key"] == key and record["data_recipe"]["num_points"] == 1024
    assert record["data_recipe"]["realism"]["drone_lock"] == "avia" and "driving_city" not in record["data_recipe"]["realism"]
    rows = record["evaluation"]["rows_d8"]
    assert [r["method"] for r in rows] == ["random", "fps", "casnet-fast-anchored"]  # D = 16 left out
    assert record["evaluation"]["commit"] == "abc1234" and "8 kept" in record["evaluation"]["protocol"]


def test_ship_classification_refuses_another_object_set(classification_run, tmp_path):
    _, cas, pointnet, config, key, table = classification_run
    with pytest.raises(SystemExit, match=f"names the object set {key}, the runs used 000000000000"):
        _classification_tool().main([str(cas), str(pointnet), str(tmp_path / "x.pth"), "--table", str(table),
                                     "--config", str(config), "--data", str(tmp_path / "objects"),
                                     "--key", "000000000000", "--commit", "abc1234"])
    assert not (tmp_path / "x.pth").exists()
