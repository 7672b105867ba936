"""The benchmark's continual-learning metrics (FACTS section 3) and a few standard ones.

A *curve* is a pair ``(steps, scores)``: the global training steps at which a task was
evaluated (strictly increasing) and its normalised returns there (floor 0, oracle 100, not
capped). Between checkpoints a curve is linear (``np.interp``); every integral is the
trapezoidal rule over the checkpoints inside the interval plus its two ends (whose values are
interpolated when they are not checkpoints). Curves are never extrapolated: an interval that
a curve does not cover is a ValueError.

Average seeds with `average_curves` *before* computing a metric, as the paper does.

Main metrics:
- `bwt`: the paper's forgetting score D_i averaged over learnt earlier tasks (lower is better).
- `fwt`: the paper's forward transfer on the final composition task (higher is better).
Beside them:
- `lopez_paz_bwt` (Lopez-Paz & Ranzato 2017) from `performance_matrix`;
- `cw_forgetting` and `cw_forward_transfer` (Continual World, Wolczyk et al. 2021).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

Curve = tuple[Sequence[float], Sequence[float]]
"""(steps, scores): evaluation checkpoints (strictly increasing) and normalised returns."""


# ----------------------------------------------------------------------------- helpers


def _as_curve(curve: Curve, name: str = "curve") -> tuple[np.ndarray, np.ndarray]:
    try:
        steps, scores = curve
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (steps, scores)") from None
    steps = np.asarray(steps, dtype=np.float64).reshape(-1)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if steps.size == 0:
        raise ValueError(f"{name} is empty")
    if steps.shape != scores.shape:
        raise ValueError(f"{name}: {steps.size} steps but {scores.size} scores")
    if not (np.all(np.isfinite(steps)) and np.all(np.isfinite(scores))):
        raise ValueError(f"{name}: steps and scores must be finite")
    if np.any(np.diff(steps) <= 0):
        raise ValueError(f"{name}: steps must be strictly increasing")
    return steps, scores


def _check_covers(steps: np.ndarray, lo: float, hi: float, name: str) -> None:
    if steps[0] > lo or steps[-1] < hi:
        raise ValueError(
            f"{name} covers steps [{steps[0]:g}, {steps[-1]:g}] but the metric needs "
            f"[{lo:g}, {hi:g}]; curves are not extrapolated (evaluate at both ends)"
        )


def value_at(curve: Curve, step: float) -> float:
    """The curve's score at `step`, linearly interpolated between checkpoints."""
    steps, scores = _as_curve(curve)
    _check_covers(steps, step, step, "curve")
    return float(np.interp(step, steps, scores))


