"""lidarops.eval.counting against hand-computed cases: every expected number below is worked out by hand
from the definitions in the module's docstring (the arithmetic is in the comments), never taken from what
the code returned. Zero cases of the Q-error, ties at the tolerance, absent classes, empty inputs, a
perfect source, a source off by a known amount, reproducibility with a seed, and bad arguments named."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from lidarops.eval import counting
from lidarops.eval.counting import (CountQueries, aggregation_errors, allowed_error, count_query_accuracy,
                                    count_query_answers, counting_accuracy, mean_absolute_error, q_error,
                                    random_count_queries, random_groups, retrieval_multiple_accuracy,
                                    retrieval_single_accuracy, within_tolerance)

# Five frames, two classes (Car, Pedestrian), used by several tests.
TRUE = np.array([[2, 0], [4, 1], [10, 2], [6, 0], [0, 0]])
PRED = np.array([[2, 0], [5, 1], [8, 0], [6, 1], [1, 0]])
# |PRED - TRUE|:  Car 0, 1, 2, 0, 1     Pedestrian 0, 0, 2, 1, 0
# largest true count: Car 10, Pedestrian 2


# ----------------------------------------------------------------------------------------------- Q-error
def test_q_error_hand_cases_and_zero_cases():
    pred = [0, 0, 5, 2, 10, 1, 0, 7]
    true = [0, 3, 0, 8, 10, 0, 1, 2]
    want = [1.0,  # 0 vs 0: both taken as 1 -> 1/1
            3.0,  # 0 vs 3: 0 -> 1, max(1/3, 3/1) = 3
            5.0,  # 5 vs 0: max(5/1, 1/5) = 5
            4.0,  # 2 vs 8: max(2/8, 8/2) = 4
            1.0,  # 10 vs 10
            1.0,  # 1 vs 0: 0 -> 1, so 1/1 (the documented blind spot; the absolute difference shows it)
            1.0,  # 0 vs 1: likewise
            3.5]  # 7 vs 2: 7/2
    got = q_error(pred, true)
    assert got.dtype == np.float64 and got.shape == (8,)
    np.testing.assert_array_equal(got, want)


def test_q_error_scalar_2d_and_empty():
    assert q_error(3, 6) == 2.0 and isinstance(q_error(3, 6), float)  # max(3/6, 6/3)
    np.testing.assert_array_equal(q_error([[4, 0], [9, 3]], [[2, 0], [3, 9]]), [[2.0, 1.0], [3.0, 3.0]])
    empty = q_error(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert empty.shape == (0,)


def test_q_error_takes_sums_beyond_a_count():
    # sums of int32 counts exceed 2**31 - 1: 3 * 2**31 against 2**31 is 3
    assert q_error(3 * 2 ** 31, 2 ** 31) == 3.0
    with pytest.raises(ValueError, match="pred"):
        q_error(2 ** 62 + 2 ** 10, 1)


def test_q_error_is_symmetric_and_at_least_one():
    a, b = np.array([0, 1, 2, 50, 7]), np.array([9, 1, 0, 49, 7])
    np.testing.assert_array_equal(q_error(a, b), q_error(b, a))
    assert (q_error(a, b) >= 1).all()


# ------------------------------------------------------------------------------------ tolerance and ties
def test_allowed_error_exact_per_class():
    true = np.array([[0, 20, 30, 100], [8, 1, 0, 5]])  # largest per class: 8, 20, 30, 100
    # 10 %: floor(0.8) = 0, floor(2) = 2, floor(3) = 3, floor(10) = 10
    np.testing.assert_array_equal(allowed_error(true, 0.10), [0, 2, 3, 10])
    # 5 %: floor(0.4) = 0, floor(1) = 1, floor(1.5) = 1, floor(5) = 5
    np.testing.assert_array_equal(allowed_error(true, 0.05), [0, 1, 1, 5])
    # 29 %: floor(2.32) = 2, floor(5.8) = 5, floor(8.7) = 8, 29 exactly (float arithmetic gives
    # 0.29 * 100 = 28.999999999999996, floor 28: the exact rule keeps the tie)
    np.testing.assert_array_equal(allowed_error(true, 0.29), [2, 5, 8, 29])
    np.testing.assert_array_equal(allowed_error(true, Fraction(1, 3)), [2, 6, 10, 33])  # floor(8/3), 20/3, 10, 100/3
    assert allowed_error([3, 7, 1], 0.5) == 3  # 1-D: an int; floor(0.5 * 7) = 3


def test_tie_at_the_tolerance_is_within():
    # one class, largest true count 20: at 5 % the allowed error is floor(0.05 * 20) = 1
    true = np.array([20, 10, 10, 10, 10])
    pred = np.array([20, 11, 12, 9, 8])     # errors 0, 1, 2, 1, 2
    np.testing.assert_array_equal(within_tolerance(pred, true, 0.05), [True, True, False, True, False])
    assert retrieval_single_accuracy(pred, true, 0.05) == pytest.approx(3 / 5)
    # at 29 % of a largest count of 100 the allowed error is 29: an error of 29 is within, 30 is not
    true, pred = np.array([100, 50, 50]), np.array([100, 79, 80])  # errors 0, 29, 30
    np.testing.assert_array_equal(within_tolerance(pred, true, 0.29), [True, True, False])


# ------------------------------------------------------------------------------------------- RETRIEVAL
def test_retrieval_single_and_multiple_by_hand():
    # 10 %: allowed Car floor(1.0) = 1, Pedestrian floor(0.2) = 0
    #   Car within:        T T F T T  -> 4/5 = 0.8
    #   Pedestrian within: T T F F T  -> 3/5 = 0.6
    #   both:              T T F F T  -> 3/5 = 0.6
    np.testing.assert_allclose(retrieval_single_accuracy(PRED, TRUE, 0.10), [0.8, 0.6])
    assert retrieval_multiple_accuracy(PRED, TRUE, 0.10) == pytest.approx(0.6)
    # 5 %: allowed Car floor(0.5) = 0, Pedestrian 0
    #   Car:  T F F T F -> 0.4;  Pedestrian: 0.6;  both: T F F F F -> 0.2
    np.testing.assert_allclose(retrieval_single_accuracy(PRED, TRUE, 0.05), [0.4, 0.6])
    assert retrieval_multiple_accuracy(PRED, TRUE, 0.05) == pytest.approx(0.2)
    # one class: MULTIPLE is SINGLE; a 1-D input gives a float
    assert retrieval_single_accuracy(PRED[:, 0], TRUE[:, 0], 0.10) == pytest.approx(0.8)
    assert retrieval_multiple_accuracy(PRED[:, 0], TRUE[:, 0], 0.10) == pytest.approx(0.8)


def test_counting_accuracy_and_mae_by_hand():
    # exact: Car T F F T F -> 0.4; Pedestrian T T F F T -> 0.6
    np.testing.assert_allclose(counting_accuracy(PRED, TRUE), [0.4, 0.6])
    # mean |error|: Car (0+1+2+0+1)/5 = 0.8; Pedestrian (0+0+2+1+0)/5 = 0.6
    np.testing.assert_allclose(mean_absolute_error(PRED, TRUE), [0.8, 0.6])
    assert counting_accuracy([1, 2, 3], [1, 2, 4]) == pytest.approx(2 / 3)


def test_absent_class():
    # a class no frame holds: largest true count 0, allowed error 0 at any tolerance
    true = np.zeros((4, 1), np.int64)
    pred = np.array([[0], [1], [0], [0]])
    np.testing.assert_array_equal(allowed_error(true, 0.10), [0])
    np.testing.assert_allclose(retrieval_single_accuracy(pred, true, 0.10), [3 / 4])
    np.testing.assert_allclose(counting_accuracy(pred, true), [3 / 4])
    # SUM: 1 against 0: difference 1, Q-error max(1/1, 1/1) = 1 (0 taken as 1)
    agg = aggregation_errors(pred, true)
    assert agg["abs_diff"].tolist() == [[1]] and agg["q_error"].tolist() == [[1.0]]
    # absent and never predicted: a perfect score
    np.testing.assert_allclose(counting_accuracy(true, true), [1.0])


def test_perfect_source():
    rng = np.random.default_rng(5)
    true = rng.poisson(3, (300, 3))
    for tol in (0.10, 0.05, 0.0):
        np.testing.assert_array_equal(retrieval_single_accuracy(true, true, tol), [1.0, 1.0, 1.0])
        assert retrieval_multiple_accuracy(true, true, tol) == 1.0
    np.testing.assert_array_equal(counting_accuracy(true, true), [1.0, 1.0, 1.0])
    res = count_query_accuracy(true, true, queries=200, groups=20, group_frames=(50, 100), seed=1)
    np.testing.assert_array_equal(res["accuracy"], [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(res["exact"], [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(res["mean_abs_error"], [0.0, 0.0, 0.0])
    agg = aggregation_errors(true, true, random_groups(300, 20, (50, 100), seed=1))
    assert (agg["abs_diff"] == 0).all() and (agg["q_error"] == 1.0).all()


def test_source_off_by_one_everywhere():
    # true counts 0..10 (11 frames), the source counts one more in every frame
    true = np.arange(11)
    pred = true + 1
    # largest 10: allowed at 10 % floor(1.0) = 1 -> every error of 1 within; at 5 % floor(0.5) = 0 -> none
    assert retrieval_single_accuracy(pred, true, 0.10) == 1.0
    assert retrieval_single_accuracy(pred, true, 0.05) == 0.0
    assert counting_accuracy(pred, true) == 0.0
    assert mean_absolute_error(pred, true) == 1.0
    # SUM: true 0+1+...+10 = 55, pred 55 + 11 = 66: difference 11, Q-error 66/55 = 1.2
    agg = aggregation_errors(pred, true)
    assert agg["true"].tolist() == [55] and agg["pred"].tolist() == [66] and agg["abs_diff"].tolist() == [11]
    assert agg["q_error"][0] == pytest.approx(1.2)


# ----------------------------------------------------------------------------------------------- COUNT
# One class over six frames; two groups: g0 = frames 0-3, g1 = frames 2-4.
C_TRUE = np.array([0, 1, 2, 2, 3, 5])
C_PRED = np.array([0, 2, 2, 1, 3, 4])
#            group  op    value   true frames -> answer     pred frames -> answer   score
# q0         g0     >=    2       0 1 2 2 -> 2              0 2 2 1 -> 2            1
# q1         g0     =     1       0 1 2 2 -> 1              0 2 2 1 -> 1            1 (the errors cancel)
# q2         g1     >     2       2 2 3   -> 1              2 1 3   -> 1            1
# q3         g1     <     2       2 2 3   -> 0              2 1 3   -> 1            0 (exactly one is 0)
# q4         g0     <=    0       0 1 2 2 -> 1              0 2 2 1 -> 1            1
# q5         g1     =     4       2 2 3   -> 0              2 1 3   -> 0            1 (both 0)
# q6         g0     >     0       0 1 2 2 -> 3              0 2 2 1 -> 3            1
# q7         g1     >=    2       2 2 3   -> 3              2 1 3   -> 2            2/3
QUERIES = CountQueries(starts=[0, 2], lengths=[4, 3], group=[[0, 0, 1, 1, 0, 1, 0, 1]],
                       op=[[3, 2, 4, 0, 1, 2, 4, 3]], value=[[2, 1, 2, 2, 0, 4, 0, 2]])


def test_count_query_answers_by_hand():
    assert [counting.OPERATORS[o] for o in QUERIES.op[0]] == [">=", "=", ">", "<", "<=", "=", ">", ">="]
    np.testing.assert_array_equal(count_query_answers(C_TRUE, QUERIES), [2, 1, 1, 0, 1, 0, 3, 3])
    np.testing.assert_array_equal(count_query_answers(C_PRED, QUERIES), [2, 1, 1, 1, 1, 0, 3, 2])
    assert QUERIES.describe(0, 7) == "frames 2-4: count >= 2"


def test_count_query_accuracy_by_hand():
    res = count_query_accuracy(C_PRED, C_TRUE, QUERIES)
    # scores 1, 1, 1, 0, 1, 1, 1, 2/3: mean (6 + 2/3) / 8 = 5/6
    assert res["accuracy"] == pytest.approx(5 / 6)
    # exact: 6 of 8
    assert res["exact"] == pytest.approx(0.75)
    # |b - a| (a true, b predicted): 0 0 0 1 0 0 0 1 -> 2/8
    assert res["mean_abs_error"] == pytest.approx(0.25)
    # two classes: the second column is perfect
    two = count_query_accuracy(np.stack([C_PRED, C_TRUE], 1), np.stack([C_TRUE, C_TRUE], 1),
                               CountQueries(QUERIES.starts, QUERIES.lengths, np.repeat(QUERIES.group, 2, 0),
                                            np.repeat(QUERIES.op, 2, 0), np.repeat(QUERIES.value, 2, 0)))
    np.testing.assert_allclose(two["accuracy"], [5 / 6, 1.0])


def test_random_groups_bounds_and_clipping():
    starts, lengths = random_groups(2000, 500, (100, 500), seed=3)
    assert starts.shape == lengths.shape == (500,)
    assert lengths.min() >= 100 and lengths.max() <= 500 and starts.min() >= 0
    assert (starts + lengths <= 2000).all()
    # fewer frames than the fewest of a group: every group is the whole drive
    starts, lengths = random_groups(50, 7, (100, 500), seed=3)
    assert starts.tolist() == [0] * 7 and lengths.tolist() == [50] * 7
    # a window the drive just fits
    starts, lengths = random_groups(120, 30, (100, 500), seed=3)
    assert lengths.min() >= 100 and lengths.max() <= 120 and (starts + lengths <= 120).all()


def test_random_queries_take_values_from_their_group():
    rng = np.random.default_rng(0)
    true = rng.poisson(3, (400, 2))
    qs = random_count_queries(true, queries=300, groups=40, group_frames=(20, 60), seed=11)
    assert qs.group.shape == (2, 300) and len(qs) == 300 and qs.classes == 2
    for c in range(2):
        for q in range(300):
            g = qs.group[c, q]
            assert qs.value[c, q] in true[qs.starts[g]:qs.starts[g] + qs.lengths[g], c]
    assert set(qs.op.ravel().tolist()) == {0, 1, 2, 3, 4}  # 600 draws: every operator


def test_reproducible_with_a_seed():
    rng = np.random.default_rng(1)
    true = rng.poisson(3, (500, 2))
    pred = np.maximum(true + rng.integers(-2, 3, true.shape), 0)
    a = count_query_accuracy(pred, true, queries=100, groups=10, seed=42)
    b = count_query_accuracy(pred, true, queries=100, groups=10, seed=42)
    for k in ("accuracy", "exact", "mean_abs_error"):
        np.testing.assert_array_equal(a[k], b[k])
    np.testing.assert_array_equal(a["queries"].value, b["queries"].value)
    # a Generator in the same state gives the same draws
    g1, g2 = random_count_queries(true, 50, 5, seed=np.random.default_rng(9)), \
        random_count_queries(true, 50, 5, seed=np.random.default_rng(9))
    np.testing.assert_array_equal(g1.group, g2.group)
    np.testing.assert_array_equal(g1.value, g2.value)
    # another seed, other queries (500 draws of 5 operators: equal by chance with probability 5**-500)
    c = random_count_queries(true, 500, 10, seed=43)
    assert not np.array_equal(a["queries"].op[:, :100], c.op[:, :100]) or \
        not np.array_equal(a["queries"].starts, c.starts)
    # the queries do not depend on the predictions
    other = count_query_accuracy(true, true, queries=100, groups=10, seed=42)
    np.testing.assert_array_equal(other["queries"].value, a["queries"].value)


# ------------------------------------------------------------------------------------------ AGGREGATION
def test_aggregation_by_hand():
    # all six frames: true 0+1+2+2+3+5 = 13, pred 0+2+2+1+3+4 = 12 -> |diff| 1, Q 13/12
    whole = aggregation_errors(C_PRED, C_TRUE)
    assert whole["true"].tolist() == [13] and whole["pred"].tolist() == [12] and whole["abs_diff"].tolist() == [1]
    assert whole["q_error"][0] == pytest.approx(13 / 12)
    # g0 (frames 0-3): true 5, pred 5 -> 0, 1;  g1 (frames 2-4): true 7, pred 6 -> 1, 7/6
    grouped = aggregation_errors(C_PRED, C_TRUE, ([0, 2], [4, 3]))
    assert grouped["true"].tolist() == [5, 7] and grouped["pred"].tolist() == [5, 6]
    np.testing.assert_allclose(grouped["q_error"], [1.0, 7 / 6])
    # zero cases: 0 vs 0 -> 1; 3 vs 0 -> 3
    zero = aggregation_errors(np.array([[0, 3], [0, 0]]), np.zeros((2, 2), np.int64))
    assert zero["abs_diff"].tolist() == [[0, 3]] and zero["q_error"].tolist() == [[1.0, 3.0]]


def test_aggregation_over_no_frames_is_zero():
    out = aggregation_errors(np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64))
    assert out["true"].tolist() == [[0, 0]] and out["abs_diff"].tolist() == [[0, 0]]
    assert out["q_error"].tolist() == [[1.0, 1.0]]


# ------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("fn", [counting_accuracy, mean_absolute_error,
                                lambda p, t: retrieval_single_accuracy(p, t, 0.1),
                                lambda p, t: retrieval_multiple_accuracy(p, t, 0.1),
                                lambda p, t: count_query_accuracy(p, t, 10, 2)])
def test_accuracy_over_no_frames_is_refused(fn):
    with pytest.raises(ValueError, match="no frames"):
        fn(np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64))
    with pytest.raises(ValueError, match="no class"):
        fn(np.zeros((3, 0), np.int64), np.zeros((3, 0), np.int64))


@pytest.mark.parametrize("pred, true, names", [
    ([1, 2], [1, 2, 3], ["pred", "(2,)", "(3,)"]),
    (np.zeros((2, 2, 2)), np.zeros((2, 2, 2)), ["pred", "(2, 2, 2)"]),
    ([1, -1], [1, 1], ["pred", "-1"]),
    ([1, 1], [1.5, 1], ["true", "whole", "1.5"]),
    ([1, np.nan], [1, 1], ["pred", "finite"]),
    ([1, np.inf], [1, 1], ["pred", "finite"]),
    (np.array([True, False]), [1, 0], ["pred", "bool"]),
    (np.array(["1", "2"]), [1, 2], ["pred", "<U1"]),
    ([1, 2], [[1, 2], [3]], ["true"]),
    (np.array([2 ** 31, 0], np.int64), [1, 1], ["pred", str(2 ** 31 - 1)]),
    (np.array([2 ** 63, 0], np.uint64), [1, 1], ["pred"]),
    (np.array([1 + 1j, 0]), [1, 1], ["pred", "complex"]),
])
def test_bad_counts_are_named(pred, true, names):
    for fn in (counting_accuracy, mean_absolute_error, lambda p, t: retrieval_single_accuracy(p, t, 0.1),
               lambda p, t: count_query_accuracy(p, t, 5, 2), aggregation_errors):
        with pytest.raises(ValueError) as e:
            fn(pred, true)
        for n in names:
            assert n in str(e.value), (n, str(e.value))


@pytest.mark.parametrize("tol", [-0.1, 1.5, float("nan"), float("inf"), True, "0.1", None])
def test_bad_tolerance_is_named(tol):
    with pytest.raises(ValueError, match="tolerance"):
        retrieval_single_accuracy(PRED, TRUE, tol)
    with pytest.raises(ValueError, match="tolerance"):
        allowed_error(TRUE, tol)


def test_bad_query_arguments_are_named():
    with pytest.raises(ValueError, match="groups"):
        random_groups(10, 0)
    with pytest.raises(ValueError, match="n_frames"):
        random_groups(0, 3)
    with pytest.raises(ValueError, match="group_frames"):
        random_groups(10, 3, (5, 4))
    with pytest.raises(ValueError, match="group_frames"):
        random_groups(10, 3, (0, 4))
    with pytest.raises(ValueError, match="group_frames"):
        random_groups(10, 3, 5)
    with pytest.raises(ValueError, match="seed"):
        random_groups(10, 3, seed=-1)
    with pytest.raises(ValueError, match="seed"):
        random_groups(10, 3, seed=1.5)
    with pytest.raises(ValueError, match="queries"):
        count_query_accuracy(PRED, TRUE, queries=0)
    with pytest.raises(ValueError, match="queries"):
        count_query_accuracy(PRED, TRUE, queries="many")
    # explicit queries that do not fit the counts
    with pytest.raises(ValueError, match="queries reach frame"):
        count_query_answers(C_TRUE[:4], QUERIES)  # g1 (frames 2-4) needs five frames
    with pytest.raises(ValueError, match="class"):
        count_query_answers(np.stack([C_TRUE, C_TRUE], 1), QUERIES)
    with pytest.raises(ValueError, match="queries.op"):
        CountQueries(starts=[0], lengths=[2], group=[[0]], op=[[5]], value=[[1]])
    with pytest.raises(ValueError, match="queries.group"):
        CountQueries(starts=[0], lengths=[2], group=[[1]], op=[[0]], value=[[1]])
    with pytest.raises(ValueError, match="groups must lie within"):
        aggregation_errors(C_PRED, C_TRUE, ([4], [3]))
