"""lidarops.models.sscater_pointpillars: SSCATeRPointPillars, the streaming PointPillars front (PillarFeatureNet,
the recycling backbone), against the full recomputation of the pushed window at every step of simulated LiDAR
streams."""
from __future__ import annotations

import pytest
import torch

from helpers.devices import DEVICES
from helpers.models import randomize_bn
from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.models.sscater_pointpillars import PillarFeatureNet, SSCATeRPointPillars
from lidarops.ops.pillars import PillarGrid

# ---- the streaming PointPillars front on simulated LiDAR streams -----------------------------------

DRIVING_AHEAD = PillarGrid.driving_ahead()
STREAMS = {"drone_bridge": (PillarGrid.drone(), 100), "driving_city": (DRIVING_AHEAD, 256)}


def streaming_model(dtype, device, negative_bias=0.3, seed=0, width=(16, 32, 64), up=32):
    """Default PointPillars layout (layer counts 3/5/5, strides 2/2/2, upsampling 1/2/4) at reduced
    width so that hundreds of CPU steps stay quick; identity does not depend on the width."""
    torch.manual_seed(seed)
    pfn = PillarFeatureNet(9, width[0])
    bb = BaseBEVBackbone(width[0], (3, 5, 5), (2, 2, 2), width, (1, 2, 4), (up, up, up))
    randomize_bn(pfn, seed)
    randomize_bn(bb, seed + 1, negative_bias)
    return pfn.eval().to(device, dtype), bb.eval().to(device, dtype)


def run_identity(scenario, steps, dtype, device, refresh_every, check_every=1, seed=3, negative_bias=0.3):
    """Stream ``steps`` 10 ms slices; every ``check_every`` steps compare with the full recomputation
    of the pushed window. Returns (worst relative difference, stats of each step)."""
    from lidarops.data.synthetic import Simulator
    grid, N = STREAMS[scenario]
    pfn, bb = streaming_model(dtype, device, negative_bias)
    model = SSCATeRPointPillars(pfn, bb, grid, max_points_per_pillar=N, refresh_every=refresh_every, dtype=dtype,
                                device=device)
    pushed_p, pushed_t = [], []
    worst, history = 0.0, []
    for i, (p, t) in enumerate(Simulator(scenario, seed=seed).slices(0.0, 0.01 * steps, 0.01)):
        end = 0.01 * (i + 1)
        if i % 37 == 20:  # a dropout: nothing arrives for this slice
            p, t = p[:0], t[:0]
        pushed_p.append(torch.from_numpy(p))
        pushed_t.append(torch.from_numpy(t))
        out = model.step(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device), now=end)
        history.append(model.stats)
        if i % check_every == 0 or i == steps - 1:
            allp, allt = torch.cat(pushed_p), torch.cat(pushed_t)
            keep = allt > model.stats.t - model.window
            pushed_p, pushed_t = [allp[keep]], [allt[keep]]
            ref = model.recompute(allp[keep], N)
            scale = ref.abs().max().item()
            diff = (out - ref).abs().max().item()
            rel = diff / scale if scale > 0 else (0.0 if diff == 0 else float("inf"))  # empty window: all zero
            worst = max(worst, rel)
            assert rel <= (1e-12 if dtype == torch.float64 else 1e-5), f"{scenario} step {i}: relative diff {rel:.3e}"
    return worst, history


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["drone_bridge", "driving_city"])
def test_sscater_stream_equals_full_recomputation_float32(scenario):
    """200 steps (2 s) on CPU, every step compared. drone_bridge runs with refresh_every=0: nothing is
    recomputed after the first step, so the bound holds for the recycled sums themselves; driving_city
    runs with the default refresh."""
    refresh = 0 if scenario == "drone_bridge" else 25
    worst, history = run_identity(scenario, 200, torch.float32, "cpu", refresh_every=refresh)
    assert sum(s.refreshed for s in history) == (1 if refresh == 0 else 8)
    changed = [s.pillars_changed / max(s.pillars_active, 1) for s in history[20:]]
    assert 0.0 < sum(changed) / len(changed) < 1.0  # pillars do change, and not all of them


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["drone_bridge", "driving_city"])
def test_sscater_stream_equals_full_recomputation_float64(scenario):
    run_identity(scenario, 25, torch.float64, "cpu", refresh_every=10, check_every=1)


@pytest.mark.parametrize("device", [d for d in DEVICES if d.values[0] == "cuda"] or
                         [pytest.param("cuda", marks=pytest.mark.skip(reason="needs a GPU; the CPU run is "
                                                                           "test_sscater_stream_equals_full_recomputation_float32"))])
def test_sscater_stream_1000_steps_on_gpu(device):
    """The GPU acceptance run: 1,000 steps (10 s) of drone_bridge with the default refresh, every 10th
    step compared with the full recomputation."""
    worst, history = run_identity("drone_bridge", 1000, torch.float32, device, refresh_every=25, check_every=10)
    assert len(history) == 1000


def test_sscater_pointpillars_bad_arguments():
    pfn, bb = streaming_model(torch.float32, "cpu")
    with pytest.raises(ValueError, match="eval mode"):
        SSCATeRPointPillars(pfn.train(), bb, PillarGrid.drone())
    pfn.eval()
    with pytest.raises(ValueError, match="refresh_every must be an int >= 0"):
        SSCATeRPointPillars(pfn, bb, PillarGrid.drone(), refresh_every=-1)
    with pytest.raises(ValueError, match="upsampled maps of different sizes"):
        SSCATeRPointPillars(pfn, bb, PillarGrid((0, 0, -1, 8.1, 8.1, 1), (0.1, 0.1)))
    with pytest.raises(ValueError, match="must equal backbone.in_channels"):
        SSCATeRPointPillars(PillarFeatureNet(9, 8).eval(), bb, PillarGrid.drone())
