"""How often DreamerV3's imagination ends a pick-cube episode within its horizon from states
whose real episode cannot end that soon (issue 70, docs/learnability.md).

    python results/diagnostics/dreamerv3_imagination.py RUNS/pick-cube-dreamerv3-s0 --dataset DIR

With a `ccfit train` run's last checkpoint, along 20 random and 20 oracle pick-cube episodes of
the Grasp dataset: the filtered posteriors at the starts (random episodes: every 10th row, the
cube still on the table; oracle episodes: rows 0-4, 23 or more steps before the oracle's own
success), then 8 imagined rollouts of the model's horizon from each, the actor's actions
sampled as in training. Per kind of start: the share of rollouts the continue head's mode ends
(`term_mode`), the termination expected under its probabilities (`term_prob`), and the
imagined rewards. The recorded windows from those starts never end in success, so a model
that knows the task imagines ~0 terminations.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from ccdata.errors import OneLineParser, run_script
from ccdata.settings import default_repo_id
from ccfit.data import load_episodes
from ccfit.replay_prefill import episode_to_replay
from ccfit.train import load_task_run

EPISODES = 20
ROLLOUTS = 8
"""Imagined rollouts per start."""
STARTS = {"random": lambda steps: range(0, steps, 10), "oracle": lambda steps: range(5)}


def posteriors(model, episode) -> tuple[torch.Tensor, torch.Tensor]:
    """The filtered (deter, stoch) at every row of `episode` (the posterior at row t + 1 has
    read action t)."""
    rows = episode_to_replay(episode, "state")
    steps = len(rows["action"])
    obs = {k: torch.as_tensor(v)[:, None].float() for k, v in rows["obs"].items()}
    action = torch.as_tensor(rows["action"]).float()[:, None]
    action_in = torch.cat([torch.zeros(1, 1, action.shape[-1]), action])
    is_first = torch.zeros(steps + 1, 1, 1)
    is_first[0] = 1
    deter, stoch, _, _ = model.rssm.observe(model.backbone.encoder(obs), action_in, is_first)
    return deter[:, 0], stoch[:, 0]


def imagine(model, heads, deter: torch.Tensor, stoch: torch.Tensor) -> dict:
    """`ROLLOUTS` rollouts of the horizon from each start: what their continue and reward
    heads predict."""
    deter, stoch = deter.repeat_interleave(ROLLOUTS, 0), stoch.repeat_interleave(ROLLOUTS, 0)
    feats = []
    for _ in range(model.cfg.horizon):
        mean, std = heads.actor(model.rssm.feat(deter, stoch))
        deter, stoch = model.rssm.img_step(deter, stoch, mean + std * torch.randn_like(mean))
        feats.append(model.rssm.feat(deter, stoch))
    feat = torch.stack(feats)
    cont = torch.sigmoid(heads.cont(feat))[..., 0]  # (horizon, rollouts)
    reward = heads.reward_mean(feat)[..., 0]
    return {
        "starts": deter.shape[0] // ROLLOUTS, "rollouts": deter.shape[0],
        "term_mode": float((cont <= 0.5).any(0).float().mean()),
        "term_prob": float((1 - cont.prod(0)).mean()),
        "imag_cont_mode_mean": float((cont > 0.5).float().mean()),
        "imag_reward_mean": float(reward.mean()), "imag_reward_max": float(reward.max()),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="dreamerv3_imagination.py",
                           description=__doc__.split("\n\n")[0])  # fmt: skip
    parser.add_argument("run", type=Path, help="a DreamerV3 pick-cube `ccfit train` run")
    parser.add_argument("--dataset", default=default_repo_id("Grasp"),
                        help="the Grasp dataset (a folder or repo id; default: LeRobot's "
                        "cache, where `ccdata generate` writes)")  # fmt: skip
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    loaded = load_task_run(args.run, "cpu")
    model, heads = loaded.model, loaded.heads
    out: dict = {"run": str(args.run), "task_step": loaded.checkpoint["task_step"]}
    with torch.no_grad():
        for policy, starts in STARTS.items():
            episodes = load_episodes(args.dataset, task="pick-cube", policy=policy,
                                     images=False)[:EPISODES]  # fmt: skip
            picked = []
            for episode in episodes:
                deter, stoch = posteriors(model, episode)
                rows = [i for i in starts(deter.shape[0] - 1) if i < deter.shape[0] - 1]
                picked.append((deter[rows], stoch[rows]))
            out[policy] = imagine(model, heads, torch.cat([d for d, _ in picked]),
                                  torch.cat([s for _, s in picked]))  # fmt: skip
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(run_script(main, "dreamerv3_imagination.py"))
