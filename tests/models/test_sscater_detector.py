"""Streaming detection with a trained-style PointPillars (SSCATeRPointPillars.from_detector): every step's
head outputs and boxes equal the detector's own eager call on the points the stream holds (its dense
backbone: zero padding, BatchNorm's shift at every site), while only the changed pillars and the sites their
changes reach are recomputed."""
from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from lidarops.models.pointpillars import PointPillars
from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

from helpers.devices import requires_cuda
from helpers.models import TINY, randomize_bn

#: a 32 x 32 grid of 0.5 m pillars (divisible by the backbone's strides 2, 2, 2), two classes
CFG = {**TINY, "class_names": ["Car", "Pedestrian"], "point_cloud_range": [0.0, -8.0, -3.0, 16.0, 8.0, 1.0],
       "voxel_size": [0.5, 0.5, 4.0], "max_points_per_voxel": 6, "score_thresh": 0.2, "nms_thresh": 0.2,
       "anchor_generator_config": [
           {**TINY["anchor_generator_config"][0], "class_name": "Car"},
           {**TINY["anchor_generator_config"][0], "class_name": "Pedestrian", "anchor_sizes": [[0.8, 0.6, 1.7]]}]}


def _detector(dtype, seed=0):
    torch.manual_seed(seed)
    model = PointPillars(CFG)
    randomize_bn(model.backbone_2d, seed)  # BatchNorm statistics away from identity: ReLU zeros, shifts
    randomize_bn(model.vfe, seed + 1)
    with torch.no_grad():
        model.dense_head.conv_cls.bias.fill_(-0.5)  # scores near 0.4: boxes pass the threshold
    return model.to(dtype).eval()


