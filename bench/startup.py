"""A short run's fixed costs: time to the first env step, to the first update, and the whole
short job, from a cold and a warm compile cache, this checkout against another version of the
code, alternating in one run. Prints JSON.

    python bench/startup.py --baseline ../base-4e65a89 --rounds 2 --out ../runs/bench-startup

The short job is `ccfit train --task reach-xy --preset cpu --obs state --train.steps=2000
--train.seed_steps=1000 --train.eval_interval=1000 --train.eval_episodes=5` (1000 seed steps,
2000 updates with the model's pretraining, three evaluations), each time in a fresh interpreter
from an empty run directory, with no seed dataset (an empty LeRobot home). Variants: `auto`
(this checkout's defaults), `off` and `on` (`--train.compile`), `baseline` (the `--baseline`
source tree first on PYTHONPATH, its defaults). Cold: an empty Inductor cache per run; warm: a
cache of the variant's own, filled by one untimed run first. Each round runs every variant cold,
then warm. Times are from the process start: the first env step and the first update are
stamped by a wrapper that marks the first call of `Trainer._env_step` and `Trainer._update`
(both versions have them). CPU time is the job's and its children's (evaluation worker, the
compile checks). Run nothing else meanwhile: on 2 cores a busy process stalls OpenMP.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from curriculum import SAME_WORK  # bench/ is this script's directory, first on sys.path

HERE = Path(__file__).resolve().parents[1]


def job(steps: int, seed_steps: int, eval_interval: int, episodes: int) -> list[str]:
    """The `ccfit train` arguments of the short job (the issue's at the defaults)."""
    return ["train", "--task", "reach-xy", "--preset", "cpu", "--obs", "state",
            f"--train.steps={steps}", f"--train.seed_steps={seed_steps}",
            f"--train.eval_interval={eval_interval}", f"--train.eval_episodes={episodes}",
            "--quiet"]  # fmt: skip


STAMPED = """
import functools, sys, time
import ccfit.train.loop as loop

def first_call(name):
    method = getattr(loop.Trainer, name)
    @functools.wraps(method)
    def stamped(self, *args, **kwargs):
        if not getattr(stamped, "seen", False):
            stamped.seen = True
            print(f"BENCH {name} {time.time():.4f}", file=sys.stderr, flush=True)
        return method(self, *args, **kwargs)
    setattr(loop.Trainer, name, stamped)

first_call("_env_step")
first_call("_update")
from ccfit.cli import main
sys.argv = ["ccfit", *sys.argv[1:]]
sys.exit(main())
"""


def run_job(variant: str, src: Path, out: Path, cache: Path, job_args: list[str]) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    flags = [f"--train.compile={variant}"] if variant in ("off", "on") else []
    flags += SAME_WORK if variant != "baseline" else []
    cmd = [sys.executable, "-c", STAMPED, *job_args, *flags, "--out", str(out / "run")]
    home = out / "lerobot"  # no seed dataset for either version
    home.mkdir(parents=True)
    env = {
        **os.environ,
        "PYTHONPATH": str(src),
        "TORCHINDUCTOR_CACHE_DIR": str(cache),
        "HF_LEROBOT_HOME": str(home),
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.time()
    # cwd=src: `python -c` puts the working directory first on sys.path, ahead of PYTHONPATH
    proc = subprocess.run(cmd, env=env, cwd=src, capture_output=True, text=True)
    wall = time.time() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{variant}: {' '.join(cmd[3:])} failed:\n{proc.stderr[-3000:]}")
    stamps = {}
    for line in proc.stderr.splitlines():
        if line.startswith("BENCH "):
            _, name, at = line.split()
            stamps[name] = float(at) - start
    config = json.loads((out / "run" / "config.json").read_text())
    last = (out / "run" / "metrics.jsonl").read_text().splitlines()[-1]
    return {
        "wall_s": wall,
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "first_env_step_s": stamps.get("_env_step"), "first_update_s": stamps.get("_update"),
        "compiled": config.get("resolved_compile"),
        "compile_reason": config.get("resolved_compile_reason"),
        "end_eval_episodes": config["train"].get("end_eval_episodes"),
        "final_normalized_return": json.loads(last)["normalized_return"],
    }  # fmt: skip


def median_of(runs: list[dict], key: str) -> float | None:
    values = [r[key] for r in runs if r[key] is not None]
    return statistics.median(values) if values else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--baseline", default=None, help="source tree of the other version (none: this one only)"
    )
    parser.add_argument(
        "--variants",
        default="auto,on,baseline",
        help="comma-separated: auto, off, on (this checkout), baseline",
    )
    parser.add_argument("--caches", default="cold,warm", help="cold, warm or both")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default=None, help="scratch folder (default: a temp dir)")
    parser.add_argument("--steps", type=int, default=2000, help="the job's --train.steps")
    parser.add_argument("--seed-steps", type=int, default=1000)
    parser.add_argument("--eval-interval", type=int, default=1000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    args = parser.parse_args()
    job_args = job(args.steps, args.seed_steps, args.eval_interval, args.eval_episodes)
    variants = args.variants.split(",")
    if "baseline" in variants and not args.baseline:
        parser.error("the baseline variant needs --baseline")
    caches = args.caches.split(",")
    root = Path(args.out or tempfile.mkdtemp(prefix="ccfit-bench-startup-"))
    src = {v: Path(args.baseline).resolve() if v == "baseline" else HERE for v in variants}
    if "warm" in caches:
        for v in variants:  # one untimed run fills the variant's own cache
            run_job(v, src[v], root / "fill" / v, root / "cache" / v, job_args)
    runs: dict[str, dict[str, list[dict]]] = {c: {v: [] for v in variants} for c in caches}
    for r in range(args.rounds):
        for c in caches:
            for v in variants:
                cache = root / "cold" / f"{v}-{r}" if c == "cold" else root / "cache" / v
                out = root / "job" / f"{c}-{v}-{r}"
                runs[c][v].append(run_job(v, src[v], out, cache, job_args))
    keys = ("wall_s", "cpu_s", "first_env_step_s", "first_update_s")
    medians = {c: {v: {k: median_of(runs[c][v], k) for k in keys} for v in variants}
               for c in caches}  # fmt: skip
    ratios = {}
    for c in caches:
        for v in variants:
            for other in ("baseline", "off"):
                if other in variants and v != other and v != "baseline":
                    ratios[f"{c}: {other} / {v} wall"] = (
                        medians[c][other]["wall_s"] / medians[c][v]["wall_s"]
                    )
    print(json.dumps({
        "job": ["ccfit", *job_args], "this_checkout_adds": SAME_WORK, "rounds": args.rounds,
        "baseline": args.baseline,
        "medians": medians, "ratios (above 1: the variant is faster)": ratios, "runs": runs,
        "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
