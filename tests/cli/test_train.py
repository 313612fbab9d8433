"""``lidarops train`` (lidarops/cli/train.py) on a tiny synthetic folder, in-process: training, resuming, what
the checkpoint records, and the table that picks what to train from MODEL.NAME."""
from __future__ import annotations

import pytest
import torch

from .helpers import one_error_line, repo_config


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_train_then_resume_then_detect(synth_kitti, tmp_path, run_cli):
    run = tmp_path / "run"
    config = repo_config("pointpillars_demo.yaml")
    args = ["train", "--config", config, "--data", synth_kitti, "--out", run, "--workers", "0", "--no-progress",
            "--epochs", "2", "--batch-size", "2", "--eval-every", "0"]
    code, out, err = run_cli(args + ["--max-steps", "3"])
    assert code == 0 and "stopped (max_steps)" in out and (run / "latest.pth").is_file(), err
    code, out, err = run_cli(args + ["--resume"])
    assert code == 0 and "finished: 4 steps" in out and (run / "final.pth").is_file(), err  # 4 frames, batch 2
    assert "moderate AP (R40): Car_3d " in out  # the evaluation after the last epoch
    ckpt = torch.load(run / "final.pth", weights_only=False)
    # written by the trainer from the model
    assert ckpt["model_class"] == "PointPillars" and ckpt["class_names"] == ["Car"]
    assert ckpt["model_config"]["class_names"] == ckpt["class_names"]
    # written by the command
    assert ckpt["config_path"] == str(config) and ckpt["data_recipe"]["frames"] == 6
    assert ckpt["train_command"].startswith("lidarops ")
    code, out, err = run_cli(["detect", synth_kitti, "--split", "val", "--checkpoint", run / "final.pth", "--out",
                              tmp_path / "det", "--score-thresh", "0.0", "--print-boxes", "3", "--device", "cpu"])
    assert code == 0 and "KITTI result file(s)" in out, err
    files = sorted((tmp_path / "det" / "data").glob("*.txt"))
    assert [f.stem for f in files] == sorted((synth_kitti / "ImageSets" / "val.txt").read_text().split())
    assert (tmp_path / "det" / f"{files[0].stem}.png").is_file() and (tmp_path / "det" / "eval.json").is_file()


def test_model_name_picks_what_to_train():
    from lidarops.cli.train import TRAINABLE
    from lidarops.models import MODELS, model_class
    from lidarops.models.pointpillars import PointPillars

    assert TRAINABLE["PointPillar"] is TRAINABLE["PointPillars"]  # OpenPCDet's name and the class's
    assert all(entry.model in MODELS for entry in TRAINABLE.values())
    assert model_class(TRAINABLE["PointPillar"].model) is PointPillars


def test_unknown_model_name_is_one_line(tmp_path, run_cli):
    unknown = tmp_path / "centerpoint.yaml"
    unknown.write_text(f"_BASE_CONFIG_: {repo_config('pointpillars_demo.yaml')}\nMODEL:\n    NAME: CenterPoint\n")
    unnamed = tmp_path / "unnamed.yaml"
    unnamed.write_text("CLASS_NAMES: ['Car']\nMODEL:\n    VFE:\n        NAME: PillarVFE\n")
    for config, expected in ((unknown, "MODEL.NAME 'CenterPoint' is not a model lidarops trains; "
                                       "known: CASNetPointNet, CASNetPointPillars, CounterNet, PointNet, PointPillar, PointPillars"),
                             (unnamed, "names no model (MODEL.NAME); lidarops trains CASNetPointNet, CASNetPointPillars, CounterNet, PointNet, PointPillar, PointPillars")):
        code, out, err = run_cli(["train", "--config", config, "--out", tmp_path / "run"])
        assert code == 2 and out == "" and expected in one_error_line(err, "train")
    assert not (tmp_path / "run").exists()


