"""Fuzz: the model floor's entry points: PointPillars configs, checkpoints and the detector's batch dict.

- **configs**: one field of a small valid config replaced by a drawn value (NaN, infinities, bools where
  numbers go, floats where ints go, strings, values on and beyond each documented bound). The oracle is the
  policy docs/detector.md states, written out again here as a table: the config is refused with a
  ``ConfigError`` naming the OpenPCDet key exactly when the table says the value is out of its range;
  otherwise it builds, and a model built from it turns a small cloud into finite boxes.
- **checkpoints**: a small model's checkpoint damaged one way (a NaN or inf in one tensor, a tensor of
  another shape, a key dropped or added, another model class, a broken config, truncated bytes):
  :func:`lidarops.models.load_model` refuses it with a ``ValueError`` naming the file and the tensor or
  key, and an undamaged one loads to the same weights.
- **batch dicts**: ``points`` and ``batch_size`` drawn (frame indices that are negative, fractional, beyond
  the batch, missing frames, huge batch sizes, wrong dtypes and shapes, empty): ``predict`` refuses with a
  ``ValueError`` naming ``batch_size`` or ``points``, or returns one result per frame with finite boxes,
  before allocating anything the size of the batch size.
- **the graphs' decoding**: ``safe_regression`` on drawn anchors vouches only for boxes the box ops accept, and the
  head's decoding of drawn rows of the anchors is those rows of decoding them all, bit for bit.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from lidarops.checkpoint import format_fields, model_fields, save_checkpoint
from lidarops.config import ConfigError
from lidarops.models import PointPillars, PointPillarsConfig, load_model

from helpers.models import TINY

from .fuzzing import assert_clear_error, fuzz, outcome

# field -> (OpenPCDet key, kind, low, high, low open, high open): the policy of docs/detector.md
_SCALARS = {
    "score_thresh": ("SCORE_THRESH", "real", 0.0, 1.0, False, True),
    "nms_thresh": ("NMS_THRESH", "real", 0.0, 1.0, False, False),
    "nms_pre_maxsize": ("NMS_PRE_MAXSIZE", "int", -1, 2**31 - 1, False, False),
    "nms_post_maxsize": ("NMS_POST_MAXSIZE", "int", -1, 2**31 - 1, False, False),
    "dir_offset": ("DIR_OFFSET", "real", -2 * math.pi, 2 * math.pi, False, False),
    "dir_limit_offset": ("DIR_LIMIT_OFFSET", "real", 0.0, 1.0, False, False),
    "cls_weight": ("cls_weight", "real", 0.0, None, False, False),
    "loc_weight": ("loc_weight", "real", 0.0, None, False, False),
    "dir_weight": ("dir_weight", "real", 0.0, None, False, False),
    "max_points_per_voxel": ("MAX_POINTS_PER_VOXEL", "int", 1, 2**31 - 1, False, False),
    "max_voxels_test": ("MAX_NUMBER_OF_VOXELS.test", "int", 1, 2**31 - 1, False, False),
    "max_voxels_train": ("MAX_NUMBER_OF_VOXELS.train", "int", 1, 2**31 - 1, False, False),
    "use_norm": ("USE_NORM", "bool", None, None, False, False),
    "with_distance": ("WITH_DISTANCE", "bool", None, None, False, False),
    "multi_classes_nms": ("MULTI_CLASSES_NMS", "bool", None, None, False, False),
}
# cheap to run: the fields a built model is run with (the others only change training or the network's size)
_RUN = {"score_thresh", "nms_thresh", "nms_pre_maxsize", "nms_post_maxsize", "dir_offset", "dir_limit_offset",
        "max_points_per_voxel", "max_voxels_test", "use_norm", "with_distance", "multi_classes_nms"}


def _valid(value, kind, lo, hi, lo_open, hi_open) -> bool:
    """The policy, independently of lidarops' checks: bools are not numbers, floats are not ints."""
    if kind == "bool":
        return type(value) is bool
    if type(value) is bool or not isinstance(value, (int, float)):
        return False
    if kind == "int" and not isinstance(value, int):
        return False
    if not math.isfinite(value):
        return False
    if lo is not None and (value <= lo if lo_open else value < lo):
        return False
    return hi is None or (value < hi if hi_open else value <= hi)


