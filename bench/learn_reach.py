"""TD-MPC2 (state obs, `cpu` preset) learning reach-xy online: the evaluation curve and wall time
as JSON. Target: normalised return >= 80 within 30k env steps in about 30 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from ccfit.config import RunConfig, TrainConfig
from ccfit.train import model_config, train_task


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", default="reach-xy")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="run directory (default: a temp dir)")
    args = parser.parse_args()
    train = TrainConfig.preset("cpu", steps=args.steps, seed=args.seed, obs="state")
    run = RunConfig(task=args.task, model="tdmpc2", model_config=model_config(
        "tdmpc2", "cpu", "state"), train=train)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        start = time.perf_counter()
        train_task(run, out, progress=False)
        wall = time.perf_counter() - start
        records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    curve = [(r["global_step"], r["normalized_return"], r["success_rate"]) for r in records]
    reached = next((s for s, n, _ in curve if n is not None and n >= 80), None)
    print(json.dumps({
        "task": args.task,
        "preset": "cpu",
        "obs": "state",
        "steps": args.steps,
        "wall_time_s": wall,
        "seconds_per_step": wall / args.steps,
        "first_step_at_or_above_80": reached,
        "final_normalized_return": curve[-1][1],
        "curve": [{"step": s, "normalized_return": n, "success_rate": p} for s, n, p in curve],
        "train_config": run.to_dict()["train"],
        "target": {"normalized_return": 80, "within_steps": 30_000},
        "cpu_count": os.cpu_count(),
    }, indent=2))


if __name__ == "__main__":
    main()
