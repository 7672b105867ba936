"""Experience-replay memory per kept transition: the 2-row items ER keeps now, measured on a
real ER memory, against the layout it replaced (a whole training window of `window` rows per
kept transition, computed from that layout: `window` observation rows plus `window` - 1
action/reward/terminated rows plus a task index). Prints JSON.

Measured for the layout before the change (ccfit at ce34307, window 64): 11504 B per kept
transition in state mode and 2362608 B at 64 px, which the formula below reproduces.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from ccfit.continual import TaskData, make_method
from ccfit.replay import ReplayBuffer


def episode(mode: str, steps: int, image_size: int, rng: np.random.Generator) -> dict:
    if mode == "state":
        obs = {"state": rng.normal(size=(steps + 1, 39)).astype(np.float32)}
    else:
        obs = {
            "pixels": rng.integers(0, 256, (steps + 1, 9, image_size, image_size), np.uint8),
            "proprio": rng.normal(size=(steps + 1, 7)).astype(np.float32),
        }
    return {
        "obs": obs,
        "action": rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
        "reward": -rng.uniform(size=steps).astype(np.float32),
        "terminated": np.zeros(steps, np.float32),
    }


def nbytes(tree) -> int:
    if isinstance(tree, torch.Tensor):
        return tree.numel() * tree.element_size()
    if isinstance(tree, dict):
        return sum(nbytes(v) for k, v in tree.items() if k != "generator")
    return 0


def measure(mode: str, window: int, image_size: int, episodes: int) -> dict:
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(None, seed=0)
    for _ in range(episodes):
        buf.add_episode(**episode(mode, 250, image_size, rng))
    er = make_method("er", fraction=0.05)
    er.after_task(0, None, TaskData.from_buffer(0, buf, batch_size=1, seq_len=window,
                                                backbone_loss=None))  # fmt: skip
    kept = er.memory.num_episodes
    new = nbytes(er.memory.state_dict()) / kept
    obs_row = sum(v.numel() // v.shape[0] * v.element_size()
                  for v in er.memory.state_dict()["obs"].values())  # fmt: skip
    transition_row = (4 + 1 + 1) * 4  # action (4), reward, terminated: float32
    old = window * obs_row + (window - 1) * transition_row + 8  # + the task index (int64)
    return {
        "obs": mode, "image_size": image_size if mode == "pixels" else None,
        "window_rows": window, "kept_transitions": kept,
        "bytes_per_kept_new": new, "bytes_per_kept_old": old, "ratio_old_new": old / new,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--window", type=int, default=64)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=8)
    args = parser.parse_args()
    rows = [measure(m, args.window, args.image_size, args.episodes) for m in ("state", "pixels")]
    print(json.dumps({"results": rows}, indent=2))


if __name__ == "__main__":
    main()
