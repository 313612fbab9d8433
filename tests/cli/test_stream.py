"""``lidarops stream`` (lidarops/cli/stream.py), run in-process on short streams (the SSCATeR calibration it shares
with the benchmarks: tests/models/test_sscater_calibration.py)."""
import json
import math

import pytest
import torch

from lidarops.cli import main
from lidarops.cli import stream as stream_cli
from helpers.devices import requires_cuda


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
def test_stream_cli_short_run(tmp_path, capsys):
    png, js = tmp_path / "trace.png", tmp_path / "steps.json"
    rc = main(["stream", "--scenario", "drone_bridge", "--seconds", "0.3", "--small", "--check-every", "5",
               "--device", "cpu", "--out", str(png), "--json", str(js), "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    # what the run demonstrates, before and after the numbers
    for text in ("SSCATeR on 0.3 s of simulated LiDAR (drone_bridge)", "O += (I_curr - I_prev) * W", "Scene: a Livox",
                 "stage", "SSCATeR ms", "full ms", "speed-up", "PFN points saved", "steps under 10 ms",
                 "compute over all 30 steps", "ReLU zeros", "changed %", "block 1 conv 1 (3x3, stride 2)",
                 "block 3 conv 6 (3x3)", "upsampling of block 3 (x4)", "What this run shows:", "- identity OK",
                 "- saving:", "- weights: random", "- real time:"):
        assert text in out, f"{text!r} missing from the output:\n{out}"
    assert out.index("Scene:") < out.index("stage") < out.index("What this run shows:")
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
    assert s["sscater_s_all"] > 0 and s["full_s_all_estimate"] > 0 and 0 <= s["full_under_budget"] <= 1
    # the JSON keeps DeltaBackbone's names; the printout and the picture use the readable labels
    assert [L["name"] for L in s["layers"]][:2] == ["block0.down0", "block0.subm1"] and s["layers"][-1]["name"] == "up2"
    assert all(L["label"] in out for L in s["layers"])
    assert abs(sum(doc["relu_zeros_first"].values()) / len(doc["relu_zeros_first"]) - 0.5) < 0.05
    assert torch.get_num_threads() >= 1  # restored after the run


@pytest.mark.slow  # end to end, seconds: `make test` runs it, `make test-fast` does not
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


def test_stream_cli_shorter_than_the_window(tmp_path, capsys):
    """BatchNorm is calibrated on the first full window, which outlasts a 50 ms run: the stream's capacity
    must hold it (it overflowed before), and the picture shows the last step with changes."""
    out_png = tmp_path / "short"  # no suffix: written as PNG under exactly this name
    rc = main(["stream", "--scenario", "drone_lock", "--seconds", "0.05", "--small", "--device", "cpu",
               "--out", str(out_png), "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "identity OK" in out and out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---- errors: one line on stderr, exit code 2, before anything runs ------------------------------------

def _error(capsys, argv) -> str:
    rc = main(["stream", "--no-progress", *argv])
    cap = capsys.readouterr()
    assert rc == 2, cap.out + cap.err
    assert cap.out == "", f"the run started before the error:\n{cap.out}"
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lidarops stream: error: "), cap.err
    return lines[0]


@pytest.mark.parametrize("argv, message", [
    (["--seconds", "0"], "--seconds must be a positive number of seconds, got 0.0"),
    (["--seconds", "-2"], "--seconds must be a positive number"),
    (["--seconds", "nan"], "--seconds must be a positive number"),
    (["--seconds", "inf"], "--seconds must be a positive number"),
    (["--slice", "0"], "--slice must be a positive number"),
    (["--window", "-0.1"], "--window must be a positive number"),
    (["--relu-zeros", "1"], "--relu-zeros must be a share in [0, 1)"),
    (["--relu-zeros", "-0.1"], "--relu-zeros must be a share in [0, 1)"),
    (["--relu-zeros", "nan"], "--relu-zeros must be a share in [0, 1)"),
    (["--check-every", "-1"], "--check-every must be an integer >= 0, got -1"),
    (["--refresh-every", "-1"], "--refresh-every must be an integer >= 0, got -1"),
    (["--threads", "0"], "--threads must be an integer >= 1, got 0"),
    (["--max-points-per-pillar", "0"], "--max-points-per-pillar must be an integer >= 1, got 0"),
    (["--max-pillars", "-5"], "--max-pillars must be an integer >= 1, got -5"),
    (["--seed", str(2 ** 70)], "--seed must be an integer that fits in 64 bits"),
])
def test_stream_cli_bad_numbers(tmp_path, capsys, argv, message):
    png = tmp_path / "x.png"
    seconds = [] if "--seconds" in argv else ["--seconds", "0.02"]
    assert message in _error(capsys, ["--device", "cpu", "--out", str(png), *seconds, *argv])
    assert not png.exists()


def test_stream_cli_unwritable_paths(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    base = ["--device", "cpu", "--seconds", "0.02"]
    assert "cannot be written" in _error(capsys, [*base, "--out", str(a_file / "x.png")])  # parent is a file
    assert "is a directory" in _error(capsys, [*base, "--out", str(tmp_path)])
    assert "matplotlib cannot write .txt files" in _error(capsys, [*base, "--out", str(tmp_path / "x.txt")])
    png = str(tmp_path / "x.png")
    assert "cannot be written" in _error(capsys, [*base, "--out", png, "--json", str(a_file / "x.json")])
    assert "is a directory" in _error(capsys, [*base, "--out", png, "--json", str(tmp_path)])
    assert "--out and --json are the same file" in _error(capsys, [*base, "--out", png, "--json", png])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # the checks leave nothing behind


def test_stream_cli_cuda_without_cuda_torch(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.version, "cuda", None)
    line = _error(capsys, ["--device", "cuda", "--seconds", "0.02"])
    assert f"--device cuda: this torch ({torch.__version__}) is built without CUDA; use --device cpu" in line
    monkeypatch.setattr(torch.version, "cuda", "13.0")  # a CUDA build on a machine without a GPU
    assert "sees no CUDA device; use --device cpu" in _error(capsys, ["--device", "cuda", "--seconds", "0.02"])


def test_stream_cli_cuda_without_lidarops_kernels(monkeypatch, capsys):
    from lidarops import extension
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(extension, "cuda_available", lambda: False)
    line = _error(capsys, ["--device", "cuda", "--seconds", "0.02"])
    assert "--device cuda: lidarops was built without its CUDA kernels" in line and "use --device cpu" in line


def test_stream_cli_extension_not_loadable(monkeypatch, capsys):
    """E.g. while the extension is being rebuilt: LidaropsBuildError, raised while the default device is
    picked, is one line too."""
    from lidarops import extension
    from lidarops.extension import LidaropsBuildError

    def broken():
        raise LidaropsBuildError("lidarops' compiled ops are not built.\nBuild them with `make build`")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(extension, "cuda_available", broken)
    assert "compiled ops are not built. Build them with `make build`" in _error(capsys, ["--seconds", "0.02"])


def test_stream_cli_capacity_too_small(tmp_path, capsys):
    rc = main(["stream", "--scenario", "drone_lock", "--seconds", "0.02", "--max-points-per-pillar", "5",
               "--device", "cpu", "--small", "--out", str(tmp_path / "x.png"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "max_points_per_pillar" in lines[0]
    assert lines[0].endswith("(--max-points-per-pillar / --max-pillars)")


def test_stream_cli_write_failure_and_interrupt(monkeypatch, capsys):
    def fail(*a, **k):
        raise PermissionError(13, "Permission denied", "x.png")

    monkeypatch.setattr(stream_cli, "run", fail)
    assert "Permission denied" in _error(capsys, ["--seconds", "0.02"])

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(stream_cli, "run", interrupt)
    assert main(["stream", "--seconds", "0.02"]) == 130
    assert capsys.readouterr().err.strip() == "lidarops stream: interrupted"


@pytest.mark.parametrize("argv", [["--scenario", "mars"], ["--small", "--full-size"], ["--dtype", "float16"],
                                  ["--device", "tpu"], ["--seconds", "two"], ["--check-every", "1.5"]])
def test_stream_cli_argparse_errors(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main(["stream", *argv])
    assert e.value.code == 2
    assert "lidarops stream: error: argument" in capsys.readouterr().err


def test_stream_run_api_errors(tmp_path):
    """The Python entry point raises ValueError naming the flag, before anything runs."""
    with pytest.raises(ValueError, match="--scenario must be one of"):
        stream_cli.run("mars", out=str(tmp_path / "x.png"))
    with pytest.raises(ValueError, match="--device must be cpu or cuda"):
        stream_cli.run(device="mps", out=str(tmp_path / "x.png"))
    with pytest.raises(ValueError, match="--seconds must be a positive number"):
        stream_cli.run(seconds=math.nan, device="cpu", out=str(tmp_path / "x.png"))


def _summary(backbone_ms, full_backbone_ms, max_rel_diff=3e-6, checks=10, stream_ms=3.0):
    return {"sscater_ms_backbone": backbone_ms, "full_ms_backbone": full_backbone_ms,
            "sscater_ms_total": backbone_ms + 5, "full_ms_total": full_backbone_ms + 5,
            "sscater_ms_pfn": 2.0, "full_ms_pfn": 6.0,
            "sscater_ms_stream": stream_ms, "full_ms_stream": 2.0, "changed_share": 0.3, "checks": checks,
            "max_rel_diff": max_rel_diff, "identity_ok": max_rel_diff <= 1e-5, "under_budget": 0.0,
            "full_under_budget": 0.0, "sscater_s_all": 5.0, "full_s_all_estimate": 6.0,
            "layers": [{"name": "block0.down0", "changed_share": 0.4}, {"name": "up2", "changed_share": 0.98}]}


def test_stream_takeaway_words():
    """The closing lines follow the figures: where recycling pays, where it does not and why, a failure."""
    cpu = torch.device("cpu")
    pays = stream_cli._takeaway(_summary(10.0, 40.0), 1e-5, 0.5, cpu)
    assert "- identity OK" in pays and "backbone 4.0x" in pays and "most of the work was recycled" in pays
    assert "(compare --relu-zeros 0.9)" in pays and "docs/sscater.md gives GPU figures" in pays
    little = stream_cli._takeaway(_summary(35.0, 36.0), 1e-5, 0.5, cpu)
    assert "little in the backbone" in little and "up to 98% of a layer's sites" in little
    assert "redid nearly a full pass" in little and "cost more than a one-off pillarize (0.7x)" in little
    failed = stream_cli._takeaway(_summary(10.0, 40.0, max_rel_diff=3e-4), 1e-5, 0.9, cpu)
    assert "- identity FAILED" in failed and "3.0e-04" in failed and "compare --relu-zeros" not in failed
    unchecked = stream_cli._takeaway(_summary(10.0, float("nan"), checks=0), 1e-5, 0.5, cpu)
    assert "identity: not checked" in unchecked and "saving: not measured" in unchecked


def test_stream_checkpoint_defaults_to_the_scene_it_was_trained_on(tmp_path):
    """--checkpoint without --scenario streams the first scene of the detector's data recipe (the Aerial-PointPillars:
    drone_bridge), driving_city for a checkpoint whose recipe names none the stream can run."""
    from lidarops.checkpoint import read_checkpoint, save_checkpoint
    from lidarops.cli.stream import _trained_scenario
    from lidarops.models import weights

    assert _trained_scenario(weights.path("aerial_pointpillars")) == "drone_bridge"
    assert _trained_scenario(weights.path("pointpillars_synth")) == "driving_city"
    record = read_checkpoint(weights.path("pointpillars_synth"))
    for recipe in ({"scenarios": [{"scenario": "nope"}, {"scenario": "drone_lock"}]}, None, {"root": "/data/kitti"}):
        save_checkpoint({**record, "data_recipe": recipe}, tmp_path / "c.pth")
        assert _trained_scenario(tmp_path / "c.pth") == ("drone_lock" if recipe and "scenarios" in recipe
                                                          else "driving_city")
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    assert _trained_scenario(tmp_path / "bad.pth") == "driving_city"


class _Recorded(Exception):
    pass


def _record_simulator(monkeypatch):
    """Replaces the simulator the stream builds by one that records its arguments and stops the run."""
    import lidarops.data.synthetic as synthetic

    seen = []

    def simulator(scenario, seed=0, realism=None, **kwargs):
        seen.append({"scenario": scenario, "seed": seed, "realism": realism})
        raise _Recorded

    monkeypatch.setattr(synthetic, "Simulator", simulator)
    return seen


def test_trained_realism_reads_the_recipe_per_scenario(tmp_path):
    """The profile of a scenario's first frames in a checkpoint's data recipe: per entry (data synth --realism per
    scenario), else the recipe's one profile, else none."""
    from lidarops.checkpoint import read_checkpoint, save_checkpoint
    from lidarops.models import weights

    record = read_checkpoint(weights.path("aerial_pointpillars"))
    cases = [({"scenarios": [{"scenario": "drone_bridge", "realism": None},
                             {"scenario": "drone_bridge", "realism": "avia"}], "realism": ["none", "avia"]},
              "drone_bridge", None),
             ({"scenarios": [{"scenario": "drone_lock", "realism": None}, {"scenario": "drone_bridge", "realism": "avia"}]},
              "drone_bridge", "avia"),
             ({"scenarios": [{"scenario": "driving_city"}], "realism": "kitti"}, "driving_city", "kitti"),
             ({"scenarios": [{"scenario": "driving_city"}], "realism": "kitti"}, "drone_lock", None),
             ({"root": "/data/kitti"}, "driving_city", None), (None, "driving_city", None)]
    for recipe, scenario, want in cases:
        save_checkpoint({**record, "data_recipe": recipe}, tmp_path / "c.pth")
        assert weights.trained_realism(tmp_path / "c.pth", scenario) == want, (recipe, scenario)
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    assert weights.trained_realism(tmp_path / "bad.pth", "drone_lock") is None


def test_stream_realism_reaches_the_simulator(tmp_path, monkeypatch, capsys):
    """--realism builds the scene with the profile; with --checkpoint it defaults to the profile the detector's
    recipe made that scenario with, and `none` streams ray-cast frames."""
    from lidarops.checkpoint import read_checkpoint, save_checkpoint
    from lidarops.models import weights

    seen = _record_simulator(monkeypatch)
    with pytest.raises(_Recorded):
        stream_cli.run("drone_lock", seconds=0.05, device="cpu", out=str(tmp_path / "x.png"), realism="avia")
    with pytest.raises(_Recorded):
        stream_cli.run("drone_lock", seconds=0.05, device="cpu", out=str(tmp_path / "x.png"), realism="none")
    record = read_checkpoint(weights.path("aerial_pointpillars"))
    save_checkpoint({**record, "data_recipe": {"scenarios": [{"scenario": "drone_bridge", "realism": "avia"}]}},
                    tmp_path / "c.pth")
    for realism in (None, "none", "avia:rotor_keep=0.5"):
        with pytest.raises(_Recorded):
            stream_cli.run_detector(str(tmp_path / "c.pth"), device="cpu", realism=realism)
    assert [s["realism"] for s in seen] == ["avia", None, "avia", None, "avia:rotor_keep=0.5"]
    assert [s["scenario"] for s in seen] == ["drone_lock", "drone_lock"] + ["drone_bridge"] * 3
    for bad in ("avai", "avia:nope=1"):
        with pytest.raises(ValueError, match="--realism"):
            stream_cli.run("drone_lock", seconds=0.05, device="cpu", out=str(tmp_path / "x.png"), realism=bad)
        with pytest.raises(SystemExit) as e:
            main(["stream", "--realism", bad])
        assert e.value.code == 2 and "argument --realism" in capsys.readouterr().err
    assert len(seen) == 5  # refused before any scene was built


@requires_cuda
def test_stream_checkpoint_on_cuda_runs_without_tf32(monkeypatch):
    """On CUDA, `stream --checkpoint` steps, detects and checks in float32 without TF32 whatever torch's flags
    (cuDNN's TF32 is on by default): the recycled layers sum in float32, so the pillar net, the head and the detector
    it is checked against must too, or a box near the threshold comes out on one side only."""
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", True)
    seen = []

    def flags(fn):
        def wrapped(*args, **kwargs):
            seen.append((fn.__name__, torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32))
            return fn(*args, **kwargs)
        return wrapped

    from lidarops.models.pointpillars import PointPillars

    for cls, name in ((SSCATeRPointPillars, "step"), (SSCATeRPointPillars, "detect"), (PointPillars, "predict")):
        monkeypatch.setattr(cls, name, flags(getattr(cls, name)))
    assert stream_cli.run_detector("aerial_pointpillars", seconds=0.1, device="cuda", check_every=5) == 0
    assert {name for name, *_ in seen} == {"step", "detect", "predict"}
    assert all(not cudnn and not matmul for _, cudnn, matmul in seen), seen
    assert torch.backends.cudnn.allow_tf32 and torch.backends.cuda.matmul.allow_tf32  # the user's flags, restored