def _values(kind, lo, hi) -> st.SearchStrategy:
    edges = [v for b in (lo, hi) if b is not None for v in (b, b - 1e-9, b + 1e-9, b - 1, b + 1)]
    if kind == "int" and lo is not None:
        edges += [int(lo), int(lo) - 1, int(lo) + 1, int(lo) + 3]
    return st.one_of(
        st.sampled_from([math.nan, math.inf, -math.inf, True, False, "0.5", None, [0.5], 2**63, -2**63]),
        st.sampled_from(edges or [0, 1]),
        st.floats(-10, 10, allow_nan=False), st.integers(-5, 600),
    )


@pytest.fixture(scope="module")
def cloud():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0.0, -4.0, -3.0, 0.0])
    return torch.cat([torch.zeros(300, 1), pts], 1)


@fuzz
@given(data=st.data())
def test_config_values_follow_the_documented_policy(cloud, data):
    field = data.draw(st.sampled_from(sorted(_SCALARS)), "field")
    key, kind, lo, hi, lo_open, hi_open = _SCALARS[field]
    value = data.draw(_values(kind, lo, hi), "value")
    cfg, err = outcome(PointPillarsConfig, **{**TINY, field: value})
    if not _valid(value, kind, lo, hi, lo_open, hi_open):
        assert isinstance(err, ConfigError), f"{field}={value!r} was accepted ({err!r})"
        assert_clear_error(err, (ConfigError,), [key], f"PointPillarsConfig({field}={value!r})")
        return
    assert err is None, f"{field}={value!r} is within the policy but was refused: {err}"
    if field in _RUN and not (kind == "int" and value > 4096):  # not the memory of 2^31 voxels
        torch.manual_seed(0)
        model = PointPillars(cfg).eval()
        with torch.no_grad():
            out = model.predict({"points": cloud, "batch_size": 1})
        assert len(out) == 1 and torch.isfinite(out[0]["boxes"]).all()


# ---------------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_checkpoint():
    torch.manual_seed(0)
    model = PointPillars(TINY).eval()
    return {**format_fields(), **model_fields(model), "model_state": dict(model.state_dict())}


def _damaged(draw, ckpt: dict) -> tuple[dict | bytes, list[str]]:
    """A copy of ``ckpt`` damaged one way, and what the error must name (besides the file)."""
    state = {k: v.clone() for k, v in ckpt["model_state"].items()}
    ckpt = {**ckpt, "model_state": state}
    floats = sorted(k for k, v in state.items() if v.is_floating_point())
    how = draw(st.sampled_from(["none", "non-finite", "shape", "drop", "extra", "class", "config", "names",
                                "truncate", "not a dict"]), "damage")
    if how == "none":
        return ckpt, []
    if how == "non-finite":
        key = draw(st.sampled_from(floats), "tensor")
        flat = state[key].view(-1)
        flat[draw(st.integers(0, flat.numel() - 1), "index")] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        return ckpt, [key]
    if how == "shape":
        key = draw(st.sampled_from(floats), "tensor")
        state[key] = torch.zeros(state[key].numel() + 1)
        return ckpt, [key]
    if how == "drop":
        key = draw(st.sampled_from(sorted(state)), "tensor")
        del state[key]
        return ckpt, [key]
    if how == "extra":
        state["dense_head.conv_extra.weight"] = torch.zeros(3)
        return ckpt, ["dense_head.conv_extra.weight"]
    if how == "class":
        name = draw(st.sampled_from(["CounterNet3000", "", "pointpillars"]), "class")
        return {**ckpt, "model_class": name}, ["model_class" if not name else name]
    if how == "config":
        field, value = draw(st.sampled_from([("score_thresh", math.nan), ("voxel_size", [1.0, -1.0, 4.0]),
                                             ("num_filters", "eight")]), "config field")
        return {**ckpt, "model_config": {**ckpt["model_config"], field: value}}, [field.upper()]
    if how == "names":
        return {**ckpt, "class_names": "Car"}, ["class_names"]
    if how == "not a dict":
        return [1, 2, 3], []
    return b"", []  # truncate: filled in by the caller


