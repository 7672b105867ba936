"""Evaluation: fixed layouts, one acting state per episode, the benchmark's discounted return."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ccdata.scoring import GAMMA, discounted_return, normalize
from ccfit.io import derived_seed
from ccfit.models.base import WorldModel
from ccfit.obs import obs_to_arrays

TRAIN_TAG, EVAL_TAG, ACTION_TAG, REPLAY_TAG = 0, 1, 2, 3
"""Independent seed streams of a run (see `ccfit.io.derived_seed`)."""


@dataclass
class EvalResult:
    returns: list[float]
    """Discounted return (gamma = ccdata.scoring.GAMMA) of each episode."""
    successes: list[bool]
    lengths: list[int]

    @property
    def discounted_return(self) -> float:
        return float(np.mean(self.returns))

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes))


def eval_seeds(seed: int, task_index: int, episodes: int) -> list[int]:
    """The fixed evaluation layouts of curriculum task `task_index` (the same at every eval)."""
    return [derived_seed(seed, EVAL_TAG, j, task_index) for j in range(episodes)]


def normalized_or_none(task_id: str, ret: float) -> float | None:
    """Normalised return, or None when the oracle reference is not available yet."""
    try:
        return float(normalize(task_id, ret))
    except ValueError:
        return None


def obs_tensors(obs: dict, obs_mode: str, device: torch.device) -> dict[str, torch.Tensor]:
    """An env observation as the model's unbatched input tensors on `device`."""
    return {k: torch.from_numpy(v).to(device) for k, v in obs_to_arrays(obs, obs_mode).items()}


@torch.no_grad()
def evaluate(env, model: WorldModel, heads: nn.Module, *, obs_mode: str, seeds: list[int],
             device: torch.device) -> EvalResult:  # fmt: skip
    """Play one episode per layout seed with `eval_mode=True`, each from a fresh acting state."""
    returns, successes, lengths = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        state = model.initial_state(heads)
        rewards, success, done = [], False, False
        while not done:
            action, state = model.act(obs_tensors(obs, obs_mode, device), heads, state,
                                      eval_mode=True)  # fmt: skip
            obs, reward, terminated, truncated, info = env.step(np.asarray(action, np.float32))
            rewards.append(reward)
            success = success or bool(info["success"])
            done = terminated or truncated
        returns.append(discounted_return(rewards, GAMMA))
        successes.append(success)
        lengths.append(len(rewards))
    return EvalResult(returns, successes, lengths)


def eval_record(task_id: str, task_index: int, stage: int, global_step: int,
                task_step: int | None, res: EvalResult) -> dict:  # fmt: skip
    """One line of metrics.jsonl."""
    ret = res.discounted_return
    return {
        "task": task_id, "task_index": task_index, "stage": stage,
        "global_step": global_step, "task_step": task_step, "discounted_return": ret,
        "normalized_return": normalized_or_none(task_id, ret),
        "success_rate": res.success_rate, "episodes": len(res.returns),
    }  # fmt: skip
