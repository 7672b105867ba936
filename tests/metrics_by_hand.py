"""The paper's BWT recomputed from a run's evaluation records, written out independently of
`ccfit.metrics` (a second implementation for the end-to-end tests to compare with)."""

from __future__ import annotations


def bwt_by_hand(records: list[dict], num_tasks: int, steps: int, interval: int) -> dict:
    """{task: D_i} for the earlier tasks with C_i > 0, where C_i is task i's score at the end
    of its stage (global step b_i = (i + 1) * steps) and D_i = 100 * integral over
    [b_i, b_N] of max(0, C_i - R_i) / ((b_N - b_i) * C_i), by trapezoids between evaluation
    points, each point's score taken from the stage that evaluated it last."""
    score: dict[tuple[int, int], float] = {}
    for r in sorted(records, key=lambda r: (r["stage"], r["global_step"])):
        score[(r["task_index"], r["global_step"])] = r["normalized_return"]
    end = num_tasks * steps
    out = {}
    for i in range(num_tasks - 1):
        b = (i + 1) * steps
        learnt = score[(i, b)]
        if learnt <= 0:
            continue
        points = list(range(b, end + 1, interval))
        drop = [max(0.0, learnt - score[(i, g)]) for g in points]
        area = sum((drop[k] + drop[k + 1]) / 2 * interval for k in range(len(points) - 1))
        out[str(i)] = 100 * area / ((end - b) * learnt)
    return out