@fuzz
@given(data=st.data())
def test_damaged_checkpoints_are_refused_by_name(tmp_path_factory, tiny_checkpoint, data):
    path = tmp_path_factory.mktemp("ckpt") / "model.pth"
    ckpt, names = _damaged(data.draw, tiny_checkpoint)
    if isinstance(ckpt, bytes):
        save_checkpoint(tiny_checkpoint, path)
        raw = path.read_bytes()
        path.write_bytes(raw[:data.draw(st.integers(0, len(raw) - 1), "cut")])
    elif isinstance(ckpt, list):
        torch.save(ckpt, path)
    else:
        save_checkpoint(ckpt, path)
    model, err = outcome(load_model, path)
    if ckpt is tiny_checkpoint or (isinstance(ckpt, dict) and not names):
        assert err is None, f"an undamaged checkpoint was refused: {err}"
        for k, v in model.state_dict().items():
            assert torch.equal(v, tiny_checkpoint["model_state"][k]), k
        return
    assert err is not None, f"a damaged checkpoint loaded ({names})"
    assert_clear_error(err, (ValueError,), names or [str(path)], f"load_model({names})")
    assert str(path) in str(err), f"the error does not name the file: {err}"


# ---------------------------------------------------------------------------------------------
# the batch dict
# ---------------------------------------------------------------------------------------------
def _tiny_counternet():
    from lidarops.models.config import PointPillarsConfig
    from lidarops.models.counternet import CounterNet, CounterNetConfig

    return CounterNet(CounterNetConfig(floor=PointPillarsConfig(**TINY).to_dict(), shared_channels=4,
                                       head_channels=4, partitions=4, delta=0.2))


def _tiny_casnet_pointpillars():
    from lidarops.models.casnet_pointpillars import CASNetPointPillars, CASNetPointPillarsConfig
    from lidarops.models.config import PointPillarsConfig

    return CASNetPointPillars(CASNetPointPillarsConfig(ratio=2, segment_points=16, k=4, radius=1.0,
                                                       task_checkpoint=None,
                                                       task=PointPillarsConfig(**TINY).to_dict()))


# every model that reads OpenPCDet's batch (points with the frame index first, batch_size)
_BATCH_MODELS = {"PointPillars": lambda: PointPillars(TINY), "CounterNet": _tiny_counternet,
                 "CASNetPointPillars": _tiny_casnet_pointpillars}


@pytest.fixture(scope="module", params=sorted(_BATCH_MODELS))
def tiny_model(request):
    torch.manual_seed(0)
    return _BATCH_MODELS[request.param]().eval()


@fuzz
@given(data=st.data())
def test_batch_dicts_give_one_result_per_frame_or_name_the_key(tiny_model, data):
    n = data.draw(st.integers(0, 40), "points")
    batch_size = data.draw(st.one_of(st.integers(-2, 5), st.sampled_from([10_000, 2**24, 2**40, 2**63 - 1]),
                                     st.sampled_from([1.0, True, "2", None, torch.tensor(2), torch.tensor([1, 1])])),
                           "batch_size")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 100), "seed"))
    xyz = torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0.0, -4.0, -3.0, 0.0])
    frames = data.draw(st.lists(st.integers(-1, 5), min_size=n, max_size=n), "frame of each point")
    idx = torch.tensor(frames, dtype=torch.float32).reshape(-1, 1)
    if data.draw(st.booleans(), "fractional index"):
        idx = idx + 0.5
    points = torch.cat([idx, xyz], 1)
    points = data.draw(st.sampled_from([points, points.double(), points[:, :4], points.half(), points.long()]),
                       "points dtype/shape")
    batch = {"points": points, "batch_size": batch_size}
    with torch.no_grad():
        out, err = outcome(tiny_model.predict, batch)
    # an int, or a 0-d integer tensor (as a NumPy int is taken); not a bool, a float or a string
    size = batch_size if type(batch_size) is int else int(batch_size) if isinstance(batch_size, torch.Tensor) \
        and batch_size.dim() == 0 and not batch_size.is_floating_point() and batch_size.dtype != torch.bool else None
    ok_size = size is not None and 1 <= size
    # any floating dtype (cast to the weights'), frame index and x, y, z, intensity
    ok_points = points.is_floating_point() and points.shape[1] == 5
    if n == 0:  # an empty scan is a batch of its own
        frames_ok = ok_points and size == 1
    else:  # every point in a frame of the batch, every frame with a point
        frames_ok = ok_points and ok_size and size <= n and bool((idx.frac() == 0).all()) \
            and set(frames) == set(range(size))
    if not frames_ok:
        assert err is not None, f"batch_size={batch_size!r}, frames {sorted(set(frames))}: accepted"
        assert_clear_error(err, (ValueError, TypeError), ["batch_size", "points"], f"predict(batch_size={batch_size!r})")
        return
    assert err is None, f"a valid batch was refused: {err}"
    assert len(out) == size
    for o in out:  # a detector's boxes, or a counter's counts
        assert torch.isfinite(o["boxes"]).all() if "boxes" in o else bool((o["counts"] >= 0).all())


