"""``lidarops sample`` (lidarops/cli/sample.py), run in-process on small clouds."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from lidarops.cli.sample import sample_count
from lidarops.data.formats.kitti import read_velodyne, write_velodyne
from .helpers import one_error_line

needs_matplotlib = pytest.mark.skipif(importlib.util.find_spec("matplotlib") is None,
                                      reason="needs matplotlib (the before/after picture)")


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, (n, 4)).astype(np.float32)
    pts[:, 2] = rng.uniform(-2, 1, n)
    pts[:, 3] = rng.uniform(0, 1, n)
    return pts


def _rows(a: np.ndarray) -> set:
    return {tuple(r) for r in a.tolist()}


@pytest.fixture
def scan(tmp_path):
    path = tmp_path / "in" / "000007.bin"
    write_velodyne(path, _cloud(403))
    return path


@pytest.fixture
def folder(tmp_path):
    root = tmp_path / "kitti"
    for i, n in enumerate((300, 250, 5)):  # the last has fewer points than the ratio
        write_velodyne(root / "training" / "velodyne" / f"{i:06d}.bin", _cloud(n, seed=i))
    return root


def _is_png(path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sample_count_rule():
    assert sample_count(403, 8) == 50
    assert sample_count(8, 8) == 1
    assert sample_count(5, 8) == 1  # ceil(n / ratio): one point
    assert sample_count(0, 8) == 0
    assert sample_count(7, 1) == 7


@pytest.mark.parametrize("method", ["random", "fps", "chunked-fps"])
def test_file_rows_of_input_count_and_format(run_cli, scan, tmp_path, method):
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", method, "--ratio", 8, "--out", out, "--device", "cpu",
                                 "--no-picture"])
    assert code == 0, err
    target = out / f"000007_{method}_d8.bin"
    kept = read_velodyne(target)  # KITTI format: float32 N x 4
    src = read_velodyne(scan)
    assert kept.shape == (403 // 8, 4)
    assert _rows(kept) <= _rows(src) and len(_rows(kept)) == kept.shape[0]  # distinct rows of the input
    assert not (out / f"000007_{method}_d8.png").exists()
    lines = stdout.splitlines()
    assert len(lines) == 1 and "403 -> 50 points" in lines[0] and " ms" in lines[0]


def test_fps_is_lidarops_fps(run_cli, scan, tmp_path):
    from lidarops import fps

    out = tmp_path / "out"
    assert run_cli(["sample", scan, "--method", "fps", "--ratio", 4, "--out", out, "--device", "cpu",
                    "--no-picture"])[0] == 0
    src = read_velodyne(scan)
    idx = fps(torch.from_numpy(src[:, :3]).unsqueeze(0), 403 // 4)[0].numpy()
    np.testing.assert_array_equal(read_velodyne(out / "000007_fps_d4.bin"), src[idx])  # the same rows, same order


def test_random_reproducible_with_seed(run_cli, scan, tmp_path):
    def kept(seed, name):
        out = tmp_path / name
        assert run_cli(["sample", scan, "--ratio", 5, "--seed", seed, "--out", out, "--device", "cpu",
                        "--no-picture"])[0] == 0
        return read_velodyne(out / "000007_random_d5.bin")

    a, b, c = kept(3, "a"), kept(3, "b"), kept(4, "c")
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@needs_matplotlib
def test_folder_one_file_per_scan_and_pictures(run_cli, folder, tmp_path):
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", folder, "--method", "chunked-fps", "--ratio", 8, "--out", out,
                                 "--device", "cpu"])
    assert code == 0, err
    names = sorted(p.name for p in (out / "velodyne").iterdir())
    assert names == ["000000.bin", "000001.bin", "000002.bin"]
    for i, n in enumerate((300, 250, 5)):
        src = read_velodyne(folder / "training" / "velodyne" / f"{i:06d}.bin")
        kept = read_velodyne(out / "velodyne" / f"{i:06d}.bin")
        assert kept.shape == (sample_count(n, 8), 4)
        assert _rows(kept) <= _rows(src)
        assert _is_png(out / "pictures" / f"{i:06d}_chunked-fps_d8.png")
    lines = stdout.splitlines()
    assert len(lines) == 4 and "one kept" in lines[2] and lines[3].startswith("wrote 3 sampled scans")


def test_folder_frames(run_cli, folder, tmp_path):
    out = tmp_path / "out"
    assert run_cli(["sample", folder, "--frames", 2, "--out", out, "--device", "cpu", "--no-picture"])[0] == 0
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == ["000000.bin", "000001.bin"]


@needs_matplotlib
def test_file_picture(run_cli, scan, tmp_path):
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", "fps", "--out", out, "--device", "cpu"])
    assert code == 0, err
    assert _is_png(out / "000007_fps_d8.png") and str(out / "000007_fps_d8.png") in stdout


def test_casnet_checkpoint(run_cli, scan, tmp_path):
    from lidarops.models.casnet import CASNet

    torch.manual_seed(0)
    config = {"num_out": 16, "k": 4, "num_oa_layers": 1}
    ckpt = tmp_path / "casnet.pth"
    torch.save({"model_config": config, "state_dict": CASNet(**config).state_dict()}, ckpt)
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", "casnet", "--checkpoint", ckpt, "--out", out,
                                 "--device", "cpu", "--no-picture"])
    assert code == 0, err
    kept = read_velodyne(out / "000007_casnet_d8.bin")
    assert kept.shape == (50, 4) and _rows(kept) <= _rows(read_velodyne(scan)) and len(_rows(kept)) == 50


def test_casnet_of_a_training_checkpoint(run_cli, scan, tmp_path):
    casnet_pointnet = pytest.importorskip("lidarops.models.casnet_pointnet")
    model = casnet_pointnet.CASNetPointNet(None, load_task=False)
    ckpt = model.save(tmp_path / "final.pth")
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", "casnet", "--checkpoint", ckpt, "--ratio", 2,
                                 "--out", out, "--device", "cpu", "--no-picture"])
    assert code == 0, err
    kept = read_velodyne(out / "000007_casnet_d2.bin")
    assert kept.shape == (201, 4) and _rows(kept) <= _rows(read_velodyne(scan)) and len(_rows(kept)) == 201


def _error(run_cli, argv, named):
    code, stdout, err = run_cli(["sample", *argv])
    assert code == 2, (stdout, err)
    line = one_error_line(err, "sample")
    assert named in line, line
    return line


def test_errors_are_one_line_naming_the_argument(run_cli, scan, tmp_path):
    out = tmp_path / "out"
    base = ["--out", out, "--device", "cpu", "--no-picture"]
    _error(run_cli, [tmp_path / "no" / "such.bin", *base], "such.bin")
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\0" * 20)  # not a whole number of 16-byte records
    _error(run_cli, [bad, *base], "bad.bin")
    (tmp_path / "scan.txt").write_text("1 2 3 4\n")
    _error(run_cli, [tmp_path / "scan.txt", *base], "scan.txt")
    (tmp_path / "empty_dir").mkdir()
    _error(run_cli, [tmp_path / "empty_dir", *base], "not a KITTI folder")
    for value in ("0", "-2", "1.5", "abc"):
        _error(run_cli, [scan, "--ratio", value, *base], "--ratio")
    _error(run_cli, [scan, "--frames", "0", *base], "--frames")
    _error(run_cli, [scan, "--method", "voxel", *base], "--method")
    _error(run_cli, [scan, "--method", "casnet", "--checkpoint", tmp_path / "none.pth", *base], "--checkpoint")
    _error(run_cli, [scan, "--method", "casnet", "--checkpoint", bad, *base], "bad.bin")
    _error(run_cli, [scan, "--method", "fps", "--checkpoint", bad, *base], "--checkpoint")
    _error(run_cli, [scan, "--out", bad, "--device", "cpu"], "--out")
    _error(run_cli, [scan, "--device", "tpu", "--out", out], "--device")
    _error(run_cli, [scan, "--method", "fps", "--fp16", *base], "--fp16")
    _error(run_cli, [scan, "--method", "casnet", "--fp16", *base], "--fp16 is for --method casnet on CUDA")
    assert not out.exists()  # nothing written by a refused command


def test_casnet_defaults_to_the_shipped_detection_casnet(run_cli, scan, tmp_path, monkeypatch):
    from lidarops.cli.sample import SHIPPED_CASNET
    from lidarops.models import weights
    from lidarops.models.casnet import CASNetSampler, load_casnet

    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", "casnet", "--out", out, "--device", "cpu", "--no-picture"])
    assert code == 0, err
    kept = read_velodyne(out / "000007_casnet_d8.bin")
    points = torch.from_numpy(read_velodyne(scan)).unsqueeze(0)
    # the whole scan through the shipped model (its anchored head takes the scan at once)
    idx = CASNetSampler(load_casnet(SHIPPED_CASNET), whole=True)(points, points.shape[1] // 8)[0]
    assert np.array_equal(kept, points[0, idx].numpy())
    monkeypatch.setattr(weights, "WEIGHTS_DIR", tmp_path / "no-weights")
    line = _error(run_cli, [scan, "--method", "casnet", "--out", out, "--device", "cpu"], "--checkpoint")
    assert SHIPPED_CASNET in line and "not found" in line


def test_casnet_checkpoint_errors(run_cli, scan, tmp_path):
    from lidarops.models.casnet import CASNet

    base = ["--method", "casnet", "--out", tmp_path / "out", "--device", "cpu", "--no-picture"]
    ckpt = tmp_path / "c.pth"
    torch.save({"state_dict": CASNet(num_out=8).state_dict()}, ckpt)
    _error(run_cli, [scan, "--checkpoint", ckpt, *base], "model_config")
    torch.save({"model_config": {"num_out": 8, "wings": 2}, "state_dict": {}}, ckpt)
    _error(run_cli, [scan, "--checkpoint", ckpt, *base], "model_config")
    torch.save({"model_config": {"num_out": 8}, "state_dict": CASNet(num_out=4).state_dict()}, ckpt)
    _error(run_cli, [scan, "--checkpoint", ckpt, *base], "weights do not fit")


def test_out_cannot_be_the_input_folder(run_cli, folder):
    _error(run_cli, [folder, "--out", folder / "training", "--device", "cpu", "--no-picture"], "--out")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_casnet_fp16_on_cuda(run_cli, scan, tmp_path):
    """The shipped CAS-Net under float16 autocast: a subset of the scan, distinct points, its count."""
    out = tmp_path / "out"
    code, stdout, err = run_cli(["sample", scan, "--method", "casnet", "--fp16", "--out", out, "--device", "cuda",
                                 "--no-picture"])
    assert code == 0, err
    kept = read_velodyne(out / "000007_casnet_d8.bin")
    assert kept.shape == (50, 4) and _rows(kept) <= _rows(read_velodyne(scan)) and len(_rows(kept)) == 50
