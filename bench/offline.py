"""Wall and CPU time of a suite's offline curriculum (`ccfit fit`), per observation mode.
Prints JSON.

    nice python bench/offline.py --obs state --model dreamerv3 --preset cpu

Each mode runs `ccfit fit --suite SUITE --preset PRESET --obs MODE --model.type=MODEL
--method.type=METHOD` in a fresh interpreter from an empty folder, so the from-scratch
reference is fitted too and the dataset is read from LeRobot's cache (`ccdata generate --suite
SUITE` makes it; nothing is generated here). Wall time is the command's; CPU time is what it
used (one torch thread: the `fit.torch_threads` default), so "cpu_min" is minutes of one core.
Beside the times: updates run (the tasks' and the reference's, PackNet's retraining aside),
CPU milliseconds per update, the end-of-task scores, BWT and FWT.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path


def run_one(obs: str, args) -> dict:
    out = Path(args.out) / obs
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cmd = [sys.executable, "-m", "ccfit.cli", "fit", "--suite", args.suite, "--preset",
           args.preset, "--obs", obs, "--seed", str(args.seed), f"--model.type={args.model}",
           f"--method.type={args.method}", "--out", str(out / "run"), "--scratch-root",
           str(out / "scratch"), "--quiet", *args.extra]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else
                f"exit {proc.returncode}", "wall_s": round(wall, 1)}  # fmt: skip
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    metrics = json.loads((out / "run" / "metrics.json").read_text())
    config = json.loads((out / "run" / "config.json").read_text())
    updates = config["fit"]["updates"] * (len(metrics["task_ends"]) + 1)
    return {
        "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "cpu_min": round(cpu / 60, 2),
        "updates": updates, "cpu_ms_per_update": round(1000 * cpu / updates, 1),
        "measurement_space": metrics["measurement_space"],
        "end_of_task": [round(x, 2) for x in metrics["end_of_task"]],
        "final_per_task": [round(x, 2) for x in metrics["final_per_task"]],
        "bwt": metrics["bwt"], "bwt_excluded": metrics["bwt_excluded"], "fwt": metrics["fwt"],
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--obs", default="state,pixels", help="modes, comma-separated")
    parser.add_argument("--suite", default="Reach")
    parser.add_argument("--model", default="dreamerv3")
    parser.add_argument("--method", default="ft")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="/tmp/ccfit-bench-offline", help="scratch folder")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[],
                        help="more `ccfit fit` options (last)")  # fmt: skip
    args = parser.parse_args()
    result = {"suite": args.suite, "model": args.model, "method": args.method,
              "preset": args.preset, "cpus": os.cpu_count()}  # fmt: skip
    for obs in args.obs.split(","):
        result[obs] = run_one(obs, args)
        print(json.dumps({obs: result[obs]}), file=sys.stderr, flush=True)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
