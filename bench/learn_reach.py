"""A world model (state obs, `cpu` preset) learning reach-xy online: the evaluation curve,
wall time and CPU time (this process, all threads) as JSON. Target: normalised return >= 80
within 30k env steps.

    python bench/learn_reach.py --model tdmpc2
    python bench/learn_reach.py --model dreamerv3 --steps 30000 -- --model.train_ratio=0.25

Arguments after `--` are `ccfit train` config flags applied on top of the preset.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from ccfit.config import TaskRunConfig
from ccfit.config_parse import parse_cli
from ccfit.train import train_task


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="tdmpc2", help="registered world model")
    parser.add_argument("--task", default="reach-xy")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--eval-interval", type=int, default=1_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="run directory (default: a temp dir)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        cfg = parse_cli(TaskRunConfig, [
            "--task", args.task, "--preset", "cpu", "--obs", "state", "--seed", str(args.seed),
            f"--model.type={args.model}", f"--train.steps={args.steps}",
            f"--train.eval_interval={args.eval_interval}", "--seed_dataset", "null",
            "--out", str(out), *extra,
        ])  # fmt: skip
        start, cpu_start = time.perf_counter(), time.process_time()
        train_task(cfg, progress=False)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    curve = [(r["global_step"], r["normalized_return"], r["success_rate"]) for r in records]
    reached = next((s for s, n, _ in curve if n is not None and n >= 80), None)
    print(json.dumps({
        "task": args.task, "model": args.model, "preset": "cpu", "obs": "state",
        "steps": args.steps, "wall_time_s": wall, "cpu_time_s": cpu,
        "seconds_per_step": wall / args.steps, "cpu_seconds_per_step": cpu / args.steps,
        "first_step_at_or_above_80": reached, "final_normalized_return": curve[-1][1],
        "curve": [{"step": s, "normalized_return": n, "success_rate": p} for s, n, p in curve],
        "config": cfg.to_dict(),
        "target": {"normalized_return": 80, "within_steps": 30_000},
        "cpu_count": os.cpu_count(),
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