@pytest.fixture(scope="module")
def cuda_pointpillars():
    import lidarops

    if not (torch.cuda.is_available() and lidarops.extension.cuda_available()):
        pytest.skip("needs a GPU and lidarops built with CUDA kernels")
    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3}).cuda().eval()
    with torch.no_grad():  # scores around 0.5, so that boxes pass the threshold
        model.dense_head.conv_cls.bias.zero_()
    return model


def _predict_batch(data) -> dict:
    """A drawn CPU batch for predict: ragged frames of TINY's range, maybe one bad value (a frame index or an
    intensity: NaN, inf, huge, fractional, negative, past the batch), float32, float64 or float16."""
    n = data.draw(st.integers(0, 300), "points")
    batch_size = data.draw(st.integers(1, 3), "batch_size")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 100), "seed"))
    xyz = torch.rand(n, 4, generator=g) * torch.tensor([8.0, 8.0, 4.0, 1.0]) + torch.tensor([0.0, -4.0, -3.0, 0.0])
    frame = torch.randint(0, batch_size, (n, 1), generator=g).float()
    points = torch.cat([frame, xyz], 1)
    if n and data.draw(st.booleans(), "a bad value"):
        row, col = data.draw(st.integers(0, n - 1), "row"), data.draw(st.sampled_from([0, 4]), "column")
        points[row, col] = data.draw(st.sampled_from([float("nan"), float("inf"), 1e9, 0.5, -1.0, 7.0]), "value")
    points = data.draw(st.sampled_from([points, points.double(), points.half()]), "dtype")
    return {"points": points, "batch_size": batch_size}


@fuzz
@given(data=st.data())
def test_cuda_predict_replayed_is_the_eager_call(cuda_pointpillars, data):
    """predict on CUDA batches (ragged frames, bad frame indices, fractional ones, other dtypes, bad intensities),
    called until it replays a graph: the eager call's detections, or its error word for word."""
    from lidarops.models import cuda_graph
    from lidarops.models.pointpillars import eager_predict

    model = cuda_pointpillars
    batch = _predict_batch(data)
    batch["points"] = batch["points"].cuda()
    with eager_predict():
        want, want_err = outcome(model.predict, batch)
    keep, recorded = cuda_graph.KEEP_GRAPHS, cuda_graph.MAX_RECORDINGS
    cuda_graph.KEEP_GRAPHS, cuda_graph.MAX_RECORDINGS = 8, 10**6  # every size keeps its graph here
    try:
        for _ in range(2):
            got, err = outcome(model.predict, batch)
    finally:
        cuda_graph.KEEP_GRAPHS, cuda_graph.MAX_RECORDINGS = keep, recorded
    if want_err is not None:
        assert err is not None and type(err) is type(want_err) and str(err) == str(want_err), \
            f"eager: {want_err!r}; replayed: {err!r}"
        return
    assert err is None, f"the eager call accepted the batch, the replay refused it: {err!r}"
    assert len(got) == len(want)
    for d, w in zip(got, want):
        assert d["labels"].tolist() == w["labels"].tolist()
        assert torch.allclose(d["scores"].double(), w["scores"].double(), atol=1e-5)
        assert torch.allclose(d["boxes"].double(), w["boxes"].double(), atol=1e-4)


@pytest.fixture(scope="module")
def cpu_pointpillars():
    from helpers.models import randomize_bn

    torch.manual_seed(0)
    model = PointPillars({**TINY, "score_thresh": 0.3})
    randomize_bn(model.backbone_2d, 3)  # what the inference copy folds
    with torch.no_grad():  # scores around 0.5, so that boxes pass the threshold
        model.dense_head.conv_cls.bias.zero_()
    return model.eval()


