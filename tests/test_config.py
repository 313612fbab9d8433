"""lidarops.config: the shipped configs load by name and by their repository path from any directory."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from lidarops.cli import main
from lidarops.config import load_config, packaged_configs, resolve_config

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def elsewhere(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_every_config_of_the_repository_is_shipped():
    in_repo = {p.stem for p in (REPO / "configs").rglob("*.yaml") if p.parent.name != "datasets"}
    assert in_repo and set(packaged_configs()) == in_repo
    assert {"pointpillars_synth", "pointpillars_demo", "pointpillars_kitti"} <= in_repo


@pytest.mark.parametrize("name", ["pointpillars_demo", "pointpillars_demo.yaml",
                                  "configs/pointpillars/pointpillars_demo.yaml", "pointpillars/pointpillars_demo"])
def test_a_shipped_config_loads_by_name_from_any_directory(elsewhere, name):
    assert not Path(name).exists()
    by_name = load_config(name)
    by_path = load_config(REPO / "configs" / "pointpillars" / "pointpillars_demo.yaml")
    assert by_name == by_path and by_name["MODEL"]["NAME"] == "PointPillar"
    assert by_name["DATA_CONFIG"]["POINT_CLOUD_RANGE"]  # the _BASE_CONFIG_ of datasets/ merged in


def test_a_file_of_the_working_directory_wins_over_a_shipped_name(elsewhere):
    (elsewhere / "pointpillars_demo.yaml").write_text("MODEL: {NAME: Mine}\n")
    assert load_config("pointpillars_demo.yaml")["MODEL"]["NAME"] == "Mine"
    assert resolve_config("pointpillars_demo.yaml") == Path("pointpillars_demo.yaml")


def test_an_unknown_name_lists_the_shipped_configs(elsewhere):
    with pytest.raises(FileNotFoundError, match=r"config file not found: nope .*shipped: .*pointpillars_synth"):
        load_config("nope")
    with pytest.raises(FileNotFoundError, match="config file not found"):
        load_config("datasets/kitti_typo.yaml")


def test_train_takes_a_config_by_name(elsewhere, capsys):
    # the config is found; the run then stops at the missing data folder, before any work
    assert main(["train", "--config", "pointpillars_demo", "--data", "no_data", "--out", "run"]) == 2
    err = capsys.readouterr().err
    assert "data folder no_data not found" in err and "config file not found" not in err
    assert not (elsewhere / "run").exists()


def test_a_copy_of_a_shipped_config_finds_its_base_anywhere(elsewhere):
    text = (REPO / "configs" / "pointpillars" / "pointpillars_demo.yaml").read_text()
    assert "    NUM_EPOCHS: " in text
    (elsewhere / "mine.yaml").write_text(re.sub(r"    NUM_EPOCHS: \d+", "    NUM_EPOCHS: 77", text))
    cfg = load_config("mine.yaml")
    assert cfg["OPTIMIZATION"]["NUM_EPOCHS"] == 77
    assert cfg["DATA_CONFIG"]["DATASET"] == load_config("pointpillars_demo")["DATA_CONFIG"]["DATASET"]


def test_set_overrides_keys_as_openpcdet_does():
    from lidarops.config import apply_overrides

    cfg = {"MODEL": {"RATIO": 8, "VARIANT": "full", "HEAD": {"SIZES": [1, 2]}}, "OPTIMIZATION": {"LR": 0.1}}
    out = apply_overrides(cfg, ["MODEL.RATIO", "4", "MODEL.VARIANT", "fast", "MODEL.HEAD.SIZES", "[3, 4, 5]",
                                "OPTIMIZATION.LR", "5e-5"])
    assert out is cfg
    assert cfg == {"MODEL": {"RATIO": 4, "VARIANT": "fast", "HEAD": {"SIZES": [3, 4, 5]}},
                   "OPTIMIZATION": {"LR": 5e-5}}
    apply_overrides(cfg, ["MODEL.HEAD", "null"])
    assert cfg["MODEL"]["HEAD"] is None


@pytest.mark.parametrize("pairs, match", [
    (["MODEL.RATIO"], "KEY VALUE pairs"),
    (["MODEL.RATO", "4"], r"MODEL has no key 'RATO' \(it has RATIO\)"),
    (["MODLE.RATIO", "4"], "the config has no key 'MODLE'"),
    (["MODEL.RATIO.X", "4"], "MODEL.RATIO has no key 'X'"),
    (["MODEL.RATIO", "[1, 2"], "not a YAML value"),
])
def test_set_refuses_what_would_change_nothing(pairs, match):
    from lidarops.config import ConfigError, apply_overrides

    with pytest.raises(ConfigError, match=match):
        apply_overrides({"MODEL": {"RATIO": 8}}, pairs)


def test_train_set_flag_refuses_an_unknown_key(tmp_path, capsys):
    code = main(["train", "--config", str(REPO / "configs/casnet/casnet_pointnet_objects.yaml"), "--out", str(tmp_path / "r"),
                 "--set", "MODEL.RATIOO", "4"])
    err = capsys.readouterr().err
    assert code == 2 and "--set MODEL.RATIOO: MODEL has no key 'RATIOO'" in err and not (tmp_path / "r").exists()


def test_the_real_scan_casnet_trains_on_the_real_scan_detectors_augmentations():
    # casnet_pointpillars_synth_real.yaml repeats the list (a base file would also merge the detector's MODEL keys)
    casnet = load_config(REPO / "configs/casnet/casnet_pointpillars_synth_real.yaml")["DATA_CONFIG"]["DATA_AUGMENTOR"]
    detector = load_config(REPO / "configs/pointpillars/pointpillars_synth_real.yaml")["DATA_CONFIG"]["DATA_AUGMENTOR"]
    assert casnet == detector
