"""Experience-replay memory per kept transition, measured on a real ER memory: ER keeps
chunks of the model's `seq_len` consecutive rows (windows with their context), compared with
the two layouts it has had before, computed from their formulas: 2-row items (o_t, o_{t+1}: no
context for a sequence model) and a whole window of `seq_len` rows per kept transition.
Prints JSON.

    python bench/er_memory.py --windows 4,32,64
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from ccfit.continual import TaskData, make_method, method_config
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
    er = make_method(method_config("er", fraction=0.05), num_tasks=2)
    er.after_task(0, None, TaskData.from_buffer(0, buf, batch_size=1, seq_len=window,
                                                backbone_loss=None))  # fmt: skip
    kept = er.memory.num_transitions
    chunks = nbytes(er.memory.state_dict()) / kept
    state = er.memory.state_dict()
    obs_row = sum(v.numel() // v.shape[0] * v.element_size() for k, v in state["rows"].items()
                  if k.startswith("obs."))  # fmt: skip
    # action (4), reward, terminated: float32; is_first: bool; task: int64
    row = obs_row + (4 + 1 + 1) * 4 + 1 + 8
    return {
        "obs": mode, "image_size": image_size if mode == "pixels" else None,
        "seq_len": window, "task_transitions": buf.num_transitions, "kept_transitions": kept,
        "kept_share": kept / buf.num_transitions, "bytes_per_kept": chunks,
        "bytes_per_kept_2row_items": 2 * row, "bytes_per_kept_whole_window": window * row,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--windows", default="4,32,64", help="seq_len values (comma list)")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=8)
    args = parser.parse_args()
    rows = [measure(m, int(w), args.image_size, args.episodes)
            for w in args.windows.split(",") for m in ("state", "pixels")]  # fmt: skip
    print(json.dumps({"results": rows}, indent=2))


if __name__ == "__main__":
    main()