def _knots(steps: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Integration points on [lo, hi]: both ends plus the checkpoints strictly inside."""
    inside = steps[(steps > lo) & (steps < hi)]
    return np.concatenate(([lo], inside, [hi]))


def rebase(curve: Curve, start: float) -> tuple[np.ndarray, np.ndarray]:
    """Shift a curve so that global step `start` becomes 0; checkpoints before it are dropped.

    Used to take a task's curve out of a curriculum (start = the step its training began) so
    it can be compared with a from-scratch run of the same task.
    """
    steps, scores = _as_curve(curve)
    keep = steps >= start
    if not np.any(keep):
        raise ValueError(f"curve has no checkpoint at or after step {start:g}")
    return steps[keep] - start, scores[keep]


def average_curves(curves: Sequence[Curve]) -> tuple[np.ndarray, np.ndarray]:
    """Mean over seeds of several curves of the same task.

    Identical checkpoints (the normal case: a fixed evaluation interval) give the plain
    pointwise mean. Otherwise every curve is linearly interpolated onto a common grid: the
    union of all checkpoints inside the range every curve covers, [max of first steps, min of
    last steps]; parts covered by only some seeds are dropped rather than extrapolated.
    """
    if len(curves) == 0:
        raise ValueError("average_curves needs at least one curve")
    parsed = [_as_curve(c, f"curve {k}") for k, c in enumerate(curves)]
    first = parsed[0][0]
    if all(s.shape == first.shape and np.array_equal(s, first) for s, _ in parsed):
        return first.copy(), np.mean([y for _, y in parsed], axis=0)
    lo = max(s[0] for s, _ in parsed)
    hi = min(s[-1] for s, _ in parsed)
    if lo > hi:
        raise ValueError(
            f"curves share no common step range (latest start {lo:g} > earliest end {hi:g})"
        )
    grid = np.unique(np.concatenate([s[(s >= lo) & (s <= hi)] for s, _ in parsed]))
    return grid, np.mean([np.interp(grid, s, y) for s, y in parsed], axis=0)


def _check_task_ends(task_ends: Sequence[float], n: int) -> np.ndarray:
    ends = np.asarray(task_ends, dtype=np.float64).reshape(-1)
    if ends.size != n:
        raise ValueError(f"{n} curves but {ends.size} task ends")
    if not np.all(np.isfinite(ends)) or np.any(np.diff(ends) <= 0):
        raise ValueError("task_ends must be finite and strictly increasing")
    return ends


# ----------------------------------------------------------------------------- paper metrics


@dataclass(frozen=True)
class BWTResult:
    """The paper's backward-transfer (forgetting) score and its parts."""

    value: float
    """Mean of D_i over the included tasks, in [0, 100] while returns stay above the floor;
    NaN when no earlier task qualifies (see `reason`). Lower is better."""
    per_task: dict[int, float]
    """D_i for each included task i (earlier tasks with C_i > floor)."""
    learnt: dict[int, float]
    """C_i = R_i(b_i), the score when task i's training ended, for every earlier task."""
    excluded: dict[int, str] = field(default_factory=dict)
    """Earlier tasks left out of the mean, with the reason."""
    reason: str | None = None
    """Why `value` is NaN, else None."""

    def __float__(self) -> float:
        return self.value


def bwt(curves: Sequence[Curve], task_ends: Sequence[float], floor: float = 0.0) -> BWTResult:
    """The paper's BWT: how much earlier tasks are forgotten after their training ends.

    curves[i] is task i's curve over global steps (evaluated with its stored heads on the
    current backbone); task_ends[i] = b_i, the step at which task i's training ended. With
    C_i = R_i(b_i):

        D_i = 100 * int_{b_i}^{b_N} max(0, C_i - R_i(s)) ds / ((b_N - b_i) * (C_i - floor))
        BWT = mean of D_i over { i < N : C_i > floor }

    Integration choice: max(0, .) is applied at each integration point (b_i, the checkpoints
    in between, b_N) and then the trapezoidal rule is used. Where the curve crosses C_i
    between two checkpoints this counts more forgetting than the exact integral of the
    interpolated curve's positive part (e.g. +20 then -20 over 10 steps: 100 here, 50 exact).
    D_i can exceed 100 only if a return drops below the floor. The last task (i = N-1) has no
    forgetting interval and is never included. No earlier task learnt -> value NaN and
    `reason` says so.
    """
    if len(curves) == 0:
        raise ValueError("bwt needs at least one task curve")
    parsed = [_as_curve(c, f"curve of task {i}") for i, c in enumerate(curves)]
    ends = _check_task_ends(task_ends, len(parsed))
    b_last = ends[-1]
    per_task: dict[int, float] = {}
    learnt: dict[int, float] = {}
    excluded: dict[int, str] = {}
    for i, (steps, scores) in enumerate(parsed[:-1]):
        b_i = ends[i]
        _check_covers(steps, b_i, b_last, f"curve of task {i}")
        c_i = float(np.interp(b_i, steps, scores))
        learnt[i] = c_i
        if not c_i > floor:
            excluded[i] = f"never learnt: C_i = {c_i:g} <= floor {floor:g}"
            continue
        s = _knots(steps, b_i, b_last)
        drop = np.maximum(0.0, c_i - np.interp(s, steps, scores))
        per_task[i] = float(100.0 * np.trapezoid(drop, s) / ((b_last - b_i) * (c_i - floor)))
    if per_task:
        return BWTResult(float(np.mean(list(per_task.values()))), per_task, learnt, excluded)
    reason = (
        "only one task: no earlier task to forget"
        if len(parsed) == 1
        else f"no earlier task was learnt (every C_i <= floor {floor:g})"
    )
    return BWTResult(math.nan, per_task, learnt, excluded, reason)


def fwt(seq_curve: Curve, scratch_curve: Curve, budget: float) -> float:
    """The paper's FWT on the final composition task (higher is better).

        FWT = (1/T) * int_0^T (R_seq(t) - R_scr(t)) dt,  T = budget

    seq_curve is the task's curve during its place in the curriculum, already rebased so its
    training starts at 0 (see `rebase`); scratch_curve is the same task learnt from scratch.
    Both are interpolated linearly onto the union of their checkpoints in [0, T] (plus 0 and
    T) and integrated by the trapezoidal rule. Both must cover [0, T]; points past T are
    ignored. The result is in score units (normalised return points).
    """
    if not (np.isfinite(budget) and budget > 0):
        raise ValueError(f"budget must be a positive number of steps, got {budget!r}")
    s_seq, y_seq = _as_curve(seq_curve, "seq_curve")
    s_scr, y_scr = _as_curve(scratch_curve, "scratch_curve")
    _check_covers(s_seq, 0.0, budget, "seq_curve (rebased to 0)")
    _check_covers(s_scr, 0.0, budget, "scratch_curve")
    grid = _knots(np.union1d(s_seq, s_scr), 0.0, float(budget))
    diff = np.interp(grid, s_seq, y_seq) - np.interp(grid, s_scr, y_scr)
    return float(np.trapezoid(diff, grid) / budget)


# ----------------------------------------------------------------------------- standard metrics


def performance_matrix(curves: Sequence[Curve], task_ends: Sequence[float]) -> np.ndarray:
    """R[j, i] = score of task i when task j's training ended (R_i(b_j)); NaN where task i's
    curve does not reach b_j (typically j < i, before task i had heads)."""
    parsed = [_as_curve(c, f"curve of task {i}") for i, c in enumerate(curves)]
    ends = _check_task_ends(task_ends, len(parsed))
    out = np.full((len(parsed), len(parsed)), np.nan)
    for i, (steps, scores) in enumerate(parsed):
        for j, b_j in enumerate(ends):
            if steps[0] <= b_j <= steps[-1]:
                out[j, i] = np.interp(b_j, steps, scores)
    return out


def lopez_paz_bwt(matrix: np.ndarray) -> float:
    """Lopez-Paz & Ranzato (2017): mean_{i < T} (R[T, i] - R[i, i]) with T the last task.

    Negative means forgetting (the opposite sign convention to `bwt`). In score units. NaN
    with a single task.
    """
    r = np.asarray(matrix, dtype=np.float64)
    if r.ndim != 2 or r.shape[0] != r.shape[1]:
        raise ValueError(f"performance matrix must be square, got shape {r.shape}")
    t = r.shape[0]
    if t < 2:
        return math.nan
    diffs = r[-1, :-1] - np.diag(r)[:-1]
    if np.any(np.isnan(diffs)):
        raise ValueError("performance matrix lacks R[i, i] or R[T, i] for some earlier task")
    return float(np.mean(diffs))


@dataclass(frozen=True)
class ForgettingResult:
    """Continual World forgetting."""

    value: float
    """Mean of F_i over earlier tasks (NaN with a single task). Higher = more forgetting."""
    per_task: dict[int, float]
    """F_i = p_i(b_i) - p_i(b_N) in score units, for each task i < N-1."""

    def __float__(self) -> float:
        return self.value


def cw_forgetting(curves: Sequence[Curve], task_ends: Sequence[float]) -> ForgettingResult:
    """Continual World (Wolczyk et al. 2021) forgetting F_i = p_i(end of i) - p_i(end).

    Reported in score units (normalised return points), not rescaled: it equals minus the
    per-task term of `lopez_paz_bwt`.
    """
    r = performance_matrix(curves, task_ends)
    per_task = {}
    for i in range(r.shape[0] - 1):
        if np.isnan(r[i, i]) or np.isnan(r[-1, i]):
            raise ValueError(f"curve of task {i} does not cover its end and the last task's end")
        per_task[i] = float(r[i, i] - r[-1, i])
    value = float(np.mean(list(per_task.values()))) if per_task else math.nan
    return ForgettingResult(value, per_task)


def cw_forward_transfer(
    seq_curve: Curve,
    scratch_curve: Curve,
    budget: float,
    scale: float = 100.0,
    clip: bool = True,
) -> float:
    """Continual World forward transfer FT = (AUC - AUC_b) / (1 - AUC_b) for one task.

    AUC = (1/T) int_0^T p(t) dt of the task learnt in the curriculum (rebased to 0) and AUC_b
    of the from-scratch reference, over the same budget T, trapezoidal on each curve's own
    checkpoints. Continual World uses success rates in [0, 1]; normalised returns are mapped
    to that range as p = score / scale (scale 100 = the oracle) and, with `clip`, clipped to
    [0, 1], since returns above the oracle would otherwise let 1 - AUC_b reach 0 or below.
    NaN when AUC_b == 1 (the reference is perfect throughout: transfer is undefined).
    """
    if not (np.isfinite(budget) and budget > 0):
        raise ValueError(f"budget must be a positive number of steps, got {budget!r}")
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale!r}")

    def auc(curve: Curve, name: str) -> float:
        steps, scores = _as_curve(curve, name)
        _check_covers(steps, 0.0, budget, name)
        grid = _knots(steps, 0.0, float(budget))
        p = np.interp(grid, steps, scores) / scale
        if clip:
            p = np.clip(p, 0.0, 1.0)
        return float(np.trapezoid(p, grid) / budget)

    a_seq = auc(seq_curve, "seq_curve (rebased to 0)")
    a_ref = auc(scratch_curve, "scratch_curve")
    if a_ref >= 1.0:
        return math.nan
    return (a_seq - a_ref) / (1.0 - a_ref)