def test_train_help(run_cli, capsys):
    with pytest.raises(SystemExit) as e:
        run_cli(["train", "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0 and "--config" in out and "CASNetPointNet, CASNetPointPillars, CounterNet, PointNet, PointPillar, PointPillars" in " ".join(out.split())


def test_gt_database_frames_builds_from_those_frames_only(synth_kitti, monkeypatch):
    """--gt-database-frames N: the gt database is built once, from the first N training frames (before, looking
    up the ids made a training dataset, which built the database from every frame first)."""
    import argparse

    import lidarops.data.augment as augment
    import lidarops.data.detection as detection
    from lidarops.cli.train import _kitti_detection_datasets
    from lidarops.config import load_config

    built = []
    real = augment.build_gt_database

    def recording(source, ids=None, *a, **kw):
        built.append(None if ids is None else list(ids))
        return real(source, ids, *a, **kw)

    monkeypatch.setattr(detection, "build_gt_database", recording)
    cfg = load_config(repo_config("pointpillars_synth.yaml"))
    args = argparse.Namespace(gt_database_frames=2, seed=0, max_train_frames=None, max_val_frames=None)
    train_set, _, _ = _kitti_detection_datasets(synth_kitti, ["Car", "Pedestrian", "Cyclist"], cfg, args)
    first_two = (synth_kitti / "ImageSets" / "train.txt").read_text().split()[:2]
    assert built == [first_two] and train_set.sampler is not None


@pytest.mark.slow  # a drone folder and two steps on the 504 x 504 grid: about 15 s
def test_aerial_pointpillars_config_trains_on_drone_scenes(tmp_path, run_cli):
    """configs/pointpillars/aerial_pointpillars_drone.yaml (issue 39) on a tiny drone_bridge + drone_lock folder: two
    training steps, a finite loss, and every drone given positive anchors by the stacked, 3D-matched layers."""
    from lidarops.config import load_config
    from lidarops.models.config import PointPillarsConfig
    from lidarops.models.pointpillars import PointPillars

    data = tmp_path / "aerial"
    code, _, err = run_cli(["data", "synth", "--scenario", "drone_bridge", "drone_lock", "--frames", "4", "--out", data,
                            "--no-progress", "--seed", "5", "--workers", "1"])
    assert code == 0, err
    config = repo_config("aerial_pointpillars_drone.yaml")
    code, out, err = run_cli(["train", "--config", config, "--data", data, "--out", tmp_path / "run", "--workers", "0",
                              "--no-progress", "--epochs", "1", "--batch-size", "1", "--eval-every", "0",
                              "--max-steps", "2"])
    assert code == 0 and "stopped (max_steps)" in out, err
    model = PointPillars(PointPillarsConfig.from_openpcdet(load_config(config)))
    head = model.dense_head
    anchors = [getattr(head, f"anchors_{i}") for i in range(head._num_anchor_sets)]
    # drones at a layer's centre, across a layer boundary, high up and low down; headings and sizes as simulated
    gt = torch.tensor([[[20.0, 0.0, 0.0, 0.7, 0.7, 0.3, 0.3, 1], [35.0, 5.0, 0.5, 0.6, 0.7, 0.25, -1.0, 1],
                        [50.0, -12.0, 4.8, 0.72, 0.66, 0.32, 2.0, 1], [12.0, 3.3, -5.2, 0.7, 0.7, 0.3, 0.0, 1]]])
    labels = head.target_assigner.assign_targets(anchors, gt)["box_cls_labels"][0]
    from lidarops.models.anchors import flatten_anchors

    flat, _ = flatten_anchors(anchors)
    pos = flat[labels > 0]
    assert len(pos) >= 4
    for box in gt[0]:
        near = pos[((pos[:, :2] - box[:2]).norm(dim=1) < 0.5)]
        assert len(near), box  # every drone has a positive anchor over it
        assert ((near[:, 2] - box[2]).abs() <= 0.5 + box[5] / 2 + 1e-6).all()  # in the layers it overlaps


def test_pretrained_model_starts_the_run_from_its_weights(synth_kitti, tmp_path, run_cli, monkeypatch):
    """``--pretrained-model`` (a shipped name or a file) hands fit a model holding exactly those weights, recorded in
    the checkpoint's extras; without it the run starts elsewhere; weights of another config, another class order, or
    no file are one error line naming the flag, before any training."""
    import lidarops.train
    from lidarops.models import weights

    seen = {}

    def fake_fit(model, *args, **kwargs):
        seen["state"] = {k: v.clone() for k, v in model.state_dict().items()}
        seen["extra"] = kwargs["extra_checkpoint"]
        raise SystemExit(0)  # stop before training: the start is what is tested

    monkeypatch.setattr(lidarops.train, "fit", fake_fit)
    shipped = weights.load("pointpillars_synth").state_dict()
    args = ["train", "--config", "pointpillars_synth", "--data", synth_kitti, "--out", tmp_path / "run", "--workers",
            "0", "--no-progress"]
    for source in ("pointpillars_synth", weights.path("pointpillars_synth")):
        with pytest.raises(SystemExit):
            run_cli(args + ["--pretrained-model", source])
        assert seen["state"].keys() == shipped.keys()
        assert all(torch.equal(seen["state"][k], shipped[k]) for k in shipped)
        assert seen["extra"]["pretrained_model"] == str(source)
    with pytest.raises(SystemExit):
        run_cli(args)
    assert not all(torch.equal(seen["state"][k], shipped[k]) for k in shipped)  # the check above can fail
    assert seen["extra"]["pretrained_model"] is None
    seen.clear()
    reordered = tmp_path / "reordered.yaml"
    base = repo_config("pointpillars_synth.yaml")
    import yaml

    from lidarops.config import load_config

    cfg = load_config(base)  # the same network for classes in another order: its weights would load
    anchors = {a["class_name"]: a for a in cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]}
    cfg["CLASS_NAMES"] = ["Pedestrian", "Car", "Cyclist"]
    cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"] = [anchors[c] for c in cfg["CLASS_NAMES"]]
    reordered.write_text(yaml.safe_dump(cfg))
    narrower = tmp_path / "narrower.yaml"
    narrower.write_text(f"_BASE_CONFIG_: {base}\nMODEL:\n    VFE:\n        NUM_FILTERS: [32]\n")
    for config, source, expected in (("pointpillars_demo", "pointpillars_synth", "the config's model ['Car']"),
                                     (narrower, "pointpillars_synth", "vfe.pfn_layers.0.linear.weight"),
                                     (reordered, "pointpillars_synth",
                                      "detects ['Car', 'Pedestrian', 'Cyclist']; the config's model ['Pedestrian',"),
                                     ("pointpillars_synth", tmp_path / "none.pth", "no such file")):
        code, out, err = run_cli(["train", "--config", config, "--data", synth_kitti, "--out", tmp_path / "bad",
                                  "--pretrained-model", source])
        line = one_error_line(err, "train")
        assert code == 2 and "--pretrained-model" in line and expected in line, line
    assert not seen and not (tmp_path / "bad").exists()
