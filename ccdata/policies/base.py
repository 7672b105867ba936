"""Policy interface and the parsed view of the 39-D privileged state that oracles read."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Policy(Protocol):
    """Anything that maps an observation dict to a (4,) float32 action in [-1, 1]."""

    def reset(self) -> None: ...

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


@dataclass(frozen=True)
class State:
    """The privileged state split into named parts (Meta-World's 39-D layout)."""

    hand: np.ndarray
    gripper_open: float
    obj1: np.ndarray
    obj1_quat: np.ndarray
    obj2: np.ndarray
    obj2_quat: np.ndarray
    goal: np.ndarray

    @classmethod
    def parse(cls, state: np.ndarray) -> State:
        s = np.asarray(state, dtype=np.float64)
        return cls(
            hand=s[0:3],
            gripper_open=float(s[3]),
            obj1=s[4:7],
            obj1_quat=s[7:11],
            obj2=s[11:14],
            obj2_quat=s[14:18],
            goal=s[36:39],
        )


def move(current: np.ndarray, target: np.ndarray, gain: float = 10.0) -> np.ndarray:
    """Proportional displacement command towards `target`, saturated to [-1, 1]."""
    return np.clip(gain * (np.asarray(target) - np.asarray(current)), -1.0, 1.0)


class Oracle:
    """Scripted policy on the privileged state. Subclasses implement `action(state)`.

    Oracles may keep phase memory (two-stage tasks); `reset()` clears it.
    """

    def reset(self) -> None:
        pass

    def action(self, s: State) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        a = np.asarray(self.action(State.parse(obs["state"])), dtype=np.float64)
        return np.clip(a, -1.0, 1.0).astype(np.float32)


def pose_action(delta: np.ndarray, grip: float) -> np.ndarray:
    """Concatenate a 3-D displacement command and a gripper effort (+1 closes)."""
    return np.concatenate([np.asarray(delta, dtype=np.float64), [grip]])
