"""What sharing first tasks (`ccfit sweep`'s default) saved a sweep, from the sweep's own cost
records. Prints JSON.

    python bench/first_task.py ../runs/results/grasp-dreamerv3-3s

Each shared first task (`RUNS/first/<key>/first.json`) records what training it cost and who
trained it; each run that started from it says so (`first_task.json`). Without sharing, every
such run would have trained it, where once was done, so the sweep would have cost its CPU
seconds (runs', references' and shared first tasks' `cost.json`; a shared first task that a
run's process trained is counted in that run's) plus (runs started from it - 1) x its cost. The
ratio is that over what it cost, for the whole sweep (references and runs without a shared
first task included) and for each shared first task's runs. Counted over what has a cost so
far: a sweep part-way gives its ratios so far.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ccfit.first_task import FIRST, FIRST_DONE, FIRST_RECORD
from ccfit.run_files import COST, SCRATCH, SWEEP_JSON


def _cpu_s(path: Path) -> float:
    return float(json.loads(path.read_text())["cpu_s"]) if path.is_file() else 0.0


def saving(root: Path) -> dict:
    """The sweep in `root`: its CPU seconds, those its shared first tasks saved, the ratio."""
    runs = [p.parent for p in sorted(root.glob(f"*/{COST}"))]
    spent = sum(_cpu_s(r / COST) for r in runs)
    spent += sum(_cpu_s(p) for p in sorted((root / SCRATCH).glob(f"*/{COST}")))
    started: dict[str, list[float]] = {}
    for run in runs:
        if (run / FIRST_RECORD).is_file():
            name = json.loads((run / FIRST_RECORD).read_text())["shared"]
            started.setdefault(name, []).append(_cpu_s(run / COST))
    shared = []
    for done in sorted((root / FIRST).glob(f"*/{FIRST_DONE}")):
        record = json.loads(done.read_text())
        cpu_s = float((record.get("cost") or {}).get("cpu_s") or 0.0)
        costs = started.get(done.parent.name, [])
        saved_s = max(len(costs) - 1, 0) * cpu_s
        # its runs' CPU seconds and the shared training's, counted once
        with_it = sum(costs)
        if record.get("trained_by") == "job":
            spent += cpu_s
            with_it += cpu_s
        shared.append({"shared": done.parent.name, "cpu_s": cpu_s, "runs": len(costs),
                       "trained_by": record.get("trained_by", "run"), "runs_cpu_s": with_it,
                       "saved_cpu_s": saved_s,
                       "runs_without_over_with": round((with_it + saved_s) / with_it, 3)
                       if with_it else None})  # fmt: skip
    saved = sum(s["saved_cpu_s"] for s in shared)
    return {
        "sweep": root.name,
        "runs_with_cost": len(runs),
        "cpu_h": round(spent / 3600, 3),
        "saved_cpu_h": round(saved / 3600, 3),
        "without_sharing_over_with": round((spent + saved) / spent, 3) if spent else None,
        "shared_first_tasks": shared,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, help="a sweep's folder (`ccfit sweep --out`)")
    args = p.parse_args(argv)
    if not (args.runs / SWEEP_JSON).is_file():
        print(f"error: {args.runs} holds no sweep ({SWEEP_JSON} missing)", file=sys.stderr)
        return 2
    print(json.dumps(saving(args.runs), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
