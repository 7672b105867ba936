"""Seconds to make a task's environment: a copy of the scene this process compiled already,
against compiling it from its file. Prints JSON.

    python bench/env_make.py --tasks reach-xy,pick-cube --rounds 5

A run makes an environment per evaluation episode (40 per task for the end-of-task score);
`SceneEnv._initialize_simulation` compiles each scene once per process and copies it. The two
ways alternate, one make each per round, state only (no renderer), in one process; medians.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import ccdata  # noqa: E402
from ccdata.tasks import base  # noqa: E402


def make_seconds(task_id: str, fresh: bool) -> float:
    if fresh:
        base._COMPILED.clear()
    start = time.perf_counter()
    env = ccdata.make_env(task_id, render=False)
    elapsed = time.perf_counter() - start
    env.close()
    return elapsed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="reach-xy,pick-cube,bin-red-blue,drawer-pnp")
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args()
    out = {"machine": platform.processor() or platform.machine(), "rounds": args.rounds,
           "tasks": {}}  # fmt: skip
    for task in args.tasks.split(","):
        make_seconds(task, fresh=False)  # the first compile, and imports
        times: dict[str, list[float]] = {"compiled": [], "copied": []}
        for _ in range(args.rounds):
            times["compiled"].append(make_seconds(task, fresh=True))
            times["copied"].append(make_seconds(task, fresh=False))
        medians = {f"{k}_s": round(statistics.median(v), 4) for k, v in times.items()}
        ratio = medians["compiled_s"] / medians["copied_s"]
        out["tasks"][task] = {**medians, "compiled_over_copied": round(ratio, 2)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
