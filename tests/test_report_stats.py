"""`ccfit.report.stats`: rliable's estimates, seeded so a report is the same file each time, the
paper's convention bootstrapped by resampling seeds, and the values checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ccfit.report.stats import (
    curve_interval,
    iqm_interval,
    mean_interval,
    metric_fields,
    probability_of_improvement,
)

SCORES = [12.0, 3.5, 40.0, 7.25, 19.0, 0.5, 28.0]


def test_an_interval_does_not_depend_on_numpys_global_state_and_leaves_it_as_it_was():
    # rliable's bootstrap draws from numpy's global generator: two callers in different states
    # must get the same interval, and each finds its own state untouched afterwards.
    np.random.seed(1)
    first = mean_interval(SCORES)
    after_first = np.random.rand()
    np.random.seed(2)
    second = mean_interval(SCORES)
    assert first == second
    np.random.seed(1)
    assert np.random.rand() == after_first
    assert first.value == pytest.approx(np.mean(SCORES))
    assert min(SCORES) < first.lo < first.value < first.hi < max(SCORES)


def test_one_seed_has_no_width_and_no_seed_no_interval():
    one = mean_interval([4.0])
    assert (one.value, one.lo, one.hi) == (4.0, 4.0, 4.0)
    assert mean_interval([]) is None


def test_the_curves_convention_resamples_seeds_as_the_per_seed_mean_does():
    # A metric linear in the curves is the same under both conventions: the bootstrap over
    # seed indices then draws the very resamples of the bootstrap over the values.
    curves = curve_interval(len(SCORES), lambda idx: float(np.mean([SCORES[i] for i in idx])))
    assert curves == mean_interval(SCORES)
    undefined = curve_interval(3, lambda idx: None)
    assert undefined is None
    # defined on the whole, undefined on some resample (here: any that repeats seed 0)
    partly = curve_interval(3, lambda idx: None if idx.count(0) > 1 else 1.0)
    assert partly.value == 1.0 and math.isnan(partly.lo) and math.isnan(partly.hi)


def test_probability_of_improvement_counts_the_seed_pairs_where_one_beats_the_other():
    lower_better = probability_of_improvement([1.0, 5.0, 3.0], [4.0, 2.0, 6.0],
                                              lower_is_better=True)  # fmt: skip
    assert lower_better.value == pytest.approx(6 / 9)  # 1<4, 1<2, 1<6, 5<6, 3<4, 3<6
    assert 0.0 <= lower_better.lo <= lower_better.value <= lower_better.hi <= 1.0
    higher_better = probability_of_improvement([1.0, 5.0, 3.0], [4.0, 2.0, 6.0],
                                               lower_is_better=False)  # fmt: skip
    assert higher_better.value == pytest.approx(3 / 9)
    assert probability_of_improvement([1.0, 2.0], [1.0, 2.0], True).value == pytest.approx(0.5)
    always = probability_of_improvement([1.0, 2.0], [3.0, 4.0], True)
    assert (always.value, always.lo, always.hi) == (1.0, 1.0, 1.0)
    assert probability_of_improvement([], [1.0], True) is None


def test_interquartile_mean_by_hand():
    scores = np.arange(16.0).reshape(8, 2)  # 16 values: the IQM keeps the middle 8
    assert iqm_interval(scores).value == pytest.approx(np.mean(np.arange(4.0, 12.0)))


def test_a_groups_metric_fields():
    fields = metric_fields("bwt", 2.0, curve_interval(3, lambda idx: None if 2 in idx else 2.0),
                           {0: 1.0, 1: 3.0, 2: None})  # fmt: skip
    assert fields["bwt"] == 2.0 and fields["bwt_seed_mean"] == 2.0
    assert (fields["bwt_min"], fields["bwt_max"], fields["bwt_seeds_defined"]) == (1.0, 3.0, 2)
    assert fields["bwt_per_seed"] == {0: 1.0, 1: 3.0, 2: None}
    # a bound that some resample leaves undefined is None (JSON holds no NaN)
    assert fields["bwt_lo"] is None and fields["bwt_hi"] is None
    assert fields["bwt_seed_mean_lo"] == 1.0 and fields["bwt_seed_mean_hi"] == 3.0
