"""How far along its task's shaped reward a single-task run's policy gets.

    python results/diagnostics/stage_reached.py RUNS/box-pnp-close-tdmpc2-s0-demo0.25 [LAYOUTS]

The composition tasks score their stages on the scene's raw reward in [0, 10] (box-pnp-close:
0-5 carrying the cube onto the box's floor, 5-10 with the cube inside while the lid is
brought, 10 on success); the benchmark's reward rescales it to [-1, 0]. A normalised return
near the floor hides which stage a policy reaches; the raw reward along its episodes shows it.
With the run's last weights, acting as evaluation does (MPPI, eval mode, the run's
observations) on the run's first LAYOUTS evaluation layouts (default 10): per layout,
success, the best raw reward and the steps spent at 5 or more; for each stage flag the scene
reports in its step info (`drawer_open`, `cube_in_drawer`, `cube_in_box`, `holding`, ...),
the steps it was true; and in a scene with a lid (the box tasks) the lid's distance to where
it closes the box after the first step and its least along the episode: whether the policy
moved the lid at all. One JSON line.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from ccdata.env import make_env
from ccdata.errors import OneLineParser, run_script
from ccfit.io import seeded
from ccfit.train import load_task_run
from ccfit.train.evaluate import eval_seeds, play_episodes

NOISE_SEED = 1


class RawRewards:
    """An environment whose steps also keep the scene's raw reward (`info['raw_reward']`)."""

    def __init__(self, env) -> None:
        self.env, self.raw, self.lid, self.flags = env, [], [], {}

    def reset(self, **kwargs):
        self.raw, self.lid, self.flags = [], [], {}
        return self.env.reset(**kwargs)

    def step(self, action):
        out = self.env.step(action)
        info = out[4]
        self.raw.append(float(info["raw_reward"]))
        for key, value in info.items():
            if key != "success" and isinstance(value, (bool, np.bool_)):
                self.flags[key] = self.flags.get(key, 0) + int(value)
        if hasattr(self.env.scene, "close_error"):
            self.lid.append(self.env.scene.close_error())
        return out


def main(argv: list[str] | None = None) -> None:
    parser = OneLineParser(prog="stage_reached.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished `ccfit train` run directory")
    parser.add_argument(
        "layouts",
        type=int,
        nargs="?",
        default=10,
        help="how many of the run's evaluation layouts to play (default 10)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    run, layouts = args.run, args.layouts
    loaded = load_task_run(run, "cpu")
    cfg = loaded.cfg
    pixels = cfg.obs == "pixels"  # cameras only where the run observed through them
    envs = [RawRewards(make_env(cfg.task, render=pixels, image_size=cfg.image_size,
                                episode_steps=cfg.train.episode_steps))
            for _ in range(layouts)]  # fmt: skip
    with seeded(NOISE_SEED, loaded.model.device):
        episodes = play_episodes(envs, loaded.model, loaded.heads, obs_mode=cfg.obs,
                                 seeds=eval_seeds(cfg.seed, 0, layouts))  # fmt: skip
    raw = [np.asarray(env.raw) for env in envs]
    print(json.dumps({
        "run": run.name, "task": cfg.task, "task_step": loaded.checkpoint["task_step"],
        "success": [e.success for e in episodes],
        "best_raw": [round(float(r.max()), 2) for r in raw],
        "steps_at_5_or_more": [int((r >= 5).sum()) for r in raw],
        "steps": [len(r) for r in raw],
        **{f"steps_{flag}": [env.flags[flag] for env in envs] for flag in sorted(envs[0].flags)},
        **({"lid_to_closed_first_and_least_m": [[round(e.lid[0], 3), round(min(e.lid), 3)]
                                                for e in envs]} if envs[0].lid else {}),
    }))  # fmt: skip


if __name__ == "__main__":
    sys.exit(run_script(main, "stage_reached.py"))
