"""Compiled updates of jobs side by side (a sweep's `--max-parallel`, one thread each) when the
compile cache was filled by a process with more threads: Inductor writes the thread count into
its CPU kernels and torch 2.11 leaves it out of the cache key (pytorch#160812), so the jobs
load kernels that spin more OpenMP threads than they have cores. `pin_inductor_threads` (what
`compile_hot_paths` does) keys the count. Prints JSON: the median update (TD-MPC2, `cpu`,
state, synthetic batch) of each of `--jobs` simultaneous one-thread processes, without and
with the pin, in alternating rounds, over a fresh cache that a `--fill-threads` process filled.

    python bench/inductor_threads.py                     # 2 jobs, cache filled at 2 threads
    python bench/inductor_threads.py --jobs 2 --rounds 3 --updates 300
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

_JOB = """
import json, statistics, sys, time, torch
threads, pin, updates = int(sys.argv[1]), sys.argv[2] == "pin", int(sys.argv[3])
torch.set_num_threads(threads)
sys.path.insert(0, {bench!r})
import torch._inductor.config
from update_rate import synthetic_batch
from ccfit.models import make_model
from ccfit.models.registry import config_class
from ccfit.train.compiled import compile_hot_paths
from ccfit.train.update import UpdateStep
cfg = config_class("tdmpc2").preset("cpu", obs_mode="state")
torch.manual_seed(0)
model = make_model(cfg, torch.device("cpu"))
model.begin_task(0, 1000)
heads = model.new_heads()
batch = synthetic_batch(cfg, torch.Generator().manual_seed(0))
compile_hot_paths(model, "on")
if not pin:  # torch's default: the count is read when compiling and not keyed
    torch._inductor.config.cpp.threads = -1
step = UpdateStep(model, heads)
for _ in range(10):
    step(batch)
times = []
for _ in range(updates):
    start = time.perf_counter()
    step(batch)
    times.append(time.perf_counter() - start)
print(json.dumps(statistics.median(times) * 1e3))
"""


def run_jobs(script: str, env: dict, threads: int, pin: bool, updates: int, jobs: int
             ) -> list[float]:  # fmt: skip
    """Median update (ms) of each of `jobs` processes started together."""
    mode = "pin" if pin else "default"
    procs = [subprocess.Popen([sys.executable, "-c", script, str(threads), mode, str(updates)],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(jobs)]  # fmt: skip
    done = [p.communicate() for p in procs]
    for p, (_, err) in zip(procs, done, strict=True):
        if p.returncode:  # a bug in the job: its own traceback
            raise RuntimeError(f"a job exited with {p.returncode}:\n{err[-3000:]}")
    return [round(json.loads(out.strip().splitlines()[-1]), 2) for out, _ in done]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--jobs", type=int, default=2, help="one-thread processes side by side")
    p.add_argument("--fill-threads", type=int, default=2, help="threads of the cache's filler")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--updates", type=int, default=300, help="timed updates per job")
    args = p.parse_args()
    script = _JOB.format(bench=os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
        start = time.perf_counter()
        run_jobs(script, env, args.fill_threads, False, 5, 1)  # the other process's kernels
        run_jobs(script, env, 1, True, 5, 1)  # the pinned kernels, compiled before timing
        fill_s = time.perf_counter() - start
        rows = {"default": [], "pinned": []}
        for _ in range(args.rounds):
            rows["default"] += run_jobs(script, env, 1, False, args.updates, args.jobs)
            rows["pinned"] += run_jobs(script, env, 1, True, args.updates, args.jobs)
    medians = {k: round(statistics.median(v), 2) for k, v in rows.items()}
    print(json.dumps({
        "jobs": args.jobs, "fill_threads": args.fill_threads, "updates": args.updates,
        "update_ms": rows, "median_ms": medians,
        "ratio_default_over_pinned": round(medians["default"] / medians["pinned"], 2),
        "compile_s": round(fill_s, 1),
    }, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
