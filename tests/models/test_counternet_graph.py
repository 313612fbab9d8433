"""CounterNet's counting as one CUDA graph (lidarops.models.cuda_graph.padded_counting, GraphedCounterNet): the
graph's body run eagerly gives each frame's own predict (partitions, overlap and merge, ragged and empty frames,
duplicate points, frames over the pillar capacity), its flags (bad intensity, too few pillar or peak rows, a merge
that has not settled) are raised where they should be, and on a GPU the replayed graph gives the body's answers."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

import lidarops
from lidarops.models.counternet import CounterNet
from lidarops.models.counting import merge_centres

from .test_counternet import SCENES, _scene, _tiny_cfg

PAD = torch.tensor([1000.0, 0, 0, 0])


def _model(partitions=1, delta=0.0, seed=0, **head) -> CounterNet:
    """A tiny CounterNet whose heatmaps hold many peaks: the final biases at 0 put every cell near 0.5."""
    torch.manual_seed(seed)
    cfg = _tiny_cfg(partitions, delta, **head)
    cfg["DATA_CONFIG"]["DATA_PROCESSOR"][2]["MAX_NUMBER_OF_VOXELS"]["test"] = 300
    model = CounterNet(cfg).eval()
    with torch.no_grad():
        for branch in model.count_head.heatmaps:
            branch[-1].bias.zero_()
            branch[-1].weight.mul_(4.0)
    return model


def _frames(empty: bool = True) -> list[torch.Tensor]:
    """Two scenes, an empty frame, a frame with duplicate points and a sparse one. (The empty frame's heatmaps
    are flat, so that every cell above the threshold is a peak: with overlapping regions more than the tests'
    peak rows; ``empty=False`` leaves it out.)"""
    frames = [_scene(i, s)[0][:, 1:] for i, s in enumerate(SCENES)]
    if empty:
        frames.append(frames[0][:0])
    frames.append(torch.cat([frames[1][:200], frames[1][:50]]))
    frames.append(frames[0][::7])
    return frames


def _padded(frames: list[torch.Tensor]) -> torch.Tensor:
    n = max(len(f) for f in frames)
    return torch.stack([torch.cat([f, PAD.to(f.device).expand(n - len(f), 4)]) for f in frames])


def _predict(model, frame):
    return model.predict({"points": F.pad(frame, (1, 0)), "batch_size": 1})[0]


def _assert_same(out: dict, b: int, want: dict, what: str) -> None:
    k = int(out["num_centres"][b])
    assert out["counts"][b].tolist() == want["counts"].tolist(), what
    assert k == want["centres"].shape[0], what
    # x, y, class exactly; the scores and features of a frame in a batch round as the network's batch does
    assert torch.equal(out["centres"][b, :k, :3], want["centres"][:, :3]), what
    assert torch.allclose(out["centres"][b, :k, 3], want["centres"][:, 3], rtol=0, atol=1e-6), what
    assert (out["centres"][b, k:] == 0).all(), what
    assert torch.allclose(out["features"][b], want["features"], rtol=1e-5, atol=1e-6), what


@pytest.mark.parametrize("partitions, delta", [(1, 0.0), (4, 0.0), (4, 0.2), (9, 0.3), (2, 0.1)])
def test_padded_counting_equals_per_frame_predict(partitions, delta):
    from lidarops.models.cuda_graph import padded_counting

    model = _model(partitions, delta)
    frames = _frames(empty=delta == 0)
    with torch.no_grad():
        out = padded_counting(model, _padded(frames), max_peaks=1536, exact_otsu=True)
    assert not out["bad"].any() and not out["peak_overflow"].any() and not out["unmerged"].any()
    merged = 0
    for b, f in enumerate(frames):
        _assert_same(out, b, _predict(model, f), f"frame {b}")
        merged += int(out["peaks"][b]) - int(out["counts"][b].sum())
    assert int(out["counts"].sum()) > 10, "the case must find peaks"
    if delta > 0:
        assert merged > 0, "the case must merge centres found by two regions"
    else:
        assert merged == 0


def test_frames_over_the_pillar_capacity_and_too_few_rows():
    from lidarops.models.cuda_graph import padded_counting

    model = _model(4, 0.2)
    frames = _frames()
    floor = model.config.floor_config()
    cells = [int((f[:, 0] / 0.32).floor().mul(48).add(((f[:, 1] + 7.68) / 0.32).floor()).unique().numel())
             for f in frames]
    assert max(cells) > floor.max_voxels_test, "a frame must hold more pillars than the capacity"
    needed = sum(min(c, floor.max_voxels_test) for c in cells)
    with torch.no_grad():
        out = padded_counting(model, _padded(frames), max_peaks=1536, exact_otsu=True)
        tight = padded_counting(model, _padded(frames), max_peaks=1536, max_pillars=needed, exact_otsu=True)
        short = padded_counting(model, _padded(frames), max_peaks=1536, max_pillars=needed - 1, exact_otsu=True)
    assert int(out["pillars"]) == needed and not bool(out["overflow"])
    assert torch.equal(tight["counts"], out["counts"]) and torch.equal(tight["centres"], out["centres"])
    assert bool(short["overflow"]) and not bool(tight["overflow"])


def test_too_few_peak_rows_are_flagged_and_counts_without_overlap_stay_exact():
    from lidarops.models.cuda_graph import padded_counting

    frames = _frames()
    for delta in (0.0, 0.2):
        model = _model(4, delta)
        with torch.no_grad():
            full = padded_counting(model, _padded(frames), max_peaks=1536, exact_otsu=True)
            few = padded_counting(model, _padded(frames), max_peaks=3, exact_otsu=True)
        assert few["centres"].shape[1] == 3
        assert few["peak_overflow"].tolist() == (full["peaks"] > 3).tolist() and few["peak_overflow"].any()
        if delta == 0:  # the counts are the peaks' number, whatever the rows hold
            assert torch.equal(few["counts"], full["counts"])
            # the rows hold each frame's first peaks, in order
            k = few["num_centres"]
            assert k.tolist() == full["num_centres"].clamp(max=3).tolist()
            assert torch.equal(few["centres"], full["centres"][:, :3])


def test_merge_settles_as_the_greedy_scan_and_flags_what_has_not():
    """Chains of conflicting centres need one round per link: too few rounds flag the frame; enough rounds give
    merge_centres' answer (the eager greedy scan)."""
    from lidarops.models.cuda_graph import padded_counting

    model = _model(9, 0.3, MERGE_RADIUS=0.8)  # a radius of more than a cell: chains of peaks conflict
    frames = _frames(empty=False)
    with torch.no_grad():
        one = padded_counting(model, _padded(frames), max_peaks=1536, merge_iterations=1, exact_otsu=True)
        out = padded_counting(model, _padded(frames), max_peaks=1536, merge_iterations=64, exact_otsu=True)
    assert not out["unmerged"].any()
    assert one["unmerged"].any(), "the case must hold a chain longer than one round settles"
    for b, f in enumerate(frames):
        _assert_same(out, b, _predict(model, f), f"frame {b}")
    # and the merged rows against merge_centres on the same peaks
    k = int(out["num_centres"][0])
    assert k > 0 and torch.equal(merge_centres(out["centres"][0, :k], 0.8), out["centres"][0, :k])


