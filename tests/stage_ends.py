"""The check that `stages.csv` and a run's metrics.json agree, shared by the tests that make
the report (over fake runs, real smoke curricula and every published run)."""

from __future__ import annotations

import pytest


def assert_stage_ends_are_the_metrics(rows: list[dict], metrics: dict) -> None:
    """`rows` (one run's rows of `stages.csv`): the end of each task's own stage is its
    end-of-task score, and the ends of the last stage are the final scores."""
    assert rows, "the run has no rows in stages.csv"
    end = {(int(r["stage"]), r["task"]): float(r["end"]) for r in rows}
    tasks = list(dict.fromkeys(r["training"] for r in rows))
    assert len(tasks) == len(metrics["end_of_task"])
    assert [end[(i, t)] for i, t in enumerate(tasks)] == pytest.approx(metrics["end_of_task"])
    last = len(tasks) - 1
    assert [end[(last, t)] for t in tasks] == pytest.approx(metrics["final_per_task"])
