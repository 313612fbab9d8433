"""Fuzz properties of ``lidarops train --set`` (lidarops.config.apply_overrides) and of the counting evaluator
(lidarops.eval.counting.CountingEvaluator): any key path and value text either changes exactly that key or is
refused with a ConfigError naming ``--set``; predictions without counts are named, never a crash."""
from __future__ import annotations

import copy

import numpy as np
from hypothesis import given, strategies as st

from lidarops.config import ConfigError, apply_overrides
from lidarops.eval.counting import CountingEvaluator

from .fuzzing import assert_clear_error, fuzz, outcome

_CFG = {"MODEL": {"RATIO": 8, "VARIANT": "full", "HEAD": {"SIZES": [1, 2]}}, "OPTIMIZATION": {"LR": 0.1}}
_KEYS = ["MODEL", "RATIO", "VARIANT", "HEAD", "SIZES", "OPTIMIZATION", "LR", "NOPE", "", "model"]
_VALUES = st.one_of(st.sampled_from(["4", "5e-5", "[1, 2]", "null", "fast", "{a: 1}", "[1, 2", ": :", "'x", ""]),
                    st.text(max_size=8))


@fuzz
@given(data=st.data())
def test_set_changes_the_key_or_names_it(data):
    n = data.draw(st.integers(0, 3), "pairs")
    pairs = []
    for _ in range(n):
        pairs.append(".".join(data.draw(st.lists(st.sampled_from(_KEYS), min_size=1, max_size=3), "key")))
        pairs.append(data.draw(_VALUES, "value"))
    if data.draw(st.booleans(), "odd"):
        pairs.append("MODEL.RATIO")
    cfg = copy.deepcopy(_CFG)
    out, err = outcome(apply_overrides, cfg, pairs)
    if err is not None:
        assert_clear_error(err, ConfigError, ["--set"], f"--set {pairs!r}")
        return
    assert out is cfg and len(pairs) % 2 == 0
    for key in pairs[::2]:  # every key named existed, so its parent chain is still there
        node = cfg
        for part in key.split(".")[:-1]:
            node = node[part]
        assert key.split(".")[-1] in node


@fuzz
@given(data=st.data())
def test_counting_evaluator_scores_or_names_the_entry(data):
    classes = data.draw(st.integers(1, 3), "classes")
    frames = data.draw(st.integers(0, 5), "frames")
    preds = []
    for _ in range(frames):
        p = {}
        if data.draw(st.booleans(), "has counts") or frames == 1:
            p["counts"] = np.array(data.draw(st.lists(st.integers(0, 9), min_size=classes, max_size=classes), "c"))
        if data.draw(st.booleans(), "has truth") or frames == 1:
            p["true_counts"] = np.array(data.draw(st.lists(st.integers(0, 9), min_size=classes, max_size=classes),
                                                  "t"))
        preds.append(p)
    ev = CountingEvaluator([f"C{k}" for k in range(classes)])
    out, err = outcome(ev, preds, [{}] * frames)
    complete = frames > 0 and all("counts" in p and "true_counts" in p for p in preds)
    if not complete:
        assert_clear_error(err, ValueError, ["predictions"], "CountingEvaluator")
        return
    assert err is None, err
    metrics, _ = out
    assert 0 <= metrics["counting_accuracy"] <= 100 and metrics["count_mae"] >= 0
