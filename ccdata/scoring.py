"""Discounted returns and the benchmark's normalised score (floor 0, oracle 100).

The score is defined on the episodes the oracle references were measured on (their length is
recorded in `references.json`, the benchmark's 250 steps): its floor and its 100 are both
returns of such episodes. A run whose episodes have another length (tests shorten them) is
scored on the same scale, so its scores are not the benchmark's.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources

import numpy as np

from ccdata.env import DEFAULT_EPISODE_STEPS
from ccdata.errors import InputError
from ccdata.tasks import get_task

GAMMA = 0.99
"""The benchmark's discount."""
REFERENCE_FILE = "references.json"


def discounted_return(rewards, gamma: float = GAMMA) -> float:
    rewards = np.asarray(rewards, dtype=np.float64)
    return float(np.sum(rewards * gamma ** np.arange(len(rewards))))


def floor_return(gamma: float = GAMMA, steps: int = DEFAULT_EPISODE_STEPS) -> float:
    """Discounted return of reward -1 at every step of a full episode of `steps` steps."""
    return -(1.0 - gamma**steps) / (1.0 - gamma)


@cache
def references() -> dict:
    """Package data written by `ccdata references`: per task the oracle's mean return."""
    path = resources.files("ccdata") / REFERENCE_FILE
    if not path.is_file():
        return {"tasks": {}}
    return json.loads(path.read_text())


def reference_episode_steps() -> int:
    """Agent steps per episode of the episodes the oracle references were measured on."""
    return int(references().get("episode_steps", DEFAULT_EPISODE_STEPS))


def oracle_reference(task_id: str) -> float:
    get_task(task_id)  # unknown id -> ValueError
    try:
        return float(references()["tasks"][task_id]["mean_discounted_return"])
    except KeyError:
        raise InputError(
            f"no oracle reference for {task_id!r}: run `ccdata references` to regenerate"
        ) from None


def normalize(task_id: str, discounted_return: float) -> float:
    """0 at the floor, 100 at the oracle's mean discounted return; not capped."""
    floor = floor_return(steps=reference_episode_steps())
    return 100.0 * (discounted_return - floor) / (oracle_reference(task_id) - floor)