# ================================================================ from run records


def task_curves(records: list[dict], num_tasks: int, key: str = "normalized_return"
                ) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """Per task (steps, scores): the records' `key` (normalised returns online, the prediction
    score offline). A task's record at its last step is taken after the method's end of task
    (e.g. PackNet's prune and retraining); should one step be logged twice, the later stands."""
    curves = []
    for t in range(num_tasks):
        by_step: dict[int, float] = {}
        for r in records:
            if r["task_index"] == t and r[key] is not None:
                by_step[int(r["global_step"])] = float(r[key])
        steps = np.array(sorted(by_step), dtype=np.float64)
        curves.append((steps, np.array([by_step[int(s)] for s in steps])))
    return curves


def compute_metrics(records: list[dict], scratch: list[dict], num_tasks: int,
                    steps_per_task: int, key: str = "normalized_return") -> dict:  # fmt: skip
    """The paper's BWT and FWT plus Lopez-Paz BWT and Continual World metrics, one run, of the
    records' `key` (see `task_curves`)."""
    curves = task_curves(records, num_tasks, key)
    if any(len(c[0]) == 0 for c in curves):
        raise ValueError(
            "normalised returns missing: run `ccdata references` first"
            if key == "normalized_return"
            else f"no {key!r} in some task's records"
        )
    ends = [(i + 1) * steps_per_task for i in range(num_tasks)]
    scratch_curve = task_curves(scratch, num_tasks, key)[-1]
    check_evaluated(curves, ends, scratch_curve, steps_per_task)
    return metrics_from_curves(curves, ends, scratch_curve, steps_per_task)


