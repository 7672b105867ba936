"""What a single-task TD-MPC2 (or PWM) run's world model reads along its task's recorded
episodes.

    python results/diagnostics/task_reading.py RUNS/tdmpc2-stack-blocks-s0 \
        RUNS/tdmpc2-pnp-red-block-s0 > results/diagnostics/task_reading.jsonl

With a `ccfit train` run's last weights, along up to 20 episodes of each policy (oracle,
noisy-oracle, random) of the task in its suite's dataset (`--dataset`: another one):
the reward head's error per step, the mean Q at the episode's actions against the mean
discounted return obtained, the one-step latent dynamics error and the policy's mean action
against the episode's; and the task's normalised return on 10 layouts x 3 noise seeds through
MPPI and through the policy's mean alone (`ccfit.analysis.reading`). A run that knows its task
predicts the rewards and orders the policies' Q as their returns are ordered; one that does
not shows where its model or its value falls short. One JSON line per run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from ccdata.errors import InputError, OneLineParser, run_script
from ccdata.settings import default_repo_id
from ccfit.analysis.reading import acting, episode_reading
from ccfit.data import load_episodes
from ccfit.train import load_task_run
from ccfit.train.run import suite_of

EPISODES = 20
POLICIES = ("oracle", "noisy-oracle", "random")


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="task_reading.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="finished `ccfit train` runs")
    parser.add_argument("--dataset", default=None, help="default: the task's suite's dataset")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for run in args.runs:
        loaded = load_task_run(run, "cpu")
        task = loaded.cfg.task
        if not hasattr(loaded.model, "Q"):
            raise InputError(f"{run}: a {loaded.cfg.model.type} run; this reads TD-MPC2-style "
                             "models (encode, next, reward, Q, pi)")  # fmt: skip
        dataset = args.dataset or default_repo_id(suite_of(task))
        out: dict = {"run": run.name, "task": task,
                     "task_step": loaded.checkpoint["task_step"]}  # fmt: skip
        for policy in POLICIES:
            episodes = load_episodes(dataset, task=task, policy=policy, images=False)[:EPISODES]
            reading = episode_reading(loaded.model, loaded.heads, episodes)
            out[policy] = {"episodes": len(episodes), **reading}
        out["acting"] = acting(
            loaded.model, loaded.heads, 0, task, episode_steps=loaded.cfg.train.episode_steps
        )
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.exit(run_script(main, "task_reading.py"))
