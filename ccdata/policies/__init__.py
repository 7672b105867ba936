"""Policies that roll out the benchmark: the scripted oracle and two exploration policies."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ccdata.errors import InputError
from ccdata.policies.base import Oracle, Policy, State, move, pose_action

POLICIES = ("oracle", "noisy-oracle", "random")


class RandomPolicy:
    """Uniform actions in [-1, 1]^4."""

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, size=4).astype(np.float32)


@dataclass
class NoisyOracle:
    """The oracle's action plus Gaussian noise; with probability `random_prob` a uniform one.

    The oracle runs at every step, so its phase memory stays in step with the episode."""

    oracle: Oracle
    noise_std: float = 0.3
    random_prob: float = 0.1
    seed: int | None = None

    def __post_init__(self) -> None:
        if self.noise_std < 0 or not 0 <= self.random_prob <= 1:
            raise InputError("noise_std must be >= 0 and random_prob in [0, 1]")
        self.rng = np.random.default_rng(self.seed)

    def reset(self) -> None:
        self.oracle.reset()

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        action = self.oracle.act(obs)  # keeps the oracle's phase memory in step
        if self.rng.random() < self.random_prob:
            return self.rng.uniform(-1.0, 1.0, size=4).astype(np.float32)
        noisy = action + self.rng.normal(0.0, self.noise_std, size=4)
        return np.clip(noisy, -1.0, 1.0).astype(np.float32)

    def params(self) -> dict:
        return {"noise_std": self.noise_std, "random_prob": self.random_prob}


def make_policy(
    name: str,
    task_id: str,
    seed: int | None = None,
    noise_std: float | None = None,
    random_prob: float | None = None,
) -> Policy:
    """'oracle', 'noisy-oracle' or 'random' for task `task_id`.

    The noisy oracle's `noise_std` and `random_prob` default to the task's calibrated values
    (`TaskSpec.exploration`)."""
    # Here, not at the top: the tasks' oracles are written with `ccdata.policies.base`, so a
    # package-level import of the tasks would make the two packages import each other.
    from ccdata.tasks import get_task

    task = get_task(task_id)
    if name == "oracle":
        return task.oracle()
    if name == "noisy-oracle":
        calibrated = task.exploration
        return NoisyOracle(
            task.oracle(),
            noise_std=calibrated.noise_std if noise_std is None else noise_std,
            random_prob=calibrated.random_prob if random_prob is None else random_prob,
            seed=seed,
        )
    if name == "random":
        return RandomPolicy(seed)
    raise InputError(f"unknown policy {name!r}; valid policies: {', '.join(POLICIES)}")


__all__ = [
    "POLICIES",
    "NoisyOracle",
    "Oracle",
    "Policy",
    "RandomPolicy",
    "State",
    "make_policy",
    "move",
    "pose_action",
]
