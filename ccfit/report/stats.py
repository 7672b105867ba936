"""Interval estimates for the report, from rliable (Agarwal et al. 2021): 95% percentile
confidence intervals from its stratified bootstrap over seeds, its probability of improvement
and its interquartile mean.

A group's metric has two conventions. The paper's averages the seeds' curves and then takes
the metric (`curve_interval`: each bootstrap sample of seeds is averaged and measured again);
the other takes each seed's metric and averages those (`mean_interval`). They differ because
BWT and forgetting are not linear in the curves (each task's drop is clipped at 0 and divided
by its end-of-task score), so a seed-averaged curve's BWT may lie outside its seeds' range.

Every estimate is seeded (`BOOTSTRAP_SEED`): a report is the same file each time it is made.
"""

from __future__ import annotations

import contextlib
import functools
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

BOOTSTRAP_REPS = 1000
"""Bootstrap samples per interval."""
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95


@dataclass(frozen=True)
class Interval:
    """A point estimate and its 95% confidence interval (equal bounds for one seed)."""

    value: float
    lo: float
    hi: float

    def cell(self) -> str:
        return f"{self.value:.2f} [{self.lo:.2f}, {self.hi:.2f}]"


@contextlib.contextmanager
def _seeded_bootstrap() -> Iterator[np.random.RandomState]:
    """rliable's stratified bootstraps (1.2) draw their resamples from numpy's global generator,
    whatever `random_state` they are given: seed it for the estimate and put back the caller's
    state. `random_state` is still passed for whatever arch draws itself; rliable hands it on as
    arch's deprecated keyword, which warns."""
    saved = np.random.get_state()
    np.random.seed(BOOTSTRAP_SEED)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield np.random.RandomState(BOOTSTRAP_SEED)
    finally:
        np.random.set_state(saved)


def _estimate(scores, func: Callable, reps: int) -> tuple[float, float, float]:
    """rliable's point estimate and percentile CI of `func` over `scores`: a (seeds x tasks)
    matrix (stratified bootstrap), or a tuple of them (each resampled on its own)."""
    from rliable import library

    with _seeded_bootstrap() as random_state:
        point, ci = library.get_interval_estimates(
            {"x": scores}, func, reps=reps, confidence_interval_size=CONFIDENCE,
            random_state=random_state,
        )  # fmt: skip
    lo, hi = np.asarray(ci["x"], dtype=float).reshape(2)
    return float(np.asarray(point["x"]).reshape(-1)[0]), float(lo), float(hi)


def mean_interval(values: Sequence[float]) -> Interval | None:
    """The mean of per-seed values with its CI; None without any value."""
    if not values:
        return None
    scores = np.asarray(values, dtype=float).reshape(-1, 1)  # seeds x one task
    if len(values) == 1:
        return Interval(float(scores[0, 0]), float(scores[0, 0]), float(scores[0, 0]))
    return Interval(*_estimate(scores, lambda s: np.array([np.mean(s)]), BOOTSTRAP_REPS))


def curve_interval(seeds: int, metric: Callable[[tuple[int, ...]], float | None]
                   ) -> Interval | None:  # fmt: skip
    """The paper's convention with its CI: `metric(indices)` is the metric of the curves of
    the seeds at `indices` (with repeats) averaged; bootstrapped over seeds by resampling the
    indices. None where the metric of all seeds is undefined; an interval with NaN bounds where
    it is defined but some resample's is not."""

    @functools.cache
    def measured(multiset: tuple[int, ...]) -> float:
        value = metric(multiset)
        return math.nan if value is None else float(value)

    def of_sample(s: np.ndarray) -> np.ndarray:
        # A resample is a multiset of seeds: its order does not change the average.
        return np.array([measured(tuple(sorted(int(i) for i in s[:, 0])))])

    whole = measured(tuple(range(seeds)))
    if math.isnan(whole):
        return None
    if seeds == 1:
        return Interval(whole, whole, whole)
    value, lo, hi = _estimate(np.arange(seeds, dtype=float).reshape(-1, 1), of_sample,
                              BOOTSTRAP_REPS)  # fmt: skip
    return Interval(value, lo, hi)


@functools.cache
def _improvement(better: tuple[float, ...], worse: tuple[float, ...]) -> Interval:
    from rliable import metrics

    @functools.cache
    def of_multisets(x: tuple[float, ...], y: tuple[float, ...]) -> float:
        return float(metrics.probability_of_improvement(np.reshape(x, (-1, 1)),
                                                        np.reshape(y, (-1, 1))))  # fmt: skip

    def of_sample(x: np.ndarray, y: np.ndarray) -> float:
        # The statistic depends on each side's multiset of seeds only (Mann-Whitney's U is
        # rank-based): a few seeds give few distinct samples.
        return of_multisets(tuple(sorted(x[:, 0])), tuple(sorted(y[:, 0])))

    x = np.asarray(better, dtype=float).reshape(-1, 1)
    y = np.asarray(worse, dtype=float).reshape(-1, 1)
    return Interval(*_estimate((x, y), of_sample, BOOTSTRAP_REPS))


def probability_of_improvement(x: Sequence[float], y: Sequence[float], lower_is_better: bool
                               ) -> Interval | None:  # fmt: skip
    """P(a seed of X scores better than a seed of Y) (ties count half), with its CI; None
    unless both have values. BWT and forgetting: lower is better."""
    if not x or not y:
        return None
    sign = -1.0 if lower_is_better else 1.0
    return _improvement(tuple(sign * v for v in x), tuple(sign * v for v in y))


def iqm_interval(scores: np.ndarray) -> Interval:
    """The interquartile mean of a (seeds x tasks) score matrix with its stratified CI."""
    from rliable import metrics

    def iqm(s: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(s)])

    return Interval(*_estimate(np.asarray(scores, dtype=float), iqm, BOOTSTRAP_REPS))


def _finite_or_none(x: float | None) -> float | None:
    # A bound is NaN where some bootstrap sample's metric is undefined; JSON has no NaN.
    return None if x is None or not math.isfinite(x) else x


def metric_fields(
    name: str, value: float | None, curve_ci: Interval | None, by_seed: dict[int, float | None]
) -> dict:
    """What a report's group holds of one metric: `value` (of the seed-averaged curves) and its
    `curve_ci` (`curve_interval`), the mean of the defined per-seed values `by_seed` and its CI,
    their min and max, how many seeds define it, and the per-seed values themselves."""
    values = [v for v in by_seed.values() if v is not None]
    seed_mean = mean_interval(values)
    out = {name: value, f"{name}_seed_mean": seed_mean.value if seed_mean else None,
           f"{name}_min": min(values) if values else None,
           f"{name}_max": max(values) if values else None,
           f"{name}_seeds_defined": len(values), f"{name}_per_seed": dict(by_seed)}  # fmt: skip
    for suffix, interval in (("", curve_ci), ("_seed_mean", seed_mean)):
        out[f"{name}{suffix}_lo"] = _finite_or_none(interval and interval.lo)
        out[f"{name}{suffix}_hi"] = _finite_or_none(interval and interval.hi)
    return out
