"""Metrics against values computed by hand (the computation is in the comments)."""

import math

import numpy as np
import pytest

import ccfit.metrics as M


def test_bwt_two_tasks_exactly_25():
    # Task 0 trains until b_0 = 10, task 1 until b_1 = 20 (= b_N).
    # Task 0: R(10) = 80 = C_0, R(20) = 40. Drop max(0, C_0 - R): 0 at 10, 40 at 20.
    # Trapezoid: (0 + 40) / 2 * 10 = 200. D_0 = 100 * 200 / ((20 - 10) * (80 - 0)) = 25.
    curves = [([0, 10, 20], [0, 80, 40]), ([10, 20], [0, 90])]
    res = M.bwt(curves, [10, 20])
    assert res.per_task == {0: pytest.approx(25.0)}
    assert res.value == pytest.approx(25.0)
    assert float(res) == pytest.approx(25.0)
    assert res.learnt == {0: pytest.approx(80.0)}
    assert res.reason is None


def test_bwt_task_end_between_checkpoints():
    # b_0 = 10 lies between checkpoints 5 and 15: C_0 = (60 + 100) / 2 = 80.
    # Knots 10, 15, 20 with R = 80, 100, 20 -> drops 0, max(0, -20) = 0, 60.
    # Trapezoid: (0 + 0) / 2 * 5 + (0 + 60) / 2 * 5 = 150. D_0 = 100 * 150 / (10 * 80) = 18.75.
    curves = [([0, 5, 15, 20], [0, 60, 100, 20]), ([10, 20], [0, 50])]
    res = M.bwt(curves, [10, 20])
    assert res.learnt[0] == pytest.approx(80.0)
    assert res.value == pytest.approx(18.75)


def test_bwt_max_is_taken_per_checkpoint_then_trapezoid():
    # C_0 = 50; R = 50 at 10, 70 at 20, 30 at 30. Drops at the knots: 0, 0, 20.
    # Per-checkpoint max then trapezoid: 0 + (0 + 20) / 2 * 10 = 100 (the exact positive part
    # of the interpolated curve would be 20 * 5 / 2 = 50). D_0 = 100 * 100 / (20 * 50) = 10.
    curves = [([0, 10, 20, 30], [0, 50, 70, 30]), ([10, 30], [0, 1])]
    assert M.bwt(curves, [10, 30]).value == pytest.approx(10.0)


def test_bwt_excludes_never_learnt_task_and_averages_the_rest():
    # Three tasks, b = 10, 20, 30.
    # Task 0: C_0 = 0 (never learnt) -> excluded even though it later "drops" nowhere.
    # Task 1: R(20) = 60, R(30) = 30: drops 0, 30 -> area (0 + 30) / 2 * 10 = 150,
    #         D_1 = 100 * 150 / (10 * 60) = 25.
    # BWT = mean over {1} = 25.
    curves = [
        ([0, 10, 20, 30], [0, 0, 10, 0]),
        ([10, 20, 30], [0, 60, 30]),
        ([20, 30], [0, 70]),
    ]
    res = M.bwt(curves, [10, 20, 30])
    assert set(res.per_task) == {1}
    assert 0 in res.excluded and "never learnt" in res.excluded[0]
    assert res.value == pytest.approx(25.0)


def test_bwt_mean_over_two_tasks_and_no_forgetting():
    # Task 0: C_0 = 100 at 10, stays 100 (D_0 = 0); later improvements never count.
    # Task 1: C_1 = 40 at 20, R(30) = 0 -> area (0 + 40) / 2 * 10 = 200,
    #         D_1 = 100 * 200 / (10 * 40) = 50. BWT = (0 + 50) / 2 = 25.
    curves = [([10, 20, 30], [100, 120, 100]), ([20, 30], [40, 0]), ([20, 30], [0, 5])]
    res = M.bwt(curves, [10, 20, 30])
    assert res.per_task == {0: pytest.approx(0.0), 1: pytest.approx(50.0)}
    assert res.value == pytest.approx(25.0)


def test_bwt_floor_changes_normaliser():
    # Same as the first test with floor 40: D_0 = 100 * 200 / (10 * (80 - 40)) = 50.
    curves = [([0, 10, 20], [0, 80, 40]), ([10, 20], [0, 90])]
    assert M.bwt(curves, [10, 20], floor=40.0).value == pytest.approx(50.0)


def test_bwt_nan_with_reason_when_no_task_qualifies():
    curves = [([0, 10, 20], [0, 0, 0]), ([10, 20], [0, 90])]
    res = M.bwt(curves, [10, 20])
    assert math.isnan(res.value) and "no earlier task was learnt" in res.reason
    single = M.bwt([([0, 10], [0, 50])], [10])
    assert math.isnan(single.value) and "only one task" in single.reason


def test_bwt_rejects_bad_input():
    with pytest.raises(ValueError, match="not extrapolated"):
        M.bwt([([0, 10, 15], [0, 80, 40]), ([10, 20], [0, 90])], [10, 20])
    with pytest.raises(ValueError, match="strictly increasing"):
        M.bwt([([0, 20, 10], [0, 80, 40]), ([10, 20], [0, 90])], [10, 20])
    with pytest.raises(ValueError, match="task ends"):
        M.bwt([([0, 10, 20], [0, 80, 40])], [10, 20])


