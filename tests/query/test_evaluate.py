"""lidarops.query.evaluate: two sources of an index aligned by frame id (rows appended out of order, frames
only one source holds reported), the metrics against hand-computed numbers and a brute-force evaluation,
reproducibility, and bad arguments named in a QueryError."""
from __future__ import annotations

import json
import math
import operator
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

from lidarops.eval import counting  # noqa: E402
from lidarops.query import FrameIndex, QueryError  # noqa: E402
from lidarops.query.evaluate import Evaluation, evaluate  # noqa: E402

CLASSES = ["Car", "Pedestrian", "Cyclist"]
OPS = {"<": operator.lt, "<=": operator.le, "=": operator.eq, ">=": operator.ge, ">": operator.gt}

# labels: frames 10-15 (frame 15's 50 cars must not count: the detector lacks frame 15)
LABELS = {"frame_id": [10, 11, 12, 13, 14, 15], "Car": [2, 4, 10, 6, 0, 50], "Pedestrian": [0, 1, 2, 0, 0, 0],
          "Cyclist": [0, 0, 0, 0, 0, 0]}
# detector: frames 20 (not in the labels), 14, 13, ..., 10 (out of order), no Cyclist column (counts 0)
DETECTOR = {"frame_id": [20, 14, 13, 12, 11, 10], "Car": [3, 1, 6, 8, 5, 2], "Pedestrian": [0, 0, 1, 0, 1, 0]}
# aligned over the common frames 10-14:
#   true Car 2 4 10 6 0   Pedestrian 0 1 2 0 0   Cyclist 0 0 0 0 0
#   pred Car 2 5  8 6 1   Pedestrian 0 1 0 1 0   Cyclist 0 0 0 0 0
TRUE3 = np.array([[2, 0, 0], [4, 1, 0], [10, 2, 0], [6, 0, 0], [0, 0, 0]])
PRED3 = np.array([[2, 0, 0], [5, 1, 0], [8, 0, 0], [6, 1, 0], [1, 0, 0]])


@pytest.fixture
def index(tmp_path):
    idx = FrameIndex.create(tmp_path / "idx", LABELS, classes=CLASSES)
    idx.append({k: v[:3] for k, v in DETECTOR.items()}, source="detector")  # two parts
    idx.append({k: v[3:] for k, v in DETECTOR.items()}, source="detector")
    return idx


def test_hand_computed(index):
    r = evaluate(index, source="detector", truth="labels", tolerances=(0.10, 0.05), groups=4, queries=50)
    assert isinstance(r, Evaluation) and r.classes == CLASSES
    # frames 10-14 in both; 20 only in the detector, 15 only in the labels
    assert r.frames == 5 and r.only_source.tolist() == [20] and r.only_truth.tolist() == [15]
    # largest true count over the common frames: Car 10 (not 50), Pedestrian 2, Cyclist 0
    assert r.max_count.tolist() == [10, 2, 0]
    # 10 %: allowed Car floor(1.0) = 1, Pedestrian floor(0.2) = 0, Cyclist 0
    assert r.allowed_error[0.10].tolist() == [1, 0, 0]
    assert r.allowed_error[0.05].tolist() == [0, 0, 0]
    # |pred - true|: Car 0 1 2 0 1, Pedestrian 0 0 2 1 0, Cyclist 0 0 0 0 0
    # 10 %: Car T T F T T = 0.8, Pedestrian T T F F T = 0.6, Cyclist 1.0; all three: T T F F T = 0.6
    np.testing.assert_allclose(r.retrieval_single[0.10], [0.8, 0.6, 1.0])
    assert r.retrieval_multiple[0.10] == pytest.approx(0.6)
    # 5 %: Car T F F T F = 0.4, Pedestrian 0.6, Cyclist 1.0; all three: T F F F F = 0.2
    np.testing.assert_allclose(r.retrieval_single[0.05], [0.4, 0.6, 1.0])
    assert r.retrieval_multiple[0.05] == pytest.approx(0.2)
    # exact counts: Car 2/5, Pedestrian 3/5, Cyclist 5/5; mean |error| Car 4/5, Pedestrian 3/5, Cyclist 0
    np.testing.assert_allclose(r.counting_accuracy, [0.4, 0.6, 1.0])
    np.testing.assert_allclose(r.mean_abs_error, [0.8, 0.6, 0.0])
    # means: true Car 22/5, Pedestrian 3/5; pred Car 22/5, Pedestrian 2/5
    np.testing.assert_allclose(r.mean_true, [4.4, 0.6, 0.0])
    np.testing.assert_allclose(r.mean_pred, [4.4, 0.4, 0.0])
    # SUM over the five frames: Car 22 vs 22 -> 0, Q 1; Pedestrian 3 vs 2 -> 1, Q 1.5; Cyclist 0 vs 0 -> 0, Q 1
    assert r.aggregation["true"].tolist() == [22, 3, 0] and r.aggregation["pred"].tolist() == [22, 2, 0]
    assert r.aggregation["abs_diff"].tolist() == [0, 1, 0]
    np.testing.assert_allclose(r.aggregation["q_error"], [1.0, 1.5, 1.0])
    # five frames, groups of 100-500 clipped to 5: every group is the whole drive, so every group's SUM is
    # the whole SUM
    assert r.groups == 4 and r.group_lengths == (5, 5) and r.queries == 50
    np.testing.assert_allclose(r.aggregation_groups["mean_q_error"], [1.0, 1.5, 1.0])
    np.testing.assert_allclose(r.aggregation_groups["max_q_error"], [1.0, 1.5, 1.0])
    np.testing.assert_allclose(r.aggregation_groups["mean_abs_diff"], [0, 1, 0])
    # Cyclist: no frame holds one, none is counted: every COUNT query answered exactly
    assert r.count["accuracy"][2] == 1.0 and r.count["exact"][2] == 1.0


