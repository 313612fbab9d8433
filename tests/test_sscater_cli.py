"""``lidarops stream`` (lidarops/sscater/cli.py), run in-process on short streams."""
import json

import pytest
import torch

from lidarops.cli import main


def test_stream_cli_short_run(tmp_path, capsys):
    png, js = tmp_path / "trace.png", tmp_path / "steps.json"
    rc = main(["stream", "--scenario", "drone_bridge", "--seconds", "0.3", "--small", "--check-every", "5",
               "--device", "cpu", "--out", str(png), "--json", str(js), "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    for text in ("stage", "SSCATeR ms", "full ms", "speed-up", "PFN points saved", "steps under 10 ms",
                 "ReLU zeros", "identity: OK", "block0.down0", "up2", "changed %"):
        assert text in out, f"{text!r} missing from the output:\n{out}"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads(js.read_text())
    assert len(doc["steps"]) == 30 and doc["small"] and doc["device"] == "cpu"
    s = doc["summary"]
    assert s["checks"] == 6 and s["identity_ok"] and s["max_rel_diff"] <= 1e-5  # steps 4, 9, ..., 29
    checked = [r for r in doc["steps"] if r["check"]]
    assert [r["step"] for r in checked] == [4, 9, 14, 19, 24, 29]
    assert all(r["check"]["points"] > 0 and r["check"]["ms_total"] > 0 for r in checked)
    assert [r["step"] for r in doc["steps"] if r["refreshed"]] == [0, 25]  # refresh_every defaults to 25
    assert 0 < s["changed_share"] < 1 and 0 < s["pfn_saved"] < 1
    assert abs(sum(doc["relu_zeros_first"].values()) / len(doc["relu_zeros_first"]) - 0.5) < 0.05
    assert torch.get_num_threads() >= 1  # restored after the run


def test_stream_cli_float64_refresh(tmp_path, capsys):
    """float64 state, refreshes inside the run, sparser ReLU: the identity bound is 1e-12."""
    rc = main(["stream", "--seconds", "0.12", "--small", "--dtype", "float64", "--check-every", "4",
               "--refresh-every", "5", "--relu-zeros", "0.8", "--device", "cpu", "--out",
               str(tmp_path / "x.png"), "--json", str(tmp_path / "x.json"), "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    doc = json.loads((tmp_path / "x.json").read_text())
    assert doc["summary"]["checks"] == 3 and doc["summary"]["max_rel_diff"] <= 1e-12
    assert [r["step"] for r in doc["steps"] if r["refreshed"]] == [0, 5, 10]


def test_stream_cli_bad_arguments(tmp_path, capsys):
    assert main(["stream", "--seconds", "0", "--device", "cpu", "--out", str(tmp_path / "x.png")]) == 2
    assert "--seconds must be a positive number" in capsys.readouterr().err
    assert main(["stream", "--scenario", "drone_lock", "--seconds", "0.02", "--max-points-per-pillar", "5",
                 "--device", "cpu", "--small", "--out", str(tmp_path / "x.png"), "--no-progress"]) == 2
    assert "max_points_per_pillar" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["stream", "--small", "--full-size"])