def test_fwt_by_hand_and_sign():
    # seq: 0 -> 50 -> 100 at 0, 10, 20; scratch: 0 -> 60 over [0, 20] (30 at 10).
    # Differences on the union grid {0, 10, 20}: 0, 20, 40.
    # Integral = (0 + 20) / 2 * 10 + (20 + 40) / 2 * 10 = 400; FWT = 400 / 20 = 20.
    seq = ([0, 10, 20], [0, 50, 100])
    scr = ([0, 20], [0, 60])
    assert M.fwt(seq, scr, 20) == pytest.approx(20.0)
    assert M.fwt(scr, seq, 20) == pytest.approx(-20.0)
    # Budget 10 truncates: (0 + 20) / 2 * 10 / 10 = 10.
    assert M.fwt(seq, scr, 10) == pytest.approx(10.0)
    # Budget between checkpoints (15): differences 0, 20, 30 at 0, 10, 15:
    # (0 + 20) / 2 * 10 + (20 + 30) / 2 * 5 = 225; / 15 = 15.
    assert M.fwt(seq, scr, 15) == pytest.approx(15.0)


def test_fwt_with_rebased_curriculum_curve():
    # In the curriculum the task starts at global step 100 (checkpoints 100, 110, 120).
    seq = M.rebase(([90, 100, 110, 120], [7, 0, 50, 100]), 100)
    np.testing.assert_array_equal(seq[0], [0, 10, 20])
    assert M.fwt(seq, ([0, 20], [0, 60]), 20) == pytest.approx(20.0)
    with pytest.raises(ValueError, match="not extrapolated"):
        M.fwt(([5, 20], [0, 1]), ([0, 20], [0, 1]), 20)
    with pytest.raises(ValueError, match="budget"):
        M.fwt(([0, 20], [0, 1]), ([0, 20], [0, 1]), 0)


def test_average_curves_same_and_different_grids():
    steps, mean = M.average_curves([([0, 10], [0, 50]), ([0, 10], [20, 70])])
    np.testing.assert_allclose(steps, [0, 10])
    np.testing.assert_allclose(mean, [10, 60])
    # Different checkpoints: common range [0, 10], grid = union {0, 5, 10}.
    # Curve a at 5 = 25 (interpolated), curve b = (0, 40, 60) -> mean (0, 32.5, 55).
    steps, mean = M.average_curves([([0, 10, 20], [0, 50, 90]), ([0, 5, 10], [0, 40, 60])])
    np.testing.assert_allclose(steps, [0, 5, 10])
    np.testing.assert_allclose(mean, [0, 32.5, 55])
    with pytest.raises(ValueError, match="at least one"):
        M.average_curves([])
    # Averaging before the metric differs from averaging the metric: BWT of the mean curve.
    seed_a = [([0, 10, 20], [0, 80, 40]), ([10, 20], [0, 90])]
    seed_b = [([0, 10, 20], [0, 80, 80]), ([10, 20], [0, 90])]
    mean_curves = [M.average_curves([a, b]) for a, b in zip(seed_a, seed_b, strict=True)]
    # Mean task-0 curve: 0, 80, 60 -> area (0 + 20) / 2 * 10 = 100 -> D_0 = 100*100/800 = 12.5.
    assert M.bwt(mean_curves, [10, 20]).value == pytest.approx(12.5)


def test_lopez_paz_and_continual_world_forgetting():
    # b = 10, 20, 30. R[j, i] = R_i(b_j):
    # task 0: 80 at 10, 70 at 20, 50 at 30; task 1: 60 at 20, 66 at 30; task 2: 90 at 30.
    curves = [([0, 10, 20, 30], [0, 80, 70, 50]), ([10, 20, 30], [0, 60, 66]), ([20, 30], [0, 90])]
    r = M.performance_matrix(curves, [10, 20, 30])
    assert r[0, 0] == 80 and r[2, 0] == 50 and r[1, 1] == 60 and r[2, 1] == 66
    assert math.isnan(r[0, 2])  # task 2 had no curve at b_0
    # Lopez-Paz: ((50 - 80) + (66 - 60)) / 2 = -12.
    assert M.lopez_paz_bwt(r) == pytest.approx(-12.0)
    # Continual World forgetting: F_0 = 80 - 50 = 30, F_1 = 60 - 66 = -6, mean 12.
    f = M.cw_forgetting(curves, [10, 20, 30])
    assert f.per_task == {0: pytest.approx(30.0), 1: pytest.approx(-6.0)}
    assert f.value == pytest.approx(12.0)
    assert math.isnan(M.lopez_paz_bwt(np.array([[5.0]])))


def test_cw_forward_transfer_by_hand():
    # AUC_seq = ((0 + 50) / 2 * 10 + (50 + 100) / 2 * 10) / 20 / 100 = 1000 / 20 / 100 = 0.5
    # AUC_b = ((0 + 60) / 2 * 20) / 20 / 100 = 0.3. FT = (0.5 - 0.3) / (1 - 0.3) = 2 / 7.
    seq = ([0, 10, 20], [0, 50, 100])
    scr = ([0, 20], [0, 60])
    assert M.cw_forward_transfer(seq, scr, 20) == pytest.approx(2 / 7)
    # Clipping: a seq curve at 150 (above the oracle) counts as 1 -> AUC_seq = 1,
    # FT = (1 - 0.3) / 0.7 = 1; without clipping AUC_seq = 1.5 -> FT = 1.2 / 0.7.
    high = ([0, 20], [150, 150])
    assert M.cw_forward_transfer(high, scr, 20) == pytest.approx(1.0)
    assert M.cw_forward_transfer(high, scr, 20, clip=False) == pytest.approx(1.2 / 0.7)
    assert math.isnan(M.cw_forward_transfer(seq, high, 20))