@fuzz
@given(data=st.data())
def test_cpu_predict_through_the_inference_copy_is_the_eager_call(cpu_pointpillars, data):
    """predict on CPU batches (ragged frames, bad frame indices, fractional ones, other dtypes, bad values) runs
    the model's inference copy: the eager call's detections up to rounding, or its error word for word; the eager
    call's detections are those of decoding every anchor."""
    from lidarops.models.pointpillars import eager_predict
    from lidarops.models.postprocess import postprocess

    model = cpu_pointpillars
    batch = _predict_batch(data)
    with eager_predict():
        want, want_err = outcome(model.predict, batch)
    got, err = outcome(model.predict, batch)
    if want_err is not None:
        assert err is not None and type(err) is type(want_err) and str(err) == str(want_err), \
            f"eager: {want_err!r}; inference copy: {err!r}"
        return
    assert err is None, f"the eager call accepted the batch, the inference copy refused it: {err!r}"
    with torch.no_grad():
        whole = postprocess(*model.dense_head.decode(model(batch)), model.config)
    assert len(got) == len(want) == len(whole)
    for d, w, h in zip(got, want, whole):
        assert w["labels"].tolist() == h["labels"].tolist() and torch.equal(w["scores"], h["scores"])
        assert torch.equal(w["boxes"], h["boxes"])
        assert d["labels"].tolist() == w["labels"].tolist()
        assert torch.allclose(d["scores"].double(), w["scores"].double(), atol=1e-5)
        assert torch.allclose(d["boxes"].double(), w["boxes"].double(), atol=1e-4)


@fuzz
@given(data=st.data())
def test_padded_inference_gives_each_frame_or_names_the_argument(data):
    """:func:`lidarops.models.cuda_graph.padded_inference` on drawn padded batches (ragged frames, empty
    ones, wrong ranks, too few columns, integer points, zero frames, bad ``max_pillars``): a ``ValueError``
    naming ``points``, ``max_pillars`` or ``model``, or one frame per row with each frame's predict."""
    from torch.nn import functional as F

    from lidarops.models.cuda_graph import padded_inference

    shape = data.draw(st.sampled_from([(2, 30, 4), (1, 0, 4), (3, 12, 5), (0, 5, 4), (2, 5, 3), (30, 4), (2, 3, 4, 1)]),
                      label="shape")
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64, torch.int32]), label="dtype")
    rows = data.draw(st.sampled_from([None, None, 1, 64, 0, -3, 2.5, True]), label="max_pillars")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 99), label="seed"))
    pts = (torch.rand(shape, generator=g) * 8 - torch.tensor([0.0, 4, 3, 0, 0][:shape[-1]] if shape[-1] <= 5
                                                                else 0)).to(dtype)
    tiny_model = _tiny_pointpillars()
    model = data.draw(st.sampled_from([tiny_model, tiny_model, "a model"]), label="model")
    with torch.no_grad():
        out, err = outcome(padded_inference, model, pts, rows)
    if err is not None:
        assert_clear_error(err, (ValueError,), ["points", "max_pillars", "model"],
                           f"padded_inference({shape}, {dtype}, max_pillars={rows!r})")
        return
    assert len(shape) == 3 and shape[0] >= 1 and shape[2] >= 4 and dtype.is_floating_point
    assert out["count"].shape == (shape[0],)
    if bool(out["overflow"]):
        return  # too few rows: flagged (GraphedPointPillars then runs predict)
    for b in range(shape[0]):
        want = tiny_model.predict({"points": F.pad(pts[b, :, :4], (1, 0)), "batch_size": 1})[0]
        k = int(out["count"][b])
        assert out["labels"][b, :k].tolist() == want["labels"].tolist()
        assert torch.allclose(out["scores"][b, :k].double(), want["scores"].double(), atol=1e-5)