def check_evaluated(curves, ends, scratch_curve, budget: float) -> None:
    """Raises ValueError unless each score the metrics read at a stage boundary was evaluated
    there, not interpolated between evaluations on either side of it: task i's at its stage's
    start (0 or b_{i-1}; the last task's FWT curve starts there) and at every b_j with j >= i
    (C_i, the performance matrix, the final scores), the reference's at 0 and at the budget.
    A run logs all of them (each task seen is evaluated at every task's end, the new task at
    its stage's step 0), so one missing means records lost from its metrics.jsonl."""
    for i, (steps, _) in enumerate(curves):
        for step in [ends[i - 1] if i else 0, *ends[i:]]:
            if not np.any(steps == step):
                raise ValueError(f"task {i} has no evaluation at global step {step:g}, where "
                                 f"the metrics read its score (records lost?)")  # fmt: skip
    for step in (0, budget):
        if not np.any(scratch_curve[0] == step):
            raise ValueError(f"the from-scratch reference has no evaluation at step {step:g}, "
                             f"where FWT reads its score (records lost?)")  # fmt: skip


def metrics_from_curves(curves, ends, scratch_curve, budget: float) -> dict:
    n = len(curves)
    bwt_result = bwt(curves, ends)
    seq = rebase(curves[-1], ends[-1] - budget)
    matrix = performance_matrix(curves, ends)
    forgetting_result = cw_forgetting(curves, ends)
    return {
        "bwt": _finite(float(bwt_result)),
        "bwt_per_task": {str(i): _finite(d) for i, d in bwt_result.per_task.items()},
        "bwt_excluded": {str(i): why for i, why in bwt_result.excluded.items()},
        "fwt": _finite(fwt(seq, scratch_curve, budget)),
        "final_per_task": [_finite(x) for x in matrix[-1]],
        "end_of_task": [_finite(matrix[i, i]) for i in range(n)],
        "lopez_paz_bwt": _finite(lopez_paz_bwt(matrix)),
        "cw_forgetting": _finite(float(forgetting_result)),
        "cw_forward_transfer": _finite(cw_forward_transfer(seq, scratch_curve, budget)),
        "task_ends": list(ends),
        "budget": budget,
    }


def _finite(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None