def test_bad_intensity_is_flagged_for_its_frame_only():
    from lidarops.models.cuda_graph import padded_counting

    model = _model()
    buffer = _padded(_frames())
    buffer[1, 3, 3] = math.inf
    with torch.no_grad():
        out = padded_counting(model, buffer, max_peaks=1536)
    assert out["bad"].tolist() == [False, True, False, False, False]


def test_device_otsu_gives_the_same_counts_here():
    """The graph's Otsu (exact=False) against the eager call's (exact=True): the same on these heatmaps, which
    hold no tie within rounding."""
    from lidarops.models.cuda_graph import padded_counting

    model = _model(4, 0.2)
    with torch.no_grad():
        exact = padded_counting(model, _padded(_frames()), max_peaks=1536, exact_otsu=True)
        fast = padded_counting(model, _padded(_frames()), max_peaks=1536)
    assert torch.equal(exact["counts"], fast["counts"]) and torch.equal(exact["centres"], fast["centres"])


def test_inference_copy_folds_batchnorm_and_leaves_the_model_alone():
    """BatchNorm after a (transposed) convolution folds into it and the count head reads the backbone's maps by
    parts: the copy's heatmaps equal the model's (float64 to 1e-10), its convolutions are channels-last, the model
    keeps its modules and weights."""
    from lidarops.models.cuda_graph import inference_copy, padded_counting

    model = _model(4, 0.2).double()
    with torch.no_grad():  # BatchNorm statistics away from (0, 1), so that folding them is seen
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = inference_copy(model)
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())
    # the count head's first convolution reads the upsampled maps one by one
    assert not isinstance(fast.count_head.shared_conv[0], torch.nn.Conv2d)
    bns = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns and not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    convs = [m for m in fast.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    assert all(c.weight.is_contiguous(memory_format=torch.channels_last) for c in convs)
    buffer = _padded(_frames(empty=False)).double()
    with torch.no_grad():
        a = padded_counting(model, buffer, max_peaks=1536, exact_otsu=True)
        b = padded_counting(fast, buffer, max_peaks=1536, exact_otsu=True)
        ha = model({"points": F.pad(_frames()[0].double(), (1, 0)), "batch_size": 1})["heatmaps"]
        hb = fast({"points": F.pad(_frames()[0].double(), (1, 0)), "batch_size": 1})["heatmaps"]
    assert all(torch.allclose(x, y, rtol=0, atol=1e-10) for x, y in zip(ha, hb))
    assert torch.equal(a["counts"], b["counts"]) and int(a["counts"].sum()) > 0
    with pytest.raises(TypeError, match="model"):
        inference_copy("a model")


@pytest.mark.parametrize("kwargs, match", [
    ({"max_peaks": 0}, "max_peaks"), ({"max_peaks": True}, "max_peaks"), ({"merge_iterations": 0}, "merge_iterations"),
    ({"exact_otsu": 1}, "exact_otsu"), ({"max_pillars": 0}, "max_pillars")])
def test_bad_arguments_name_themselves(kwargs, match):
    from lidarops.models.cuda_graph import padded_counting

    with pytest.raises(ValueError, match=match):
        padded_counting(_model(), _padded(_frames()), **kwargs)


def test_bad_points_and_models_are_refused():
    from lidarops.models.cuda_graph import padded_counting
    from lidarops.models.pointpillars import PointPillars

    model = _model()
    with pytest.raises(ValueError, match="points"):
        padded_counting(model, torch.zeros(5, 4))
    with pytest.raises(ValueError, match="points"):
        padded_counting(model, torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match="CounterNet"):
        padded_counting(PointPillars(), _padded(_frames()))
    cfg = _tiny_cfg()
    cfg["MODEL"]["BACKBONE_2D"]["MODE"] = "sparse"
    with pytest.raises(ValueError, match="dense"):
        padded_counting(CounterNet(cfg).eval(), _padded(_frames()))


def test_graphed_counternet_needs_cuda():
    from lidarops.models.cuda_graph import GraphedCounterNet

    with pytest.raises(TypeError, match="CounterNet"):
        GraphedCounterNet(torch.nn.Linear(2, 2))
    with pytest.raises(ValueError, match="optimize"):
        GraphedCounterNet(_model(), optimize=1)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            GraphedCounterNet(_model())


@pytest.mark.skipif(not (torch.cuda.is_available() and lidarops.extension.cuda_available()),
                    reason="needs a GPU and lidarops built with CUDA kernels")
@pytest.mark.parametrize("partitions, delta", [(1, 0.0), (4, 0.2)])
def test_graphed_counternet_equals_the_body_and_predict(partitions, delta):
    from lidarops.models.cuda_graph import GraphedCounterNet, padded_counting, precision_mode

    model = _model(partitions, delta).cuda()
    frames = [f.cuda() for f in _frames(empty=delta == 0)]
    graphed = GraphedCounterNet(model, capacity=1000, batch_size=3, max_peaks=1536)
    for group in (frames[:3], frames[3:], frames[1:2]):  # smaller and larger frames after each other: padding restored
        got = graphed(group)
        with torch.no_grad():
            body = padded_counting(model, _padded(group), max_peaks=1536, exact_otsu=True)
        for b, f in enumerate(group):
            with precision_mode("fp32"):  # the graph's arithmetic: no TF32
                want = _predict(model, f)
            assert got[b]["counts"].tolist() == want["counts"].tolist() == body["counts"][b].tolist()
            assert torch.allclose(got[b]["centres"], want["centres"], atol=1e-6)
            assert torch.allclose(got[b]["features"], want["features"], atol=1e-5)
    with precision_mode("fp32"):
        wants = [_predict(model, f) for f in frames]
    one = graphed(frames[0])
    assert one["counts"].tolist() == wants[0]["counts"].tolist()
    # too few peak rows: the replay is redone eagerly
    few = GraphedCounterNet(model, capacity=1000, batch_size=2, max_peaks=2)
    for b, got in enumerate(few(frames[:2])):
        assert got["counts"].tolist() == wants[b]["counts"].tolist()
    # the folded, channels-last copy: the same counts here, the model untouched
    fast = GraphedCounterNet(model, capacity=1000, batch_size=len(frames), max_peaks=1536, optimize=True)
    assert [d["counts"].tolist() for d in fast(frames)] == [w["counts"].tolist() for w in wants]
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    bad = frames[0].clone()
    bad[0, 3] = math.inf
    with pytest.raises(ValueError, match="intensity"):
        graphed([bad])
    with pytest.raises(ValueError, match="capacity"):
        graphed(torch.zeros(1001, 4, device="cuda"))