@fuzz
@given(data=st.data())
def test_padded_counting_gives_each_frame_or_names_the_argument(data):
    """:func:`lidarops.models.cuda_graph.padded_counting` on drawn padded batches (ragged frames, empty ones, wrong
    ranks, too few columns, integer points, bad ``max_pillars`` / ``max_peaks`` / ``merge_iterations`` /
    ``exact_otsu``, a model that is no CounterNet): a ``ValueError`` naming the argument, or each frame's predict
    (unless a flag says the rows were too few or the merge unsettled)."""
    from torch.nn import functional as F

    from lidarops.models.cuda_graph import padded_counting

    shape = data.draw(st.sampled_from([(2, 30, 4), (1, 0, 4), (3, 12, 5), (0, 5, 4), (2, 5, 3), (30, 4)]), label="shape")
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64, torch.int32]), label="dtype")
    kwargs = {"max_pillars": data.draw(st.sampled_from([None, None, 1, 64, 0, 2.5]), label="max_pillars"),
              "max_peaks": data.draw(st.sampled_from([1024, 1024, 1, 0, -2, True]), label="max_peaks"),
              "merge_iterations": data.draw(st.sampled_from([16, 16, 1, 0]), label="merge_iterations"),
              "exact_otsu": data.draw(st.sampled_from([True, True, False, 1]), label="exact_otsu")}
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 99), label="seed"))
    pts = (torch.rand(shape, generator=g) * 8 - torch.tensor([0.0, 4, 3, 0, 0][:shape[-1]] if shape[-1] <= 5
                                                            else 0)).to(dtype)
    torch.manual_seed(0)
    tiny = _tiny_counternet().eval()
    model = data.draw(st.sampled_from([tiny, tiny, _tiny_pointpillars()]), label="model")
    with torch.no_grad():
        out, err = outcome(padded_counting, model, pts, **kwargs)
    if err is not None:
        assert_clear_error(err, (ValueError,), ["points", "max_pillars", "max_peaks", "merge_iterations",
                                                "exact_otsu", "model"], f"padded_counting({shape}, {dtype}, {kwargs})")
        return
    assert len(shape) == 3 and shape[0] >= 1 and shape[2] >= 4 and dtype.is_floating_point
    assert out["counts"].shape == (shape[0], tiny.config.num_classes)
    if bool(out["overflow"]) or not kwargs["exact_otsu"]:
        return
    for b in range(shape[0]):
        if out["peak_overflow"][b] or out["unmerged"][b]:
            continue
        want = tiny.predict({"points": F.pad(pts[b, :, :4], (1, 0)), "batch_size": 1})[0]
        assert out["counts"][b].tolist() == want["counts"].tolist()


def _tiny_pointpillars():
    torch.manual_seed(0)
    return PointPillars(TINY).eval()


@pytest.fixture(scope="module")
def selection_file(tmp_path_factory):
    """A saved SelectedCounter of two tiny CounterNets (one model needs no selector) and a PointPillars file."""
    from lidarops.models.counternet_selection import SelectedCounter

    root = tmp_path_factory.mktemp("selection")
    paths = []
    for i in range(2):
        m = _tiny_counternet().eval()
        paths.append(root / f"cn{i}.pth")
        save_checkpoint({**format_fields(), **model_fields(m), "model_state": m.state_dict()}, [paths[-1]])
    pp = PointPillars(TINY)
    save_checkpoint({**format_fields(), **model_fields(pp), "model_state": pp.state_dict()}, [root / "pp.pth"])
    SelectedCounter([_tiny_counternet()]).save(root / "one.pth", [paths[0]])
    return root


@fuzz
@given(data=st.data())
def test_damaged_selection_files_are_refused_by_name(selection_file, data):
    """A SelectedCounter file damaged one way (members missing, empty, naming a missing file or a detector; another
    model_class; truncated bytes) is refused by load_model with a ValueError naming the file; an undamaged one
    loads."""
    from lidarops.checkpoint import read_checkpoint

    good = read_checkpoint(selection_file / "one.pth")
    kind = data.draw(st.sampled_from(["none", "no_members", "empty", "missing", "detector", "class", "truncated"]))
    path = selection_file / f"damaged_{kind}.pth"
    ckpt = {**good, "model_config": dict(good["model_config"])}
    if kind == "no_members":
        del ckpt["model_config"]["members"]
    elif kind == "empty":
        ckpt["model_config"]["members"] = []
    elif kind == "missing":
        ckpt["model_config"]["members"] = ["not_there.pth"]
    elif kind == "detector":
        ckpt["model_config"]["members"] = ["pp.pth"]
    elif kind == "class":
        ckpt["model_class"] = data.draw(st.sampled_from(["SelectedCounters", "PointPillars"]))
    save_checkpoint(ckpt, [path])
    if kind == "truncated":
        raw = path.read_bytes()
        path.write_bytes(raw[:data.draw(st.integers(0, len(raw) - 1))])
    model, err = outcome(load_model, path)
    if kind == "none":
        assert err is None and type(model).__name__ == "SelectedCounter", err
        return
    assert_clear_error(err, (ValueError, FileNotFoundError), [str(path), path.name], f"load_model({kind})")


