"""Seconds per pixel evaluation with the environments here and in worker processes
(`--train.env_workers`). Prints JSON.

    python bench/eval_workers.py --workers 0,2 --episodes 5 --repeats 3

One evaluation is what a run does for one task at an evaluation point: `--episodes` episodes
of `--task` from their fixed layouts, played together (`play_episodes`: one batched eval-mode
act per step, then every environment steps and renders its three cameras). The model is
`--model` at its `--preset` size on pixels with fresh weights, its hot paths compiled as
`--compile` says (a run's `auto` by default), one torch thread as in a run; every evaluation
draws the same planner noise, so it plays the same episodes. Worker counts alternate per
repeat; the first evaluation of each count (making the environments, starting the workers) is
not timed. The ratio is the median without workers over each count's median.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import torch  # noqa: E402

import ccdata.env  # noqa: E402
from ccdata.processes import available_cores  # noqa: E402
from ccdata.tasks.registry import TASKS  # noqa: E402
from ccfit.config_base import PRESETS  # noqa: E402
from ccfit.io import seeded  # noqa: E402
from ccfit.models import make_model, model_names  # noqa: E402
from ccfit.models.registry import config_class  # noqa: E402
from ccfit.train import EnvPool, eval_seeds, play_episodes  # noqa: E402
from ccfit.train.compiled import compile_hot_paths  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="tdmpc2")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--task", default="reach-xyz")
    parser.add_argument("--episodes", type=int, default=5, help="the cpu preset's")
    parser.add_argument("--workers", default="0,2", help="comma-separated counts")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--compile", default="auto", help="--train.compile")
    parser.add_argument(
        "--episode-steps",
        type=int,
        default=ccdata.env.DEFAULT_EPISODE_STEPS,
        help="steps per episode (fewer: a quick check of the script)",
    )
    args = parser.parse_args()
    counts = [int(x) for x in args.workers.split(",") if x.isdigit()]
    if len(counts) != len(args.workers.split(",")):
        parser.error(f"--workers takes comma-separated counts >= 0, got {args.workers!r}")
    if args.model not in model_names():
        parser.error(f"unknown model {args.model!r}; valid: {', '.join(model_names())}")
    if args.preset not in PRESETS:
        parser.error(f"unknown preset {args.preset!r}; valid: {', '.join(PRESETS)}")
    if args.task not in TASKS:
        parser.error(f"unknown task {args.task!r}; valid: {', '.join(TASKS)}")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = config_class(args.model).preset(args.preset, obs_mode="pixels")
    model = make_model(cfg, "cpu").eval()
    compiled = compile_hot_paths(model, args.compile)
    heads = model.new_heads()
    seeds = eval_seeds(0, 0, args.episodes)
    pools = {n: EnvPool("pixels", cfg.image_size, n, episode_steps=args.episode_steps)
             for n in counts}  # fmt: skip

    def evaluate(n: int) -> tuple[float, int]:
        start = time.perf_counter()
        with seeded(0, model.device):  # the same planner noise at every evaluation, as in a run
            episodes = play_episodes(pools[n].get(args.task, len(seeds)), model, heads,
                                     obs_mode="pixels", seeds=seeds)  # fmt: skip
        return time.perf_counter() - start, sum(len(e.rewards) for e in episodes)

    steps = {n: evaluate(n)[1] for n in counts}  # untimed: environments made, workers started
    times: dict[int, list[float]] = {n: [] for n in counts}
    for _ in range(args.repeats):
        for n in counts:
            seconds, played = evaluate(n)
            assert played == steps[n], "the same layouts play the same episodes"
            times[n].append(seconds)
    for pool in pools.values():
        pool.close()
    medians = {n: statistics.median(t) for n, t in times.items()}
    here = medians.get(0)
    print(json.dumps({
        "model": args.model, "preset": args.preset, "task": args.task,
        "episodes": args.episodes, "episode_steps": args.episode_steps,
        "env_steps_per_evaluation": steps[counts[0]],
        "torch_threads": args.threads, "compiled": compiled, "available_cores": available_cores(),
        "evaluation_s": {str(n): t for n, t in times.items()},
        "evaluation_s_median": {str(n): m for n, m in medians.items()},
        "ratio_here_over_workers": ({str(n): here / m for n, m in medians.items() if n}
                                    if here is not None else None),
        "machine": platform.machine(), "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "torch": torch.__version__,
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
