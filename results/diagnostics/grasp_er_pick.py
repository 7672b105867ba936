"""Why ER loses Grasp's pick-cube (TD-MPC2) where EWC keeps it.

    python results/diagnostics/grasp_er_pick.py RUNS/Grasp-tdmpc2-{ewc,er,ft}-state-cpu-s0 \
        > results/diagnostics/grasp_er_pick.jsonl

For each finished Grasp curriculum, its final backbone with the stored heads of an earlier task:
- reading: along 20 oracle and 20 random episodes of the task from the Grasp dataset (true
  rewards and discounted returns known), the stored reward head's error per step, the stored Q
  at the episode's actions against the discounted return obtained, the latent dynamics'
  one-step error |next(z_t, a_t) - encode(o_t+1)|^2 / |encode(o_t+1)|^2 and the stored policy's
  mean action against the episode's;
- acting: the task's normalised return over 10 layouts x 3 noise seeds, acting as evaluation
  does (MPPI through dynamics, reward and Q) and with the stored policy's mean alone.
One JSON line per run.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import torch

from ccdata.errors import OneLineParser, run_script
from ccdata.settings import default_repo_id
from ccfit.analysis.reading import acting, episode_reading
from ccfit.curriculum import load_run
from ccfit.data import load_episodes

DATASET = default_repo_id("Grasp")  # LeRobot's cache, where `ccdata generate` writes, or the Hub
EPISODES = 20


def reading(model, method, heads, index: int, task: str, policy: str) -> dict:
    episodes = load_episodes(DATASET, task=task, policy=policy, images=False)[:EPISODES]
    return episode_reading(model, heads, episodes,
                           lambda: method.evaluating(index, model.backbone))  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="grasp_er_pick.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="finished Grasp curricula")
    runs = parser.parse_args(argv).runs
    torch.set_num_threads(1)
    for run in runs:
        loaded = load_run(run, "cpu")
        cfg, model, method, stored = loaded.cfg, loaded.model, loaded.method, loaded.stored_heads
        model.eval()
        method_view = functools.partial(method.evaluating, backbone=model.backbone)
        out: dict = {"run": run.name}
        for index, task in enumerate(cfg.tasks[:-1]):  # the earlier tasks
            heads = stored[index].eval()
            for policy in ("oracle", "random"):
                out[f"{task}/reading/{policy}"] = reading(model, method, heads, index, task,
                                                          policy)  # fmt: skip
            out[f"{task}/acting"] = acting(
                model, heads, index, task, method_view, episode_steps=cfg.train.episode_steps
            )
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.exit(run_script(main, "grasp_er_pick.py"))
