"""Fuzz: the classification side of CAS-Net's experiments: PointNet's batch dict and config, and the object-set
Dataset's arguments and resampling.

- **batch dicts**: ``points`` (any rank, dtype, size, NaN and infinities) and ``labels`` (any shape, dtype and
  value) drawn, in training and eval mode. The oracle, written out here independently of lidarops' checks:
  the batch is refused with a ``ValueError`` naming ``batch['points']`` (checked first) or ``batch['labels']``
  exactly when the documented contract says so; otherwise the model returns a finite scalar loss (training)
  or finite ``(B, K)`` logits (eval).
- **configs**: one field of a valid :class:`PointNetConfig` replaced by a drawn value: a ``ConfigError``
  naming the YAML key exactly when the policy table says the value is out of range, else a model that runs.
- **datasets**: the Dataset's arguments drawn: a ``ValueError`` naming the argument, or items of exactly
  ``(num_points, in_channels)`` finite float32 values; :func:`resample` of any cloud gives exactly
  ``num_points`` of its rows, each of them when there are not more.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from lidarops.config import ConfigError
from lidarops.data.object_sets import NORMALIZE_MODES, Augmentation, ObjectClassificationDataset, resample
from lidarops.models.pointnet import PointNet, PointNetConfig

from .fuzzing import assert_clear_error, assert_no_error, fuzz, outcome
from .test_fuzz_models import _valid  # the config policy, stated once

# small tensors: one intra-op thread (OpenMP wake-ups on a shared machine cost more than the work)
pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(class_names=["a", "b", "c"], mlp=[8, 8, 8, 16, 32], fc=[16, 8])
K = 3


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return PointNet(PointNetConfig(**SMALL))


# ---------------------------------------------------------------------------------------------------- batches
@st.composite
def batches(draw):
    rank = draw(st.sampled_from([3, 3, 3, 3, 2, 4]), "rank")
    shape = [draw(st.integers(0, 5), f"dim{i}") for i in range(rank)]
    if rank == 3 and draw(st.booleans(), "enough columns"):
        shape[2] = draw(st.integers(3, 5), "columns")
    dtype = draw(st.sampled_from([torch.float32, torch.float32, torch.float64, torch.float16, torch.int64,
                                  torch.bool]), "points dtype")
    values = torch.from_numpy(np.asarray(draw(st.lists(st.floats(-1e3, 1e3, allow_nan=False, width=32),
                                                       min_size=1, max_size=1), "seed value"), np.float32))
    points = (torch.randn(shape, generator=torch.Generator().manual_seed(int(abs(values[0]) * 7) % 1000))
              * (1 + values.abs())).to(dtype)
    if dtype.is_floating_point and points.numel() and draw(st.booleans(), "poison"):
        flat = points.view(-1)
        flat[draw(st.integers(0, flat.numel() - 1), "at")] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    batch: dict = {"points": points}
    how = draw(st.sampled_from(["good", "good", "none", "shape", "float", "bool", "range", "list"]), "labels")
    b = shape[0] if rank >= 1 else 0
    if how == "good":
        batch["labels"] = torch.tensor(draw(st.lists(st.integers(0, K - 1), min_size=b, max_size=b)), dtype=torch.int64)
    elif how == "shape":
        batch["labels"] = torch.zeros(b, 1, dtype=torch.int64) if draw(st.booleans()) else torch.zeros(b + 1).long()
    elif how == "float":
        batch["labels"] = torch.zeros(b)
    elif how == "bool":
        batch["labels"] = torch.zeros(b, dtype=torch.bool)
    elif how == "range":
        bad = draw(st.sampled_from([-1, K, K + 5, -(2**40)]))
        batch["labels"] = torch.tensor([bad] + [0] * max(b - 1, 0), dtype=torch.int64)[:max(b, 1)]
    elif how == "list":
        batch["labels"] = [0] * b
    return batch


def _expected_error(batch: dict, training: bool) -> str | None:
    """The key the error must name, or None for a valid batch: the contract of PointNet's docstring (shapes and
    dtypes first, points then labels; then the values: finite points, labels in range)."""
    p = batch["points"]
    if p.dim() != 3 or not p.is_floating_point() or p.shape[0] < 1 or p.shape[1] < 1 or p.shape[2] < 3:
        return "batch['points']"
    labels = batch.get("labels")
    if training:
        if not isinstance(labels, torch.Tensor) or tuple(labels.shape) != (p.shape[0],) \
                or labels.is_floating_point() or labels.dtype == torch.bool:
            return "batch['labels']"
        if p.shape[0] < 2:
            return "batch['points']"
    if not bool(torch.isfinite(p[..., :3].float()).all()):
        return "batch['points']"
    if training and bool(((labels < 0) | (labels >= K)).any()):
        return "batch['labels']"
    return None


@fuzz
@given(batch=batches(), training=st.booleans())
def test_batches_give_a_loss_or_logits_or_name_the_key(model, batch, training):
    model.train(training)
    out, err = outcome(model, batch)
    want = _expected_error(batch, training)
    what = f"{'train' if training else 'eval'} points {tuple(batch['points'].shape)} {batch['points'].dtype}, " \
           f"labels {batch.get('labels')!r}"
    if want is not None:
        assert_clear_error(err, ValueError, [want], what)
        return
    assert_no_error(err, what)
    if training:
        assert out["loss"].shape == () and torch.isfinite(out["loss"]), what
    else:
        assert out.shape == (batch["points"].shape[0], K) and torch.isfinite(out).all(), what


# ---------------------------------------------------------------------------------------------------- configs
# field -> (YAML key, kind, lo, hi, lo open, hi open): the policy of PointNetConfig's docstring
_POLICY = {
    "in_channels": ("used_feature_list", "int", 3, 1024, False, False),
    "dropout": ("MODEL.DROPOUT", "real", 0.0, 1.0, False, True),
    "label_smoothing": ("MODEL.LABEL_SMOOTHING", "real", 0.0, 1.0, False, True),
    "feature_transform_weight": ("MODEL.FEATURE_TRANSFORM_WEIGHT", "real", 0.0, None, False, False),
    "input_transform": ("MODEL.INPUT_TRANSFORM", "bool", None, None, False, False),
}


@fuzz
@given(data=st.data())
def test_config_values_follow_the_policy(data):
    field = data.draw(st.sampled_from(sorted(_POLICY)), "field")
    key, kind, lo, hi, lo_open, hi_open = _POLICY[field]
    edges = [v for b in (lo, hi) if b is not None for v in (b, b - 1e-9, b + 1e-9, b - 1, b + 1)]
    value = data.draw(st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, True, False, "0.5", None, [0.5]]),
                                st.sampled_from(edges or [0, 1]), st.floats(-3, 3, allow_nan=False),
                                st.integers(-5, 40)), "value")
    cfg, err = outcome(PointNetConfig, **{**SMALL, field: value})
    if not _valid(value, kind, lo, hi, lo_open, hi_open):
        assert_clear_error(err, ConfigError, [key], f"PointNetConfig({field}={value!r})")
        return
    assert_no_error(err, f"PointNetConfig({field}={value!r})")
    net = PointNet(cfg).eval()
    assert torch.isfinite(net({"points": torch.randn(2, 8, cfg.in_channels)})).all()


@fuzz
@given(widths=st.lists(st.one_of(st.integers(-2, 12), st.sampled_from([True, 2.0, "8", None])), max_size=4),
       which=st.sampled_from(["mlp", "fc"]))
def test_layer_widths_are_positive_ints_or_named(widths, which):
    cfg, err = outcome(PointNetConfig, **{**SMALL, which: widths})
    ok = all(type(w) is int and w >= 1 for w in widths) and (which == "fc" or widths)
    key = "MODEL.MLP" if which == "mlp" else "MODEL.FC"
    if not ok:
        assert_clear_error(err, ConfigError, [key], f"{which}={widths!r}")
        return
    assert_no_error(err, f"{which}={widths!r}")
    logits = PointNet(cfg).eval()({"points": torch.randn(2, 5, 3)})
    assert logits.shape == (2, K)


# ---------------------------------------------------------------------------------------------------- datasets
@fuzz
@given(p=st.integers(1, 300), n=st.integers(1, 300), seed=st.integers(0, 2**32))
def test_resample_gives_exactly_n_rows_of_the_cloud(p, n, seed):
    pts = np.arange(p, dtype=np.float32)[:, None].repeat(3, 1)
    out = resample(pts, n, np.random.default_rng(seed))
    rows = out[:, 0].astype(np.int64)
    assert out.shape == (n, 3) and np.array_equal(out, pts[rows])
    if p <= n:
        assert set(rows.tolist()) == set(range(p))
    else:
        assert len(set(rows.tolist())) == n


def _clouds(sizes):
    rng = np.random.default_rng(0)
    return [rng.normal(size=(s, 4)).astype(np.float32) for s in sizes]


@fuzz
@given(num_points=st.one_of(st.integers(-2, 70), st.sampled_from([2.0, True, "64", None])),
       in_channels=st.one_of(st.integers(1, 6), st.sampled_from([3.0, False])),
       normalize=st.sampled_from([*NORMALIZE_MODES, "box", None]),
       seed=st.one_of(st.integers(-1, 2**40), st.sampled_from([0.5, "1"])),
       sizes=st.lists(st.integers(1, 90), min_size=1, max_size=4), augment=st.booleans())
def test_dataset_arguments_are_checked_by_name(num_points, in_channels, normalize, seed, sizes, augment):
    ds, err = outcome(ObjectClassificationDataset, _clouds(sizes), [0] * len(sizes), ["x"], num_points=num_points,
                      in_channels=in_channels, normalize=normalize, seed=seed,
                      augment=Augmentation() if augment else None)
    names = []
    if type(num_points) is not int or not 1 <= num_points <= 1 << 20:
        names.append("num_points")
    if type(in_channels) is not int or not 3 <= in_channels <= 1024:
        names.append("in_channels")
    if type(seed) is not int or seed < 0:
        names.append("seed")
    if normalize not in NORMALIZE_MODES:
        names.append("normalize")
    what = f"num_points={num_points!r}, in_channels={in_channels!r}, normalize={normalize!r}, seed={seed!r}"
    if names:
        assert_clear_error(err, ValueError, names, what)
        return
    if in_channels > 4:  # the clouds hold 4 columns
        assert_clear_error(err, ValueError, ["clouds[0]"], what)
        return
    assert_no_error(err, what)
    for i in range(len(ds)):
        item = ds[i]["points"]
        assert item.shape == (num_points, in_channels) and item.dtype == torch.float32 and torch.isfinite(item).all()
