"""How precisely a DreamerV3 pick-cube run's world model (state observations) knows where the
hand, the cube and the goal are (issue 70, docs/learnability.md).

    python results/diagnostics/dreamerv3_state_precision.py RUNS/pick-cube-s0 --dataset DIR

With a `ccfit train` run's last checkpoint, along 20 oracle, 20 noisy-oracle and 20 random
pick-cube episodes of the Grasp dataset, per position (x, y, z of the 39-D state, in metres),
the mean distance between the recorded position and the one decoded:
- `posterior`: from the filtered state at each row (the model has read that observation);
- `prior_1`: one step ahead, from the previous row's filtered state and the recorded action;
- `open_loop_15`: the position at the episode's last row, decoded after the model's horizon
  (15 steps) of priors with the recorded actions from the row 15 before it; `still`: the
  same distance had the position stayed where it was at that row;
- `mean`: the distance to the position's mean over these rows, what a model that knows
  nothing of it would score.
And `p_end_open_loop`: the continue head's termination probability at that open-loop last
row (the oracle's episodes end there in success; the random ones do not).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import NamedTuple

import torch

from ccdata.errors import InputError, OneLineParser, run_script
from ccdata.settings import default_repo_id
from ccfit.analysis.encoder_probe import POSITIONS
from ccfit.data import load_episodes
from ccfit.replay_prefill import episode_to_replay
from ccfit.train import load_task_run

EPISODES = 20
OPEN_LOOP = 15
PARTS = {"hand": POSITIONS["hand"], "cube": POSITIONS["object"], "goal": POSITIONS["goal"]}


def filtered(model, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Model states (rows, F) after reading each row's observation (row t + 1 has read action
    t), from the learned initial state, as training filters a window."""
    rows = state.shape[0]
    action_in = torch.cat([torch.zeros(1, action.shape[-1]), action])[:rows, None]
    is_first = torch.zeros(rows, 1, 1)
    is_first[0] = 1
    embed = model.backbone.encoder({"state": state[:, None]})
    deter, stoch, _, _ = model.rssm.observe(embed, action_in, is_first)
    return deter[:, 0], stoch[:, 0]


def decode(model, deter: torch.Tensor, stoch: torch.Tensor) -> torch.Tensor:
    return model.backbone.decoder.predict(model.rssm.feat(deter, stoch))["state"]


def distances(pred: torch.Tensor, true: torch.Tensor) -> dict[str, torch.Tensor]:
    return {name: (pred[..., s] - true[..., s]).norm(dim=-1) for name, s in PARTS.items()}


class Reading(NamedTuple):
    """One episode's distances (kind -> position -> per-row tensor), its states and the
    termination probability at its open-loop last row."""

    distances: dict[str, dict[str, torch.Tensor]]
    states: torch.Tensor
    p_end: torch.Tensor


def read_episode(model, heads, episode) -> Reading:
    rows = episode_to_replay(episode, "state")
    state = torch.as_tensor(rows["obs"]["state"]).float()
    action = torch.as_tensor(rows["action"]).float()
    deter, stoch = filtered(model, state, action)
    prior_d, prior_s = model.rssm.img_step(deter[:-1], stoch[:-1], action, sample=False)
    out = {"posterior": distances(decode(model, deter, stoch), state),
           "prior_1": distances(decode(model, prior_d, prior_s), state[1:])}  # fmt: skip
    start = max(0, state.shape[0] - 1 - OPEN_LOOP)
    d, s = deter[start : start + 1], stoch[start : start + 1]
    for t in range(start, state.shape[0] - 1):
        d, s = model.rssm.img_step(d, s, action[t : t + 1], sample=False)
    out["open_loop_15"] = distances(decode(model, d, s), state[-1:])
    out["still"] = distances(state[start : start + 1], state[-1:])
    p_end = 1.0 - torch.sigmoid(heads.cont(model.rssm.feat(d, s))).reshape(1)
    return Reading(out, state, p_end)


def summarise(readings: list[Reading]) -> dict:
    states = torch.cat([r.states for r in readings])
    summary: dict = {"rows": states.shape[0]}
    for kind in ("posterior", "prior_1", "open_loop_15", "still"):
        summary[kind] = {name: float(torch.cat([r.distances[kind][name] for r in readings]).mean())
                         for name in PARTS}  # fmt: skip
    summary["mean"] = {name: float(v.mean()) for name, v in
                       distances(states.mean(0, keepdim=True), states).items()}  # fmt: skip
    summary["p_end_open_loop"] = float(torch.cat([r.p_end for r in readings]).mean())
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="dreamerv3_state_precision.py",
                           description=__doc__.split("\n\n")[0])  # fmt: skip
    parser.add_argument("run", type=Path, help="a DreamerV3 pick-cube `ccfit train` run (state)")
    parser.add_argument("--dataset", default=default_repo_id("Grasp"),
                        help="the Grasp dataset (a folder or repo id; default: LeRobot's "
                        "cache, where `ccdata generate` writes)")  # fmt: skip
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    loaded = load_task_run(args.run, "cpu")
    cfg = loaded.model.cfg
    if cfg.type != "dreamerv3" or cfg.obs_mode != "state":
        raise InputError(
            f"{args.run} is a {cfg.type} run from {cfg.obs_mode}; this script reads a "
            "DreamerV3 run from state (its decoder rebuilds the state)"
        )
    out: dict = {"run": str(args.run), "task_step": loaded.checkpoint["task_step"],
                 "state_recon_scale": cfg.state_recon_scale}  # fmt: skip
    with torch.no_grad():
        for policy in ("oracle", "noisy-oracle", "random"):
            episodes = load_episodes(args.dataset, task="pick-cube", policy=policy,
                                     images=False)[:EPISODES]  # fmt: skip
            if episodes:
                out[policy] = summarise([read_episode(loaded.model, loaded.heads, e)
                                         for e in episodes])  # fmt: skip
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    sys.exit(run_script(main, "dreamerv3_state_precision.py"))
