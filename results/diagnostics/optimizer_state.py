"""What keeping the backbone's optimiser state across tasks changes: two sweeps of the same grid
and code, one with `--train.keep_backbone_optimizer=true` (the paper's authors' behaviour), one
without (every task starts fresh optimisers, as the published `cpu` runs).

    python results/diagnostics/optimizer_state.py ../runs/results/reach-tdmpc2-keepopt \\
        ../runs/results/reach-tdmpc2-freshopt > results/diagnostics/optimizer_state.jsonl

The first task of a seed starts fresh in both arms, so its records must agree exactly (checked:
`first_task_identical`); the arms part from the second task on, which makes a per-seed paired
difference meaningful. One JSON line per (model, suite, method): each arm's BWT, forgetting
and FWT (of the seed-averaged curves, with the per-seed values), and per seed the difference
keep minus fresh of BWT, forgetting, FWT, and the mean end-of-task and final scores.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ccdata.errors import InputError, OneLineParser, run_script
from ccfit.report import METRICS_SHOWN, group_metrics, group_runs
from ccfit.report.runs import find_runs


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def _by_method(sweep: Path) -> dict[tuple[str, str, str], list]:
    """(model, suite, method) -> the sweep's finished runs (one group each: one config)."""
    out = {}
    for (backbone, suite, method, _), runs in group_runs(find_runs([sweep])).items():
        if (backbone, suite, method) in out:
            raise InputError(f"{sweep} holds two configs of {backbone}/{suite}/{method}")
        out[(backbone, suite, method)] = runs
    return out


def _first_task(run) -> list[dict]:
    return [r for r in run.records if r.get("stage", r["task_index"]) == 0]


def compare(keep_dir: Path, fresh_dir: Path) -> list[dict]:
    keep, fresh = _by_method(keep_dir), _by_method(fresh_dir)
    lines = []
    for key in sorted(set(keep) & set(fresh)):
        arms = {"keep": keep[key], "fresh": fresh[key]}
        line = {"model": key[0], "suite": key[1], "method": key[2]}
        for arm, runs in arms.items():
            g = group_metrics(runs)
            line[arm] = {name: g[name] for name in METRICS_SHOWN}
            line[arm]["per_seed"] = {
                r.seed: {name: r.metrics.get(source) for name, source in METRICS_SHOWN.items()}
                for r in runs
            }
        paired = {r.seed: r for r in arms["fresh"]}
        line["keep_minus_fresh"] = {}
        line["first_task_identical"] = {}
        for run in arms["keep"]:
            other = paired.get(run.seed)
            if other is None:
                continue
            a, b = run.metrics, other.metrics
            diff = {name: (None if a.get(source) is None or b.get(source) is None
                           else a[source] - b[source])
                    for name, source in METRICS_SHOWN.items()}  # fmt: skip
            diff["mean_end_of_task"] = _mean(a["end_of_task"]) - _mean(b["end_of_task"])
            diff["mean_final"] = _mean(a["final_per_task"]) - _mean(b["final_per_task"])
            line["keep_minus_fresh"][run.seed] = diff
            line["first_task_identical"][run.seed] = _first_task(run) == _first_task(other)
        lines.append(line)
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="optimizer_state.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("keep", type=Path, help="the sweep with keep_backbone_optimizer")
    parser.add_argument("fresh", type=Path, help="the same sweep without it")
    args = parser.parse_args(argv)
    for line in compare(args.keep, args.fresh):
        print(json.dumps(line, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "optimizer_state.py"))
