"""The episode plan of a dataset: which episodes, in which order, with which seeds.

A leaf module: the generation engine (`ccdata.record`) and the episode writer (`ccdata.writer`)
both import it, and it imports neither.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ccdata.settings import POLICY_ORDER, DatasetSettings
from ccdata.suites import get_suite


@dataclass(frozen=True)
class EpisodeSpec:
    """One planned episode."""

    task_id: str
    task_index: int
    """Position of the task in the suite (the `task_id_index` column)."""
    policy: str
    index: int
    """Index among this task's episodes of this policy."""
    seed: int
    """Episode seed: `make_env(task_id).reset(seed=seed)` replays it."""

    @property
    def policy_index(self) -> int:
        return POLICY_ORDER.index(self.policy)

    @property
    def key(self) -> str:
        return f"{self.task_id}__{self.policy}__{self.seed}"


def episode_seed(seed: int, task_id: str, policy: str, index: int) -> int:
    """A 62-bit seed from (base seed, task, policy, index); stable across processes and runs.

    The task enters by a checksum of its id, so a task shared by several suites gets the same
    episodes in each of them."""
    entropy = [seed, zlib.crc32(task_id.encode()), POLICY_ORDER.index(policy), index]
    hi, lo = np.random.SeedSequence(entropy).generate_state(2, np.uint32)
    return int((int(hi) << 32 | int(lo)) >> 2)


def policy_seed(ep_seed: int) -> int:
    """The policy's own seed, decorrelated from the environment's stream of the same episode."""
    return int(np.random.SeedSequence([ep_seed, 0x9E3779B9]).generate_state(1, np.uint64)[0])


def plan(config: DatasetSettings) -> list[EpisodeSpec]:
    """Every episode of the dataset in order: per task, oracle then noisy-oracle then random."""
    counts = {
        "oracle": config.episodes,
        "noisy-oracle": config.explore_episodes,
        "random": config.explore_episodes,
    }
    specs = [
        EpisodeSpec(task.id, t, policy, i, episode_seed(config.seed, task.id, policy, i))
        for t, task in enumerate(get_suite(config.suite).tasks)
        for policy in POLICY_ORDER
        for i in range(counts[policy])
    ]
    if len({s.seed for s in specs}) != len(specs):  # 62-bit seeds: practically never
        raise RuntimeError("episode seed collision; choose another base seed")
    return specs