@fuzz
@given(data=st.data())
def test_safe_regression_vouches_for_every_box_within_it(data):
    """:func:`lidarops.models.anchor_head.safe_regression` on drawn anchors (sizes from 0.1 mm to 50 km, centres up
    to 600 km away): an integer in [0, 10]; every box decoded from regressions within it (the corners of the cube
    and drawn points inside; headings through the direction bins) is one the box ops accept; a size of 0 or below,
    a NaN or an infinity gives 0."""
    import itertools

    from lidarops.models.anchor_head import safe_regression
    from lidarops.models.anchors import ResidualCoder, decode_direction
    from lidarops.ops.boxes import unsupported_boxes

    n = data.draw(st.integers(1, 5), label="anchors")
    size = st.floats(1e-4, 5e4)
    anchors = torch.tensor([[data.draw(st.floats(-6e5, 6e5), label="x"), data.draw(st.floats(-100, 100), label="y"),
                             data.draw(st.floats(-5, 5), label="z"), data.draw(size, label="dx"),
                             data.draw(size, label="dy"), data.draw(size, label="dz"),
                             data.draw(st.floats(-math.pi, math.pi), label="heading")] for _ in range(n)])
    bound = safe_regression(anchors)
    assert 0 <= bound <= 10 and bound == int(bound)
    if bound:
        corners = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=7)))
        g = torch.Generator().manual_seed(data.draw(st.integers(0, 99), label="seed"))
        deltas = torch.cat([corners, torch.rand(64, 7, generator=g) * 2 - 1]) * bound
        boxes = ResidualCoder(7).decode(deltas[:, None, :].expand(-1, n, -1), anchors[None])
        for label in (0, 1):
            boxes[..., 6] = decode_direction(boxes[..., 6], torch.full(boxes.shape[:2], label))
            assert not unsupported_boxes(boxes.reshape(-1, 7)).any(), f"bound {bound} for {anchors.tolist()}"
    bad = anchors.clone()
    bad[data.draw(st.integers(0, n - 1), label="row"), data.draw(st.integers(3, 5), label="column")] = \
        data.draw(st.sampled_from([0.0, -1.0, math.nan, math.inf]), label="bad size")
    assert safe_regression(bad) == 0


@fuzz
@given(data=st.data())
def test_head_decode_of_some_anchors_is_those_rows_of_the_whole(data):
    """``AnchorHeadSingle.decode(preds, anchors)`` on drawn rows of the anchors (repeated, any order) and drawn raw
    outputs (large, tiny, negative): bit for bit the rows of decoding every anchor (NaN where it gives NaN)."""
    model = _tiny_pointpillars()
    head = model.dense_head
    A, C, code = head.anchors_flat.shape[0], head.num_class, head.box_coder.code_size
    B = data.draw(st.integers(1, 2), label="frames")
    scale = data.draw(st.sampled_from([1e-3, 1.0, 30.0, 100.0]), label="scale")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 99), label="seed"))
    preds = {"cls_preds": torch.randn(B, A * C, generator=g) * scale,
             "box_preds": torch.randn(B, A * code, generator=g) * scale,
             "dir_cls_preds": torch.randn(B, A * 2, generator=g)}
    idx = torch.tensor(data.draw(st.lists(st.lists(st.integers(0, A - 1), min_size=3, max_size=3), min_size=B,
                                          max_size=B), label="rows"))
    with torch.no_grad():
        cls, boxes = head.decode(preds)
        rows = lambda t, w: torch.gather(t.view(B, A, w), 1, idx[..., None].expand(-1, -1, w))  # noqa: E731
        picked = {"cls_preds": rows(preds["cls_preds"], C), "box_preds": rows(preds["box_preds"], code),
                  "dir_cls_preds": rows(preds["dir_cls_preds"], 2)}
        cls_c, boxes_c = head.decode(picked, head.anchors_flat[idx])
    torch.testing.assert_close(cls_c, rows(cls, C), rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(boxes_c, rows(boxes, 7), rtol=0, atol=0, equal_nan=True)