def test_count_queries_against_brute_force(index):
    r = evaluate(index, source="detector", groups=3, queries=40, seed=7)
    # the same draw (over every class of the index, in its order), answered with plain Python
    qs = counting.random_count_queries(TRUE3, 40, 3, (100, 500), seed=7)
    for c in range(3):
        scores, exact, diffs = [], [], []
        for q in range(40):
            g = qs.group[c, q]
            frames = range(qs.starts[g], qs.starts[g] + qs.lengths[g])
            op, v = OPS[counting.OPERATORS[qs.op[c, q]]], qs.value[c, q]
            a = sum(1 for f in frames if op(TRUE3[f, c], v))
            b = sum(1 for f in frames if op(PRED3[f, c], v))
            scores.append(1.0 if a == b == 0 else min(a, b) / max(a, b))
            exact.append(a == b)
            diffs.append(abs(a - b))
        assert r.count["accuracy"][c] == pytest.approx(sum(scores) / 40)
        assert r.count["exact"][c] == pytest.approx(sum(exact) / 40)
        assert r.count["mean_abs_error"][c] == pytest.approx(sum(diffs) / 40)


def test_perfect_source(index):
    r = evaluate(index, source="labels", truth="labels", groups=5, queries=30)
    assert r.frames == 6 and len(r.only_source) == len(r.only_truth) == 0
    for t in (0.10, 0.05):
        np.testing.assert_array_equal(r.retrieval_single[t], [1.0, 1.0, 1.0])
        assert r.retrieval_multiple[t] == 1.0
    np.testing.assert_array_equal(r.counting_accuracy, [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(r.count["accuracy"], [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(r.aggregation["q_error"], [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(r.aggregation_groups["max_q_error"], [1.0, 1.0, 1.0])


def test_random_tables_against_brute_force(tmp_path):
    """Ids with gaps, several parts, a source off by -1/0/+1: RETRIEVAL and SUM recomputed in plain Python
    with exact fractions."""
    rng = np.random.default_rng(3)
    n = 240
    ids = np.sort(rng.choice(10_000, n, replace=False))
    labels = {"frame_id": ids, **{c: rng.poisson(lam, n) for c, lam in zip(CLASSES, (5, 2, 0.4))}}
    idx = FrameIndex.create(tmp_path / "idx", labels)
    det = {"frame_id": ids, **{c: np.maximum(labels[c] + rng.integers(-1, 2, n), 0) for c in CLASSES}}
    order = rng.permutation(n)
    for part in np.array_split(order, 3):
        idx.append({k: v[part] for k, v in det.items()}, source="detector")
    r = evaluate(idx, source="detector", groups=50, queries=100, group_frames=(20, 80))
    assert r.frames == n and r.group_lengths[0] >= 20 and r.group_lengths[1] <= 80
    for t in (0.10, 0.05):
        within_all = [True] * n
        for c_i, c in enumerate(CLASSES):
            top = max(int(v) for v in labels[c])
            allowed = math.floor(Fraction(str(t)) * top)
            within = [abs(int(p) - int(q)) <= allowed for p, q in zip(det[c], labels[c])]
            within_all = [a and b for a, b in zip(within_all, within)]
            assert r.allowed_error[t][c_i] == allowed
            assert r.retrieval_single[t][c_i] == pytest.approx(sum(within) / n)
        assert r.retrieval_multiple[t] == pytest.approx(sum(within_all) / n)
    for c_i, c in enumerate(CLASSES):
        st, sp = int(sum(labels[c])), int(sum(det[c]))
        assert r.aggregation["abs_diff"][c_i] == abs(st - sp)
        assert r.aggregation["q_error"][c_i] == pytest.approx(max(max(sp, 1) / max(st, 1), max(st, 1) / max(sp, 1)))


def test_reproducible_and_independent_of_the_classes_scored(index):
    a = evaluate(index, groups=6, queries=60, seed=5).as_dict()
    b = evaluate(index, groups=6, queries=60, seed=5).as_dict()
    assert a == b
    g1 = evaluate(index, groups=6, queries=60, seed=np.random.default_rng(2)).as_dict()
    g2 = evaluate(index, groups=6, queries=60, seed=np.random.default_rng(2)).as_dict()
    assert g1 == g2 and g1["seed"] is None
    # Pedestrian alone: the same COUNT queries as among all three; MULTIPLE over it alone is its SINGLE
    one = evaluate(index, classes=["Pedestrian"], groups=6, queries=60, seed=5)
    assert one.classes == ["Pedestrian"]
    assert one.count["accuracy"][0] == a["count"]["accuracy"]["Pedestrian"]
    assert one.retrieval_multiple[0.1] == pytest.approx(0.6)  # Pedestrian's SINGLE at 10 %


def test_tables_and_json(index):
    r = evaluate(index, groups=4, queries=20)
    text = r.format()
    assert "5 common frame(s)" in text
    assert "1 frame(s) (ids 20) only in detector" in text and "1 frame(s) (ids 15) only in labels" in text
    car = next(line for line in text.splitlines() if line.startswith("Car ") and "0.800" in line)
    assert car.split() == ["Car", "10", "1", "0.800", "0", "0.400"]  # max, ± and SINGLE at 10 % and 5 %
    multiple = next(line for line in text.splitlines() if line.startswith("all (MULTIPLE)"))
    assert multiple.split()[-2:] == ["0.600", "0.200"]
    assert [t for t, _, _ in r.tables()][0].startswith("RETRIEVAL") and len(r.tables()) == 4
    d = json.loads(json.dumps(r.as_dict()))
    assert d["retrieval_single"]["0.1"]["Car"] == pytest.approx(0.8)
    assert d["aggregation"]["q_error"]["Pedestrian"] == pytest.approx(1.5)
    assert d["only_source"] == [20] and d["only_truth"] == [15]


def test_index_path(index):
    assert evaluate(str(index.root), groups=2, queries=5).frames == 5


@pytest.mark.parametrize("kwargs, names", [
    ({"source": "radar"}, ["source", "'radar'", "detector, labels"]),
    ({"truth": "lidar"}, ["truth", "'lidar'"]),
    ({"classes": ["Truck"]}, ["'Truck'", "Car, Pedestrian, Cyclist"]),
    ({"classes": "Car"}, ["classes"]),
    ({"classes": []}, ["classes"]),
    ({"classes": ["Car", "Car"]}, ["classes"]),
    ({"tolerances": (0.1, 2)}, ["tolerances", "2"]),
    ({"tolerances": ()}, ["tolerances"]),
    ({"tolerances": (0.1, float("nan"))}, ["tolerances"]),
    ({"tolerances": (0.1, 0.1)}, ["tolerances"]),
    ({"groups": 0}, ["groups"]),
    ({"queries": 0}, ["queries"]),
    ({"queries": 2.5}, ["queries"]),
    ({"group_frames": (5, 1)}, ["group_frames"]),
    ({"seed": -1}, ["seed"]),
    ({"seed": "x"}, ["seed"]),
])
def test_bad_arguments_are_named(index, kwargs, names):
    with pytest.raises(QueryError) as e:
        evaluate(index, **kwargs)
    for n in names:
        assert n in str(e.value), (n, str(e.value))


def test_no_common_frame(index):
    index.append({"frame_id": [100, 101], "Car": [1, 2]}, source="other")
    with pytest.raises(QueryError, match="share no frame"):
        evaluate(index, source="other")


def test_bad_index():
    with pytest.raises(QueryError, match="index"):
        evaluate(42)


def test_import_stays_light():
    """Importing the module loads neither DuckDB nor pyarrow nor pandas (they load on the first query)."""
    code = ("import sys, lidarops.query, lidarops.query.evaluate, lidarops.eval.counting; "
            "print(sorted(m for m in ('duckdb', 'pyarrow', 'pandas', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
