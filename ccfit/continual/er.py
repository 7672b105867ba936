"""Experience replay (Rolnick et al. 2019) on the backbone.

After each task a reservoir sample of its replay is kept: about `fraction` (5%, the authors'
setting) of its real transitions. While later tasks train, `penalty` returns the backbone loss
on a sample of the kept set (all earlier tasks pooled), weighted by r / (1 - r) with
r = `replay_ratio`.

Why that weight: mixing replay into a batch in proportion r gives the backbone loss
(1 - r) * L_current + r * L_replay (each term a batch mean). The trainer already adds
L_current with weight 1, so adding r / (1 - r) * L_replay gives the same mixture times
1 / (1 - r): the same direction, the replay share of the backbone loss exactly r. Only backbone
terms are mixed: replayed transitions carry another task's rewards, so they never reach the
current heads. Online, the current task's head losses (reward, value, termination) also reach
the backbone and are not scaled by 1 / (1 - r): beside them the backbone terms, replay included,
weigh 1 / (1 - r) times what a batch mixed in proportion r would give them. Offline the
backbone loss is all there is.
The replay batch has its own size (`batch_size`); its gradient is unbiased for L_replay.

What is kept are whole training windows, not single transitions: a sequence model (a recurrent
state-space model trained on windows of 32 or 64 rows) needs the rows before a transition as
context, and a window replayed from 2-row items would start every transition from the
recurrent model's initial state. The task's replay
rows are cut into consecutive chunks of the model's `seq_len` rows (each a window as training
samples it: it may cross an episode boundary, which `is_first` marks); the reservoir runs over
those chunks and keeps round(fraction * n / (seq_len - 1)) of them, n being the task's real
transitions, so about `fraction` of its transitions are kept whatever the window length.
Memory: seq_len / (seq_len - 1) rows per kept transition (at most 2, for seq_len 2), in an
ER-owned `ReplayBuffer` on the CPU; a replay window is exactly one kept chunk.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from ccfit.config_base import check
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


@dataclass
class ExperienceReplayConfig(MethodConfig):
    """Options of experience replay (`--method.type=er`); the reservoir is seeded by the run."""

    fraction: float = 0.05
    """Share of each finished task's transitions kept (reservoir sampling over windows)."""
    replay_ratio: float = 0.5
    """Share r of replayed samples in the equivalent mixed batch (weight r / (1 - r))."""
    batch_size: int | None = None
    """Replayed windows per update (None: the model's batch size)."""
    through_heads: bool = False
    """Replay each kept window through the stored (frozen) heads of its own task as well: the
    model's whole loss (reward, termination and value terms besides the backbone's), whose
    gradient reaches the backbone only. Holds the features the stored heads read; False
    replays the backbone loss only, as the paper's text describes ER."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check(0.0 < self.fraction <= 1.0, f"er: fraction must be in (0, 1], got {self.fraction}")
        check(0.0 <= self.replay_ratio < 1.0,
              f"er: replay_ratio must be in [0, 1), got {self.replay_ratio}")  # fmt: skip
        check(self.batch_size is None or self.batch_size >= 1,
              f"er: batch_size must be >= 1 or None, got {self.batch_size}")  # fmt: skip


@register_method("er", ExperienceReplayConfig)
class ExperienceReplay(ContinualMethod):
    """Reservoir-sampled replay of earlier tasks' windows through the backbone loss."""

    shares_first_task = True

    cfg: ExperienceReplayConfig

    def __init__(self, cfg: ExperienceReplayConfig, num_tasks: int, seed: int = 0) -> None:
        super().__init__(cfg, num_tasks, seed)
        self.memory = ReplayBuffer(capacity=None, seed=seed)
        """Kept windows of all earlier tasks, one stored episode each, on the CPU."""
        self.seq_len: int | None = None
        """Rows per kept (and replayed) window: the model's (`TaskData.seq_len`)."""
        self.batch_size = cfg.batch_size
        """Replayed windows per update (the model's batch size unless configured)."""
        self.kept: dict[int, torch.Tensor] = {}
        """Per finished task, the first rows of its kept windows in its replay."""

    @property
    def weight(self) -> float:
        return self.cfg.replay_ratio / (1.0 - self.cfg.replay_ratio)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index in self.kept:
            raise ValueError(f"er: task {task_index} was already added to the replay memory")
        if self.seq_len is not None and task_data.seq_len != self.seq_len:
            raise ValueError(f"er: seq_len {task_data.seq_len} differs from {self.seq_len}")
        length = self.seq_len = task_data.seq_len
        if self.batch_size is None:
            self.batch_size = task_data.batch_size
        chunks = task_data.num_rows // length
        # Python's round (half to even): a task with n < 10 transitions keeps nothing at 5%.
        k = min(chunks, int(round(self.cfg.fraction * task_data.num_transitions / (length - 1))))
        rng = np.random.default_rng([self.seed, task_index])
        starts = torch.from_numpy(reservoir_indices(chunks, k, rng)) * length
        self.kept[task_index] = starts
        if k:
            self.memory.add_windows(task_data.windows(starts), task=task_index)

    def replay_batch(self, device: torch.device | str = "cpu") -> Batch | None:
        """`batch_size` kept windows (uniform, with replacement); None while nothing is kept."""
        if self.memory.num_episodes == 0:
            return None
        return self.memory.sample_at_episode_starts(self.batch_size, self.seq_len).to(device)

    def penalty(self, backbone: nn.Module, backbone_loss: ReplayLosses) -> torch.Tensor:
        zero = zero_like_backbone(backbone)
        if self.memory.num_episodes == 0 or self.weight == 0.0:
            return zero
        if not self.cfg.through_heads or backbone_loss.stored_heads is None:
            return self.weight * backbone_loss(self.replay_batch(zero.device))
        # Each window goes through the stored heads of the task it was kept from: the whole
        # model loss, backbone terms included, with those frozen heads' reward, termination
        # and value predictions held to the kept transitions. Grouped on the host, where the
        # memory is: grouping on the device would read its task ids back every update.
        batch = self.replay_batch()
        first = batch.task[0]
        total = zero
        for task in first.unique().tolist():
            rows = (first == task).nonzero().squeeze(1)
            part = backbone_loss.stored_heads(batch.select(rows).to(zero.device), int(task))
            total = total + part * (len(rows) / batch.size)
        return self.weight * total

    def state_dict(self) -> dict[str, Any]:
        return {
            "memory": self.memory.state_dict(),
            "seq_len": self.seq_len,
            "batch_size": self.batch_size,
            "kept": {k: v.clone() for k, v in self.kept.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.memory.load_state_dict(state["memory"])
        self.seq_len = None if state["seq_len"] is None else int(state["seq_len"])
        self.batch_size = state["batch_size"]
        self.kept = {int(k): torch.as_tensor(v) for k, v in state["kept"].items()}
