"""Why ER transfers less than FT to a composition task (TD-MPC2): replay while it trains, or the
state ER reaches it in?

    ccfit run --suite Grasp --preset cpu --method.type=er --seed 2 --keep-stages \
        --out RUNS/grasp-er-s2 --scratch-root SWEEP/scratch
    ccfit run --suite Grasp --preset cpu --method.type=er --seed 2 --method.replay_ratio=0 \
        --out RUNS/grasp-er-s2-noreplay-after2 --branch-from RUNS/grasp-er-s2 --branch-after 2 \
        --scratch-root SWEEP/scratch
    python results/diagnostics/er_branch.py RUNS/grasp-er-s2 \
        RUNS/grasp-er-s2-noreplay-after2 SWEEP/Grasp-tdmpc2-ft-state-cpu-s2 \
        > results/diagnostics/grasp_er_branch.jsonl

The branch is the ER run up to the end of the task before the composition (the same weights,
stored heads, kept windows and RNG) and trains the composition without replaying them
(`replay_ratio` 0, so ER's penalty is zero and draws nothing). If it learns the composition as
FT does, the replay's share of every update is what slows ER; if as ER does, the backbone ER
hands to it is. A branch after the first task (`--branch-after 1`) trains as FT does
(`tests/test_branch.py`): FT made on the machine that made the ER run, where a published FT
run was made on another kind of CPU (`drawerpnp_er_branch.jsonl`; its commands are in
`results/diagnostics/README.md`). One JSON line per run: the composition task's curve while it
trains (task steps of the first evaluation at 50 and at 80, mean of the last 21 evaluations,
its end-of-task score), the mean score of each earlier task while it trains, the run's FWT
and Continual World forward transfer; then one line per from-scratch reference.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ccdata.errors import OneLineParser, run_script
from ccfit.analysis.learnability import first_step_at
from ccfit.io import read_run_json

LAST = 21
"""Evaluations averaged at the end of the task (the last 20 000 steps at a 1000-step interval,
and the end-of-task evaluation)."""


def curve_summary(records: list[dict]) -> dict:
    """The statistics of one task's curve (its own records, in task-step order)."""
    records = sorted(records, key=lambda r: r["task_step"])
    last = [r["normalized_return"] for r in records[-LAST:]]
    return {
        "evaluations": len(records),
        "first_at_50": first_step_at(records, 50.0),
        "first_at_80": first_step_at(records, 80.0),
        f"mean_last_{LAST}": sum(last) / len(last),
        "end_of_task": records[-1]["normalized_return"],
    }


def summarise(run: Path) -> tuple[dict, Path]:
    """The run's line, and its from-scratch reference's directory."""
    leave_out = "this diagnostic"
    metrics = read_run_json(run / "metrics.json", leave_out=leave_out)
    config = read_run_json(run / "config.json", leave_out=leave_out)
    records = read_run_json(run / "metrics.jsonl", lines=True, leave_out=leave_out)
    last = max(r["task_index"] for r in records)
    own = [r for r in records if r["task_index"] == last and r["stage"] == last]
    earlier: dict[str, list[float]] = {}
    for r in records:
        if r["stage"] == last and r["task_index"] < last:
            earlier.setdefault(r["task"], []).append(r["normalized_return"])
    line = {
        "run": run.name,
        "earlier_while_it_trains": {t: sum(v) / len(v) for t, v in earlier.items()},
        "method": config["method"],
        "branch": config.get("resolved_branch"),
        "task": own[0]["task"],
        **curve_summary(own),
        "fwt": metrics["fwt"],
        "cw_forward_transfer": metrics["cw_forward_transfer"],
    }
    return line, Path(metrics["scratch_dir"])


def main(argv: list[str] | None) -> None:
    parser = OneLineParser(prog="er_branch.py", description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="finished curriculum run directories")
    args = parser.parse_args(argv)
    references: dict[str, Path] = {}
    for run in args.runs:
        line, scratch = summarise(run)
        references.setdefault(scratch.name, scratch)
        print(json.dumps(line, sort_keys=True))
    for name, scratch in references.items():
        records = read_run_json(scratch / "metrics.jsonl", lines=True,
                                leave_out="this diagnostic")  # fmt: skip
        print(json.dumps({"run": name, "reference": True, **curve_summary(records)},
                         sort_keys=True))  # fmt: skip


if __name__ == "__main__":
    sys.exit(run_script(main, "er_branch.py"))
