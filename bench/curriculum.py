"""Wall and CPU time of whole curricula, this checkout against another version of the code,
back to back on the same machine. Prints JSON.

    python bench/curriculum.py --baseline ../baseline --models tdmpc2,dreamerv3 \\
        --out ../runs/bench-curriculum

Each (model, version) runs `ccfit run --suite SUITE --preset PRESET --obs state --seed SEED
--method.type=METHOD` in a fresh interpreter whose `ccfit` package is the version's (its source
tree first on PYTHONPATH), from an empty run directory (so the from-scratch reference is
trained too), versions alternating per model. Wall time is the command's; CPU time is what it
and its child processes (evaluation, from-scratch workers) used. Beside the times, each run's
end-of-task scores, BWT and FWT (the learning must not change beyond seed noise).

`--baseline` is a source tree of another commit, e.g. `git worktree add ../baseline 4e65a89`.
Run nothing else meanwhile (`../shared/tools/anchors/wait_quiet.sh` waits for that).

Compiling is part of a run's cost, and Inductor caches what it compiled on disk
(TORCHINDUCTOR_CACHE_DIR): a machine's first run compiles every hot path (cold), later runs
load them (warm). `--inductor-cache cold` gives each run an empty cache; `warm` runs this
checkout once more first, untimed, to fill a cache of its own; `both` times it cold, then warm.
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

HERE = Path(__file__).resolve().parents[1]

SAME_WORK = ["--train.end_eval_episodes=null"]
"""Flags only this checkout's runs get, here and in `startup.py`, so that both versions do the
same work: since fbae683 the `cpu` preset ends each task with a longer evaluation of its own (40
episodes), which the baseline does not play (null: each task's end plays `eval_episodes`, as
the baseline's does)."""


def run_one(src: Path, out: Path, args, model: str, cache: Path, ours: bool) -> dict:
    """One curriculum in a fresh interpreter; `ours`: this checkout's code (not the baseline)."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cmd = [sys.executable, "-m", "ccfit.cli", "run", "--suite", args.suite, "--preset",
           args.preset, "--obs", "state", "--seed", str(args.seed),
           f"--model.type={model}", f"--method.type={args.method}",
           f"--train.steps={args.steps}", "--out", str(out / "run"),
           "--scratch-root", str(out / "scratch"), "--quiet",
           *(SAME_WORK if ours else []), *args.extra]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(src), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
           "TORCHINDUCTOR_CACHE_DIR": str(cache)}  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    # cwd=src: `python -m` puts the working directory first on sys.path, ahead of PYTHONPATH
    proc = subprocess.run(cmd, env=env, cwd=src, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{src}: {' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    metrics = json.loads((out / "run" / "metrics.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "wall_s": wall, "cpu_s": cpu, "cores_busy": cpu / wall,
        "end_of_task": metrics["end_of_task"], "bwt": metrics["bwt"], "fwt": metrics["fwt"],
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--baseline",
        default=None,
        help="source tree of the other version (none: time this one only)",
    )
    parser.add_argument("--models", default="tdmpc2,dreamerv3")
    parser.add_argument("--suite", default="Reach")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--method", default="ft")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=6000,
                        help="steps per task, given to both versions: a model's per-suite "
                        "budget may differ between them")  # fmt: skip
    parser.add_argument(
        "--out", default="/tmp/ccfit-bench-curriculum", help="scratch folder for the runs"
    )
    parser.add_argument("--inductor-cache", choices=("cold", "warm", "both"), default="both",
                        help="time runs with an empty compile cache, a filled one, or both "
                             "(this checkout only; see the module doc)")  # fmt: skip
    parser.add_argument(
        "--extra",
        nargs=argparse.REMAINDER,
        default=[],
        help="more `ccfit run` options for both versions (last)",
    )
    args = parser.parse_args()
    current = {"cold": ["current_cold"], "warm": ["untimed", "current_warm"],
               "both": ["current_cold", "current_warm"]}[args.inductor_cache]  # fmt: skip
    versions = [(name, HERE) for name in current]
    if args.baseline:
        versions = [("baseline", Path(args.baseline).resolve()), *versions]
    results: dict[str, dict] = {}
    for model in args.models.split(","):
        row = {}
        cache = Path(args.out) / f"{model}-inductor-cache"
        for name, src in versions:
            if name in ("baseline", "current_cold"):
                shutil.rmtree(cache, ignore_errors=True)
            result = run_one(
                src, Path(args.out) / f"{model}-{name}", args, model, cache, ours=name != "baseline"
            )
            if name != "untimed":
                row[name] = result
                print(json.dumps({model: {name: result}}), file=sys.stderr, flush=True)
        for name in ("current_cold", "current_warm"):
            if "baseline" in row and name in row:
                base, cur = row["baseline"], row[name]
                row[f"wall_ratio_baseline_over_{name}"] = base["wall_s"] / cur["wall_s"]
                row[f"cpu_ratio_baseline_over_{name}"] = base["cpu_s"] / cur["cpu_s"]
        results[model] = row
    print(json.dumps({
        "suite": args.suite, "preset": args.preset, "method": args.method, "seed": args.seed,
        "obs": "state", "steps": args.steps, "cpu_count": os.cpu_count(), "baseline": args.baseline,
        "inductor_cache": args.inductor_cache, "extra": args.extra,
        "this_checkout_adds": SAME_WORK, "results": results,
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
