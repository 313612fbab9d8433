"""lidarops.train on GPUs: ``torchrun`` + NCCL DDP, SyncBatchNorm, evaluation gathered over ranks.

Skipped without 2 CUDA devices. The file is also the torchrun script the tests launch::

    torchrun --standalone --nproc_per_node=2 tests/train/test_cuda.py OUT_DIR BATCH [--sync-bn]

With BatchNorm in training mode, 2 GPUs x 8 frames match 1 GPU x 16 frames only with ``sync_bn``: each
rank otherwise normalises with the statistics of its own 8 frames.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import torch
from torch import nn
from torch.utils.data import Dataset

from lidarops.train import TrainConfig, fit, load_checkpoint

N_FRAMES, PER_GPU, EPOCHS = 32, 8, 3


class Frames(Dataset):
    def __init__(self, n: int, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 4, generator=g)
        self.y = torch.sin(self.x @ torch.randn(4, 2, generator=g))

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> dict:
        return {"x": self.x[i], "y": self.y[i], "frame_id": i}


def collate(items: list[dict]) -> dict:
    return {"x": torch.stack([it["x"] for it in items]), "y": torch.stack([it["y"] for it in items]),
            "frame_id": [it["frame_id"] for it in items]}


class BNModel(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        # no bias before BatchNorm: its true gradient is zero, and Adam would turn the rounding noise of
        # that zero into full-size steps that differ from run to run
        self.net = nn.Sequential(nn.Linear(4, 32, bias=False), nn.BatchNorm1d(32), nn.ReLU(), nn.Linear(32, 2))

    def forward(self, batch: dict):
        pred = self.net(batch["x"])
        if not self.training:
            return pred
        return {"loss": (pred - batch["y"]).pow(2).sum(-1).mean()}

    def postprocess(self, raw, batch):
        return [{"y": r} for r in raw]


def order_evaluator(predictions, frames):
    ids = [f["frame_id"] for f in frames]
    return {"frames": len(ids), "in_order": float(ids == list(range(len(ids))))}, ""


def train(out_dir: str, batch_size: int, sync_bn: bool, device: str = "auto") -> dict:
    config = TrainConfig(epochs=EPOCHS, batch_size=batch_size, num_workers=2, seed=0, log_every=1, progress=False,
                         tensorboard=False, ckpt_every_min=None, sync_bn=sync_bn, device=device)
    result = fit(BNModel(), Frames(N_FRAMES), collate, config, out_dir, val_dataset=Frames(7, seed=1),
                 evaluator=order_evaluator)
    return {"world_size": result.world_size, "fps": result.frames_per_s, "fps_total": result.frames_per_s_total,
            "metrics": result.metrics, "global_step": result.global_step}


def _torchrun(out_dir, sync_bn: bool) -> dict:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", __file__,
           str(out_dir), str(PER_GPU)] + (["--sync-bn"] if sync_bn else [])
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=400, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((out_dir / "result.json").read_text())


if __name__ == "__main__":  # the torchrun script
    out, batch = sys.argv[1], int(sys.argv[2])
    res = train(out, batch, "--sync-bn" in sys.argv)
    if int(os.environ.get("RANK", "0")) == 0:
        with open(os.path.join(out, "result.json"), "w") as f:
            json.dump(res, f)
    sys.exit(0)

import pytest  # noqa: E402  (not needed by the torchrun script)

pytestmark = pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs 2 CUDA devices")


def test_ddp_nccl_sync_bn_matches_one_gpu_on_the_global_batch(tmp_path):
    one = train(str(tmp_path / "one"), 2 * PER_GPU, sync_bn=False, device="cuda:0")
    synced = _torchrun(tmp_path / "two_sync", sync_bn=True)
    unsynced = _torchrun(tmp_path / "two", sync_bn=False)
    ref = load_checkpoint(tmp_path / "one" / "final.pth")["model_state"]
    for name, run, should_match in (("two_sync", synced, True), ("two", unsynced, False)):
        state = load_checkpoint(tmp_path / name / "final.pth")["model_state"]
        diffs = {k: (state[k].float() - ref[k].float()).abs().max().item() for k in ref}
        diff = max(diffs.values())
        assert (diff < 1e-5) == should_match, f"{name}: max difference {diff:.3e}; {diffs}"
        assert run["world_size"] == 2 and run["global_step"] == one["global_step"] == EPOCHS * N_FRAMES // 16
        assert run["metrics"] == {"frames": 7.0, "in_order": 1.0}
    print(f"\ntoy throughput: 1 GPU {one['fps']:.0f} frames/s; 2 GPUs {synced['fps']:.0f} per process, "
          f"{synced['fps_total']:.0f} in all")
