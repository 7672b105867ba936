"""Experience replay (Rolnick et al. 2019) on the backbone.

After each task a reservoir sample of `fraction` (5%, the authors' setting) of its real
transitions is kept. While later tasks train, `penalty` returns the backbone loss on a sample
of the kept set (all earlier tasks pooled), weighted by r / (1 - r) with r = `replay_ratio`.

Why that weight: mixing replay into a batch in proportion r gives the backbone loss
(1 - r) * L_current + r * L_replay (each term a batch mean). The trainer already adds
L_current with weight 1, so adding r / (1 - r) * L_replay gives the same mixture times
1 / (1 - r): the same direction, the replay share exactly r. Only backbone terms are mixed:
replayed transitions carry another task's rewards, so they never reach the current heads.
The replay batch has its own size (`batch_size`); its gradient is unbiased for L_replay.

Memory: each kept transition is one 2-row item (o_t with a_t, r_t, terminated_t; then
o_{t+1}) in an ER-owned `ReplayBuffer` on the CPU, so is_first separates the items: about
2 rows per kept transition, whatever the model's window length. A replay window has the
model's `seq_len` rows and starts on an item, uniform over the kept transitions; past its
first transition it runs into the next items, which `is_first` masks out of a rollout
(a model with per-row terms, such as reconstruction, still learns from every row).
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
    ReplayLosses,
    TaskData,
    register_method,
    zero_like_backbone,
)
from ccfit.models.base import Batch
from ccfit.replay import ReplayBuffer


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


@register_method("er")
class ExperienceReplay(ContinualMethod):
    """Reservoir-sampled replay of earlier tasks' transitions through the backbone loss."""

    def __init__(
        self,
        num_tasks: int | None = None,
        fraction: float = 0.05,
        replay_ratio: float = 0.5,
        batch_size: int | None = None,
        through_heads: bool = False,
        seed: int = 0,
    ) -> None:
        super().__init__(num_tasks)
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        if not 0.0 <= replay_ratio < 1.0:
            raise ValueError(f"replay_ratio must be in [0, 1), got {replay_ratio}")
        if batch_size is not None and batch_size < 1:
            raise ValueError(f"batch_size must be >= 1 or None, got {batch_size}")
        self.fraction = fraction
        """Share of each finished task's transitions kept (reservoir sampling)."""
        self.replay_ratio = replay_ratio
        """Share r of replayed samples in the equivalent mixed batch (weight r / (1 - r))."""
        self.batch_size = batch_size
        """Replayed windows per update (None: the model's batch size, from `TaskData`)."""
        self.through_heads = through_heads
        """Replay each kept transition through its own task's stored heads as well."""
        self.seed = seed
        """Seeds the reservoir (per task: [seed, task]) and the replay sampler."""
        self.memory = ReplayBuffer(capacity=None, seed=seed)
        """Kept transitions of all earlier tasks as 2-row items, on the CPU."""
        self.seq_len: int | None = None
        """Rows per replay window: the model's (`TaskData.seq_len`)."""
        self.kept: dict[int, np.ndarray] = {}
        """Per finished task, the indices of its kept transitions."""

    @property
    def weight(self) -> float:
        return self.replay_ratio / (1.0 - self.replay_ratio)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index in self.kept:
            raise ValueError(f"er: task {task_index} was already added to the replay memory")
        if self.seq_len is not None and task_data.seq_len != self.seq_len:
            raise ValueError(f"er: seq_len {task_data.seq_len} differs from {self.seq_len}")
        self.seq_len = task_data.seq_len
        if self.batch_size is None:
            self.batch_size = task_data.batch_size
        n = task_data.num_transitions
        # Python's round (half to even): a task with n < 10 keeps nothing at 5%.
        k = int(round(self.fraction * n))
        rng = np.random.default_rng([self.seed, task_index])
        indices = reservoir_indices(n, k, rng)
        self.kept[task_index] = indices
        if k == 0:
            return
        kept = task_data.transitions(indices)
        if kept.action.shape[0] != k:
            raise ValueError(f"task_data.transitions returned {kept.action.shape[0]} for {k}")
        self.memory.add_transitions(kept, task=task_index)

    def replay_batch(self, device: torch.device | str = "cpu") -> Batch | None:
        """`batch_size` windows of `seq_len` rows from the memory, each starting on a kept
        transition (uniform, with replacement); None while nothing is kept."""
        if self.memory.num_episodes == 0:
            return None
        return self.memory.sample_at_episode_starts(self.batch_size, self.seq_len).to(device)

    def penalty(self, backbone: nn.Module, backbone_loss: ReplayLosses) -> torch.Tensor:
        zero = zero_like_backbone(backbone)
        if self.memory.num_episodes == 0 or self.weight == 0.0:
            return zero
        batch = self.replay_batch(zero.device)
        if not self.through_heads or backbone_loss.stored_heads is None:
            return self.weight * backbone_loss(batch)
        # Each window goes through the stored heads of the task it starts in (its row 0): the
        # whole model loss, backbone terms included, with those frozen heads' reward,
        # termination and value predictions held to the kept transitions.
        first = batch.task[0]
        total = zero
        for task in first.unique().tolist():
            rows = (first == task).nonzero().squeeze(1)
            part = backbone_loss.stored_heads(batch.select(rows), int(task))
            total = total + part * (len(rows) / batch.size)
        return self.weight * total

    def state_dict(self) -> dict[str, Any]:
        return {
            "memory": self.memory.state_dict(),
            "seq_len": self.seq_len,
            "batch_size": self.batch_size,
            "kept": {k: v.copy() for k, v in self.kept.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.memory.load_state_dict(state["memory"])
        self.seq_len = None if state["seq_len"] is None else int(state["seq_len"])
        self.batch_size = state.get("batch_size", self.batch_size)
        self.kept = {int(k): np.asarray(v) for k, v in state["kept"].items()}


@MethodConfig.register_subclass("er")
@dataclass
class ExperienceReplayConfig(MethodConfig):
    """Options of experience replay (`--method.type=er`); the reservoir is seeded by the run."""

    fraction: float = 0.05
    """Share of each finished task's transitions kept (reservoir sampling)."""
    replay_ratio: float = 0.5
    """Share r of replayed samples in the equivalent mixed batch (weight r / (1 - r))."""
    batch_size: int | None = None
    """Replayed windows per update (None: the model's batch size)."""
    through_heads: bool = False
    """Replay each kept window through the stored (frozen) heads of its own task as well: the
    model's whole loss (reward, termination and value terms besides the backbone's), whose
    gradient reaches the backbone only. Holds the features the stored heads read; False
    replays the backbone loss only, as the paper's text describes ER."""
