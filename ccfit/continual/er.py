"""Experience replay (Rolnick et al. 2019) on the backbone.

After each task a reservoir sample of `fraction` (5%, the authors' setting) of its transitions
is kept. While later tasks train, `penalty` returns the backbone loss on a uniform sample of
the kept set (all earlier tasks pooled), weighted by r / (1 - r) with r = `replay_ratio`.

Why that weight: mixing replay into a batch in proportion r gives the backbone loss
(1 - r) * L_current + r * L_replay (each term a batch mean). The trainer already adds
L_current with weight 1, so adding r / (1 - r) * L_replay gives the same mixture times
1 / (1 - r): the same direction, the replay share exactly r. Only backbone terms are mixed:
replayed transitions carry another task's rewards, so they never reach the current heads.
The replay batch has its own size (`batch_size`); its gradient is unbiased for L_replay.

Kept transitions are stored as the subsequences a training batch is made of (H+1 steps from
each kept start index), on the CPU: memory is (H+1) x the raw transitions kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from ccfit.continual.base import (
    ContinualMethod,
    MethodConfig,
    TaskData,
    register_method,
    zero_like_backbone,
)
from ccfit.models.base import Batch


def reservoir_indices(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """Algorithm R over the stream 0..n-1: a uniform k-subset, returned sorted.

    Item j (0-based, j >= k) replaces a random slot with probability k / (j + 1). The draws
    are vectorised; only the (about k log(n/k)) replacements are applied in a loop, in stream
    order, so the result is exactly Algorithm R's.
    """
    if not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    reservoir = np.arange(k, dtype=np.int64)
    if k == 0 or k == n:
        return reservoir if k == 0 else np.arange(n, dtype=np.int64)
    stream = np.arange(k, n, dtype=np.int64)
    slots = rng.integers(0, stream + 1)
    hits = slots < k
    for j, slot in zip(stream[hits], slots[hits], strict=True):
        reservoir[slot] = j
    return np.sort(reservoir)


def _batch_to_dict(batch: Batch) -> dict[str, Any]:
    return {
        "obs": dict(batch.obs),
        "action": batch.action,
        "reward": batch.reward,
        "terminated": batch.terminated,
        "task": batch.task,
    }


def _cat(a: Batch, b: Batch) -> Batch:
    if set(a.obs) != set(b.obs):
        raise ValueError(f"replay batches disagree on obs keys: {sorted(a.obs)} vs {sorted(b.obs)}")
    return Batch(
        obs={k: torch.cat([a.obs[k], b.obs[k]], dim=1) for k in a.obs},
        action=torch.cat([a.action, b.action], dim=1),
        reward=torch.cat([a.reward, b.reward], dim=1),
        terminated=torch.cat([a.terminated, b.terminated], dim=1),
        task=torch.cat([a.task, b.task], dim=0),
    )


def _select(batch: Batch, rows: torch.Tensor) -> Batch:
    return Batch(
        obs={k: v[:, rows] for k, v in batch.obs.items()},
        action=batch.action[:, rows],
        reward=batch.reward[:, rows],
        terminated=batch.terminated[:, rows],
        task=batch.task[rows],
    )


@register_method("er")
class ExperienceReplay(ContinualMethod):
    """Reservoir-sampled replay of earlier tasks' transitions through the backbone loss."""

    def __init__(
        self,
        num_tasks: int | None = None,
        fraction: float = 0.05,
        replay_ratio: float = 0.5,
        batch_size: int = 256,
        seed: int = 0,
    ) -> None:
        super().__init__(num_tasks)
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        if not 0.0 <= replay_ratio < 1.0:
            raise ValueError(f"replay_ratio must be in [0, 1), got {replay_ratio}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.fraction = fraction
        """Share of each finished task's transitions kept (reservoir sampling)."""
        self.replay_ratio = replay_ratio
        """Share r of replayed samples in the equivalent mixed batch (weight r / (1 - r))."""
        self.batch_size = batch_size
        """Replayed subsequences per update."""
        self.seed = seed
        """Seeds the reservoir (per task: [seed, task]) and the replay sampler."""
        self.memory: Batch | None = None
        """All kept subsequences of earlier tasks, on the CPU (batch dim = kept items)."""
        self.kept: dict[int, np.ndarray] = {}
        """Per finished task, the start indices of its kept transitions."""
        self._generator = torch.Generator().manual_seed(seed)

    @property
    def weight(self) -> float:
        return self.replay_ratio / (1.0 - self.replay_ratio)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index in self.kept:
            raise ValueError(f"er: task {task_index} was already added to the replay memory")
        n = task_data.num_transitions
        # Python's round (half to even): a task with n < 10 keeps nothing at 5%.
        k = int(round(self.fraction * n))
        rng = np.random.default_rng([self.seed, task_index])
        indices = reservoir_indices(n, k, rng)
        self.kept[task_index] = indices
        if k == 0:
            return
        kept = task_data.gather(indices).to("cpu")
        if kept.size != k:
            raise ValueError(f"task_data.gather returned {kept.size} items for {k} indices")
        self.memory = kept if self.memory is None else _cat(self.memory, kept)

    def replay_batch(self, device: torch.device | str = "cpu") -> Batch | None:
        """A uniform sample (with replacement) of `batch_size` kept subsequences."""
        if self.memory is None:
            return None
        rows = torch.randint(self.memory.size, (self.batch_size,), generator=self._generator)
        return _select(self.memory, rows).to(device)

    def penalty(self, backbone: nn.Module, backbone_loss) -> torch.Tensor:
        zero = zero_like_backbone(backbone)
        if self.memory is None or self.weight == 0.0:
            return zero
        return self.weight * backbone_loss(self.replay_batch(zero.device))

    def state_dict(self) -> dict[str, Any]:
        return {
            "memory": None if self.memory is None else _batch_to_dict(self.memory),
            "kept": {k: v.copy() for k, v in self.kept.items()},
            "generator": self._generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        memory = state["memory"]
        self.memory = None if memory is None else Batch(**memory)
        self.kept = {int(k): np.asarray(v) for k, v in state["kept"].items()}
        self._generator.set_state(state["generator"])


@MethodConfig.register_subclass("er")
@dataclass
class ExperienceReplayConfig(MethodConfig):
    """Options of experience replay (`--method.type=er`); the reservoir is seeded by the run."""

    fraction: float = 0.05
    """Share of each finished task's transitions kept (reservoir sampling)."""
    replay_ratio: float = 0.5
    """Share r of replayed samples in the equivalent mixed batch (weight r / (1 - r))."""
    batch_size: int = 256
    """Replayed windows per update."""