def _slices(steps, seed=0, per_slice=40):
    """Slices of 10 ms: points in the grid (and a few outside it), some pillars crowded past their slots."""
    g = torch.Generator().manual_seed(seed)
    for k in range(steps):
        pts = torch.rand(per_slice, 4, generator=g) * torch.tensor([16.0, 16.0, 4.0, 1.0]) + torch.tensor([0, -8.0, -3, 0])
        hot = torch.rand(per_slice // 4, 4, generator=g) * torch.tensor([1.0, 1.0, 4.0, 1.0]) + torch.tensor([4.0, 0, -3, 0])
        out = torch.tensor([[20.0, 0.0, 0.0, 0.5], [3.0, 1.0, 5.0, 0.5]])  # beyond x, above z
        pts = torch.cat([pts, hot, out])
        t = 0.01 * k + torch.rand(len(pts), generator=g, dtype=torch.float64) * 0.01
        yield pts.float(), t


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_streamed_boxes_equal_the_detector_on_the_window(device, dtype, tol):
    detector = _detector(dtype).to(device)
    stream = SSCATeRPointPillars.from_detector(detector, window=0.1, refresh_every=7, dtype=dtype)
    boxes_seen = recycled = 0
    for k, (pts, t) in enumerate(_slices(30)):
        stream.step(pts.to(device), t.to(device))
        recycled += not stream.stats.refreshed
        window = stream.window_points()
        batch = {"points": F.pad(window.to(dtype), (1, 0)), "batch_size": 1}
        with torch.no_grad():
            raw = detector(batch)
            got_raw = detector.dense_head(stream.delta.out.to(dtype))
        for key in ("cls_preds", "box_preds", "dir_cls_preds"):
            scale = raw[key].abs().max().item() or 1.0
            err = (got_raw[key] - raw[key]).abs().max().item() / scale
            assert err <= tol, (k, key, err)
        got, want = stream.detect(), detector.postprocess(raw)[0]
        assert got["labels"].tolist() == want["labels"].tolist(), k
        assert torch.allclose(got["scores"], want["scores"], atol=tol * 10), k
        assert torch.allclose(got["boxes"], want["boxes"], atol=tol * 100), k
        boxes_seen += len(want["labels"])
    assert recycled >= 20 and boxes_seen > 0, (recycled, boxes_seen)
    assert stream.stats.pillars_changed < stream.stats.pillars_active + stream.stats.points_out


@requires_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_detect_as_a_cuda_graph_equals_the_eager_head_and_postprocess(monkeypatch, dtype):
    """detect() on CUDA replays the head, decode and padded post-processing as one graph (DETECT_CUDA_GRAPH): the
    same boxes as the eager head and postprocess on the same map, at every step; the boxes it returned are the
    caller's (the next replay does not overwrite them); a change of TF32 or of the detector's config captures the
    graph again."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)
    detector = _detector(dtype, seed=4).cuda()
    stream = SSCATeRPointPillars.from_detector(detector, window=0.1, refresh_every=6, dtype=dtype)
    kept, boxes_seen = [], 0
    for k, (pts, t) in enumerate(_slices(24, seed=5)):
        stream.step(pts.cuda(), t.cuda())
        got = stream.detect()
        assert stream._detect_graph is not None
        with torch.no_grad():
            want = detector.postprocess(detector.dense_head(stream.delta.out.to(dtype)))[0]
        assert got["labels"].tolist() == want["labels"].tolist(), k
        tol = 1e-12 if dtype == torch.float64 else 1e-5  # cuDNN may pick another algorithm inside the graph
        assert torch.allclose(got["scores"], want["scores"], rtol=0, atol=tol), k
        assert torch.allclose(got["boxes"], want["boxes"], rtol=0, atol=tol * 100), k
        kept.append((got, {key: v.clone() for key, v in got.items()}))
        boxes_seen += len(want["labels"])
    for got, copy in kept:
        assert all(torch.equal(got[key], copy[key]) for key in copy)
    assert boxes_seen > 0
    graph = stream._detect_graph[2]
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    stream.detect()
    assert stream._detect_graph[2] is not graph
    # the graph holds the config's thresholds: a change in place is seen
    with torch.no_grad():
        want = detector.postprocess(detector.dense_head(stream.delta.out.to(dtype)))[0]
    assert len(want["scores"]) > 0
    kept = detector.config.score_thresh
    detector.config.score_thresh = float(want["scores"].max()) + 1e-3  # no box is kept
    assert stream.detect()["labels"].tolist() == []
    detector.config.score_thresh = kept
    # boxes out of the supported range (sizes exp(40) times the anchor's): the eager post-processing's error
    with torch.no_grad():
        detector.dense_head.conv_box.bias[3:6] += 40.0  # in place: the graph reads the parameter's memory
    with pytest.raises(ValueError, match="boxes must hold centres within"):
        detector.postprocess(detector.dense_head(stream.delta.out.to(dtype)))
    with pytest.raises(ValueError, match="boxes must hold centres within"):
        stream.detect()


def test_warm_up_records_every_graph_before_the_first_step(monkeypatch, device):
    """warm_up() records the CUDA graphs of the refresh, the update and detect() for every capacity up to the pillars
    given, so that no step records one below that; the steps' boxes are those of a stream without it. On the CPU
    it records nothing and changes nothing. It refuses to run once the stream has started, and a bad count."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    dtype = torch.float32
    detector = _detector(dtype, seed=2).to(device)
    warm = SSCATeRPointPillars.from_detector(detector, window=0.1, refresh_every=7, dtype=dtype)
    cold = SSCATeRPointPillars.from_detector(detector, window=0.1, refresh_every=7, dtype=dtype)
    recorded = warm.warm_up(pillars=700, points=4096)
    graphs, pushes = warm.delta.cuda_graphs, len(warm.stream._push_graphs)
    if device == "cuda":  # refreshes 1024; updates 256, 512, 1024; detect; pushes of 1024 ... 4096 points
        assert recorded == 5 + pushes and graphs == 4 and warm._detect_graph is not None, (recorded, graphs)
        assert pushes == 3, pushes
    else:
        assert recorded == 0 and graphs == 0 and pushes == 0
    for k, (pts, t) in enumerate(_slices(16, seed=3)):
        warm.step(pts.to(device), t.to(device))
        cold.step(pts.to(device), t.to(device))
        assert warm.stats.pillars_active <= 700
        assert warm.delta.cuda_graphs == graphs and len(warm.stream._push_graphs) == pushes, k  # none by a step
        got, want = warm.detect(), cold.detect()
        assert got["labels"].tolist() == want["labels"].tolist(), k
        assert torch.allclose(got["scores"], want["scores"], rtol=0, atol=1e-5), k
    with pytest.raises(ValueError, match="before the first step"):
        warm.warm_up()
    warm.reset()
    for bad in (0, -3, 2.5, True, "64"):
        with pytest.raises(ValueError, match="pillars must be an int >= 1"):
            warm.warm_up(bad)
    for bad in (-1, 2.5, True, None):
        with pytest.raises(ValueError, match="points must be an int >= 0"):
            warm.warm_up(100, points=bad)
    for bad in (300, 128, 512.0, True):
        with pytest.raises(ValueError, match="capacity must be a power of two >= 256"):
            warm.delta.prepare_update(bad, warm._changed_features)
    with pytest.raises(ValueError, match="features must be a function of the sites"):
        warm.delta.prepare_update(512, torch.zeros(512, 4))


@pytest.mark.parametrize("dense_share", [2.0, 0.5, 0.0])  # never, the default, always the dense head
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_head_on_changed_sites_equals_the_head_on_the_whole_map(monkeypatch, device, dtype, tol, dense_share):
    """The head recomputed only where the recycled map changed since the last call (detect every step, or after
    several steps, across refreshes), or as one dense convolution once HEAD_DENSE_SHARE of the sites changed,
    equals the head run on the whole map."""
    from lidarops.models import sscater_pointpillars

    monkeypatch.setattr(sscater_pointpillars, "HEAD_DENSE_SHARE", dense_share)
    detector = _detector(dtype, seed=2).to(device)
    stream = SSCATeRPointPillars.from_detector(detector, window=0.1, refresh_every=9, dtype=dtype)
    partial = 0
    for k, (pts, t) in enumerate(_slices(40, seed=3)):
        stream.step(pts.to(device), t.to(device))
        if k % 3 == 1:  # some steps pass without a call: their changes add up
            continue
        partial += stream._head_sites is not None and len(stream._head_sites) > 0
        got = stream.head_outputs()
        with torch.no_grad():
            want = detector.dense_head(stream.delta.out.to(dtype))
        for key in ("cls_preds", "box_preds", "dir_cls_preds"):
            scale = want[key].abs().max().item() or 1.0
            err = (got[key] - want[key]).abs().max().item() / scale
            assert err <= tol, (k, key, err)
    if not stream.delta.sync_free:  # on the CPU the head worked on the changed sites only
        assert partial >= 10, partial


def test_stream_holds_the_detectors_slots_and_drops_the_rest():
    detector = _detector(torch.float32)
    stream = SSCATeRPointPillars.from_detector(detector)
    assert stream.stream.max_points_per_pillar == CFG["max_points_per_voxel"] and stream.stream.overflow == "drop"
    for pts, t in _slices(3):
        stream.step(pts, t)
    assert stream.stats.points_dropped > 0  # the crowded pillars
    window = stream.window_points()
    assert window.shape[1] == 4 and len(window) == stream.stream.num_points


def test_from_detector_refuses_what_it_cannot_stream():
    with pytest.raises(TypeError, match="detector must be a PointPillars"):
        SSCATeRPointPillars.from_detector(torch.nn.Linear(2, 2))
    with pytest.raises(ValueError, match="backbone_mode='dense'"):
        SSCATeRPointPillars.from_detector(PointPillars({**CFG, "backbone_mode": "sparse"}))
    plain = SSCATeRPointPillars.from_detector(_detector(torch.float32))
    plain.detector = None
    with pytest.raises(ValueError, match="detect\\(\\) needs a model made by"):
        plain.detect()


def test_cli_stream_with_a_checkpoint_prints_boxes_and_checks_them(tmp_path, capsys):
    """``lidarops stream --checkpoint``: a step per slice with its boxes, every check the detector's own boxes on
    the same points (exit 0), the figures in --json."""
    import json

    from lidarops.checkpoint import format_fields, save_checkpoint
    from lidarops.cli import main

    detector = _detector(torch.float32)
    path = tmp_path / "pp.pth"
    save_checkpoint({**format_fields(), "model_class": "PointPillars", "model_config": detector.config.to_dict(),
                     "class_names": list(detector.config.class_names), "model_state": detector.state_dict()}, [path])
    rc = main(["stream", "--checkpoint", str(path), "--seconds", "0.08", "--check-every", "3", "--device", "cpu",
               "--json", str(tmp_path / "steps.json")])
    out = capsys.readouterr().out
    assert rc == 0, out
    steps = json.loads((tmp_path / "steps.json").read_text())["steps"]
    assert [s["step"] for s in steps] == list(range(8))
    checks = [s["same_as_detector"] for s in steps if "same_as_detector" in s]
    assert checks == [True, True] and "2 check(s) against the detector: all the same boxes" in out
    assert sum(sum(s["boxes"].values()) for s in steps) > 0 and any(not s["refreshed"] for s in steps)
    assert main(["stream", "--checkpoint", str(tmp_path / "missing.pth"), "--device", "cpu"]) == 2


@pytest.mark.slow  # a shipped detector on the CPU: about half a minute
@pytest.mark.parametrize("name, scenario", [("pointpillars_synth", "driving_city"),
                                            ("aerial_pointpillars", "drone_bridge")])
def test_shipped_detector_streamed_gives_its_own_boxes(name, scenario):
    """The trained checkpoints on a short stream of their scenes (the KITTI-view detector on driving_city; the
    Aerial-PointPillars, 504 x 504 pillars and anchors in 13 height layers, on the Avia's drone_bridge): at each
    checked step the same labels as the detector on the stream's points, scores within float32 rounding, boxes
    found."""
    from lidarops.data.synthetic import Simulator
    from lidarops.models import weights

    detector = weights.load(name)
    stream = SSCATeRPointPillars.from_detector(detector)
    sim = Simulator(scenario, seed=3)
    found = 0
    for k in range(9):
        pts, t = sim.stream(0.01 * k, 0.01 * (k + 1))
        stream.step(torch.from_numpy(pts), torch.from_numpy(t))
        if k % 4 == 0 or k == 8:
            got = stream.detect()
            want = detector.predict({"points": F.pad(stream.window_points(), (1, 0)), "batch_size": 1})[0]
            assert got["labels"].tolist() == want["labels"].tolist(), k
            assert torch.allclose(got["scores"], want["scores"], atol=1e-5), k
            assert torch.allclose(got["boxes"], want["boxes"], atol=1e-4), k
            found += len(want["labels"])
    assert found > 0 and not stream.stats.refreshed


@pytest.mark.slow  # 1,000 steps of 10 ms on the GPU: about half a minute, most of it simulating the stream
@requires_cuda
@pytest.mark.parametrize("name, scenario, realism", [("pointpillars_synth", "driving_city", None),
                                                     ("aerial_pointpillars", "drone_bridge", None),
                                                     ("aerial_pointpillars", "drone_bridge", "avia")])
def test_shipped_detector_streamed_on_cuda_for_1000_steps(monkeypatch, name, scenario, realism):
    """Issue 39's long identity: a shipped detector streamed on CUDA for 1,000 steps of a scene it was trained on
    (ray-cast, and the Aerial-PointPillars' realism profile; about 40 refreshes): every 10th step the boxes are the detector's on the stream's points, and the head outputs
    on the recycled map are as close to the exact answer (the detector in float64 on the same pillars) as the
    float32 detector's own are. (cuDNN's TF32 off: the detector's own convolutions would round their inputs to 10
    bits.) A fixed tolerance against the float32 detector cannot be the test: on driving_city that detector is
    itself 4e-5 of its largest output away from the exact answer on the H200 (3e-5 on a CPU)."""
    import copy

    from lidarops.data.synthetic import Simulator
    from lidarops.models import weights

    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)

    detector = weights.load(name).cuda()
    exact = copy.deepcopy(detector).double()
    stream = SSCATeRPointPillars.from_detector(detector, device="cuda")
    sim = Simulator(scenario, seed=5, realism=realism)
    checked = found = recycled = 0
    worst = {"stream": 0.0, "detector": 0.0, "between": 0.0}
    for k in range(1012):
        pts, t = sim.stream(0.01 * k, 0.01 * (k + 1))
        stream.step(torch.from_numpy(pts).cuda(), torch.from_numpy(t).cuda(), now=0.01 * (k + 1))
        recycled += not stream.stats.refreshed
        if k < 12 or k % 10:
            continue
        batch = {"points": F.pad(stream.window_points(), (1, 0)), "batch_size": 1}
        with torch.no_grad():
            raw = detector(batch)
            got_raw = detector.dense_head(stream.delta.out)
            vox = detector.voxelize(batch["points"], 1)  # float64 points could fall into other cells
            vox64 = [v.double() if v.is_floating_point() else v for v in vox]
            ref = exact.dense_head(exact.backbone_2d(exact.map_to_bev(exact.vfe(*vox64), vox[2], 1)))
        for key in ("cls_preds", "box_preds", "dir_cls_preds"):
            scale = ref[key].abs().max().item() or 1.0
            for who, x, y in (("stream", got_raw[key], ref[key]), ("detector", raw[key], ref[key]),
                              ("between", got_raw[key], raw[key])):
                worst[who] = max(worst[who], (x.double() - y.double()).abs().max().item() / scale)
        got, want = stream.detect(), detector.postprocess(raw)[0]
        assert got["labels"].tolist() == want["labels"].tolist(), k
        assert torch.allclose(got["scores"], want["scores"], atol=1e-4), k
        checked, found = checked + 1, found + len(want["labels"])
    print(f"worst relative error of the head outputs over {checked} checks against float64: "
          f"stream {worst['stream']:.2e}, detector {worst['detector']:.2e}; between them {worst['between']:.2e}")
    # float32 sums in another order, over up to 25 recycled steps between refreshes: no further from the exact
    # answer than twice the float32 detector's own error (a missed or doubled delta is off by far more)
    assert worst["stream"] <= max(2 * worst["detector"], 1e-5), worst
    assert checked == 100 and found > 0 and recycled > 900, (checked, found, recycled)
