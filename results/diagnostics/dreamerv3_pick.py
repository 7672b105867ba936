"""Why DreamerV3 at its `cpu` size does not learn pick-cube.

    python results/diagnostics/dreamerv3_pick.py RUNS/pick-cube-dreamerv3-s0 \
        > results/diagnostics/dreamerv3_pick.json
    python results/diagnostics/dreamerv3_pick.py RUNS/dreamerv3-pick-cube-s0-bc0.5 \
        > results/diagnostics/dreamerv3_pick_cloning.json
    python results/diagnostics/dreamerv3_pick.py RUNS/dreamerv3-pick-cube-s0-demo \
        > results/diagnostics/dreamerv3_pick_control.json

With a finished single-task run's weights (`ccfit train`), along 20 oracle and 20 random
pick-cube episodes of the Grasp dataset: (1) the reward head along the filtered posteriors
against the recorded rewards, (2) the critic's value along them against the discounted return
the episode actually obtained, (3) the actor's mean action against the episode's. If (1) and
(2) hold on the oracle's episodes, the world model knows what grasping pays and the gap is in
behaviour learning.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from ccdata.errors import OneLineParser, run_script
from ccdata.settings import default_repo_id
from ccfit.data import load_episodes
from ccfit.replay_prefill import episode_to_replay
from ccfit.train import load_task_run

DATASET = default_repo_id("Grasp")  # LeRobot's cache, where `ccdata generate` writes, or the Hub
EPISODES = 20


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="dreamerv3_pick.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished DreamerV3 pick-cube `ccfit train` run")
    run = parser.parse_args(argv).run
    torch.set_num_threads(1)
    loaded = load_task_run(run, "cpu")
    model, heads = loaded.model, loaded.heads
    out: dict = {"run": run.name, "task_step": loaded.checkpoint["task_step"]}
    for policy in ("oracle", "random"):
        episodes = load_episodes(DATASET, task="pick-cube", policy=policy, images=False)
        sums_true, sums_pred, errors, values, returns, actions = [], [], [], [], [], []
        for episode in episodes[:EPISODES]:
            rows = episode_to_replay(episode, "state")
            steps = len(rows["action"])
            obs = {k: torch.as_tensor(v)[:, None].float() for k, v in rows["obs"].items()}
            action = torch.as_tensor(rows["action"]).float()[:, None]
            # the posterior at row t + 1 sees action t (transition t -> t + 1)
            action_in = torch.cat([torch.zeros(1, 1, action.shape[-1]), action])
            is_first = torch.zeros(steps + 1, 1, 1)
            is_first[0] = 1
            with torch.no_grad():
                embed = model.backbone.encoder(obs)
                deter, stoch, _, _ = model.rssm.observe(embed, action_in, is_first, sample=False)
                feat = model.rssm.feat(deter, stoch)[:, 0]
                reward = heads.reward_mean(feat[1:])[:, 0].numpy()
                value = heads.value(feat)[:, 0].numpy()
                mean, _ = heads.actor(feat[:-1])
            true = np.asarray(rows["reward"], dtype=np.float64).reshape(-1)
            g = np.zeros(steps + 1)
            for t in reversed(range(steps)):
                g[t] = true[t] + model.cfg.discount * g[t + 1]
            sums_true.append(true.sum())
            sums_pred.append(reward.sum())
            errors.append(np.abs(reward - true).mean())
            values.append(value[:steps].mean())
            returns.append(g[:steps].mean())
            actions.append(np.abs(mean.numpy() - rows["action"]).mean())
        out[policy] = {
            "episodes": len(errors), "reward_abs_err_per_step": float(np.mean(errors)),
            "reward_sum_true_mean": float(np.mean(sums_true)),
            "reward_sum_pred_mean": float(np.mean(sums_pred)),
            "corr_episode_reward_sums": float(np.corrcoef(sums_true, sums_pred)[0, 1]),
            "value_mean": float(np.mean(values)), "discounted_return_mean": float(np.mean(returns)),
            "actor_vs_episode_abs_action_diff": float(np.mean(actions)),
        }  # fmt: skip
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(run_script(main, "dreamerv3_pick.py"))
