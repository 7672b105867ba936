"""PackNet (Mallya & Lazebnik 2018) on the backbone: iterative pruning and freezing.

Prunable tensors are the weights of Linear and Conv layers (subclasses included, e.g. a
NormedLinear). Every entry has an owner: -1 = free, t = kept for task t. Per task t, an
explicit state machine:

    TRAINING  -- after_task(t) -->  PRUNED  -- first retrain step -->  RETRAINING
        -- `retrain_steps` steps done -->  FROZEN  -- before_task(t + 1) -->  TRAINING

- TRAINING: free entries train; entries owned by earlier tasks stay fixed.
- after_task(t), t not the last task: per layer keep `keep_fraction` (25%) of the still-free
  entries, the largest in magnitude; they become owned by t. The other free entries are set
  to 0 and stay free for the next tasks. The last task is not pruned: it owns every free
  entry.
- RETRAINING: the trainer runs `wants_retrain_steps` extra updates; only entries owned by t
  move, free ones stay 0.
- FROZEN: values are stored; from now on owned entries never change.
- Biases, norm parameters and any other non-prunable parameter train during task 0 and are
  frozen with task 0's weights (shared by all tasks, as in PackNet).

Fixed entries do not move under Adam: a gradient hook zeroes their gradient (so clipping
ignores them and no new gradient enters Adam's moments for them), and since the moments they
already hold would still move them, `after_step` writes them back from the stored copy exactly
(free entries back to 0 while retraining).

`evaluating(i)` sets the entries task i did not use (owned by later tasks, or free while a
later task is training) to 0 and restores them exactly afterwards.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum
from typing import Any

import torch
from torch import nn

from ccfit.config_base import check
from ccfit.continual.base import (
    ContinualMethod,
    MethodConfig,
    TaskData,
    register_method,
    trainable_parameters,
)

FREE = -1
"""Owner value of a free (not yet kept) entry."""


class Phase(Enum):
    IDLE = "idle"  # before the first task
    TRAINING = "training"
    PRUNED = "pruned"  # pruned, retraining requested but not started
    RETRAINING = "retraining"
    FROZEN = "frozen"


def prunable_weights(backbone: nn.Module) -> set[int]:
    """ids of the weight tensors PackNet prunes (Linear and Conv layers)."""
    layers = (nn.Linear, nn.modules.conv._ConvNd)
    return {id(m.weight) for m in backbone.modules() if isinstance(m, layers)}


@dataclass
class PackNetConfig(MethodConfig):
    """Options of PackNet (`--method.type=packnet`)."""

    PRESETS = {"smoke": {"retrain_steps": 20}}

    keep_fraction: float = 0.25
    """Share of each layer's still-free weights kept for a task (by magnitude)."""
    retrain_steps: int = 1000
    """Updates after pruning, before freezing (the trainer runs them after the task's steps,
    through `wants_retrain_steps`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check(0.0 < self.keep_fraction < 1.0,
              f"packnet: keep_fraction must be in (0, 1), got {self.keep_fraction}")  # fmt: skip
        check(self.retrain_steps >= 0,
              f"packnet: retrain_steps must be >= 0, got {self.retrain_steps}")  # fmt: skip

    def check_curriculum(self, num_tasks: int) -> None:
        check(num_tasks <= 127,
              f"packnet stores owners as int8: at most 127 tasks, got {num_tasks}")  # fmt: skip


@register_method("packnet", PackNetConfig)
class PackNet(ContinualMethod):
    """Parameter isolation by magnitude pruning, per-task masks and frozen copies."""

    shares_first_task = True

    cfg: PackNetConfig

    def __init__(self, cfg: PackNetConfig, num_tasks: int, seed: int = 0) -> None:
        super().__init__(cfg, num_tasks, seed)
        self.phase = Phase.IDLE
        """Where the current task is in the state machine."""
        self.task = -1
        """Index of the current (or last finished) task."""
        self.retrain_done = 0
        """Retrain steps already run for the current task."""
        self.owner: dict[str, torch.Tensor] = {}
        """Per prunable weight (by name): int8 owner per entry, -1 = free."""
        self.stored: dict[str, torch.Tensor] = {}
        """Values at the last freeze: owned weight entries and (after task 0) shared params."""
        self.shared_frozen = False
        """Whether biases / norms / other non-prunable parameters are frozen (after task 0)."""
        # Derived on every phase change, so an update only applies them (see `_update_masks`):
        # the parameters held, and per parameter the entries allowed to move (float 0/1) and
        # the values the held entries are written back to.
        self._held: list[nn.Parameter] = []
        self._moving: list[torch.Tensor] = []
        self._held_values: list[torch.Tensor] = []
        self._grad_keep: dict[str, torch.Tensor] = {}
        self._hooked: dict[int, Any] = {}

    # ------------------------------------------------------------------ helpers
    def _params(self, backbone: nn.Module) -> Iterator[tuple[str, nn.Parameter, bool]]:
        """(name, parameter, prunable) for the backbone's trainable parameters."""
        weights = prunable_weights(backbone)
        for name, p in trainable_parameters(backbone):
            yield name, p, id(p) in weights

    def _align(self, backbone: nn.Module) -> None:
        """Owners for new weights; owners and stored values on their parameter's device (a
        resumed run loads them on the CPU, the backbone may be on a GPU)."""
        for name, p, prunable in self._params(backbone):
            if prunable and name not in self.owner:
                self.owner[name] = torch.full(p.shape, FREE, dtype=torch.int8, device=p.device)
            for table in (self.owner, self.stored):
                if name in table and table[name].device != p.device:
                    table[name] = table[name].to(p.device)

    def _attach(self, backbone: nn.Module) -> None:
        """Register owners for new weights and gradient hooks (idempotent)."""
        self._align(backbone)
        for name, p, _ in self._params(backbone):
            if id(p) not in self._hooked:
                self._hooked[id(p)] = p.register_hook(self._grad_hook(name))
        self._update_masks(backbone)

    def _grad_hook(self, name: str):
        def hook(grad: torch.Tensor) -> torch.Tensor:
            keep = self._grad_keep.get(name)
            return grad if keep is None else grad * keep

        return hook

    def _update_masks(self, backbone: nn.Module) -> None:
        """Per phase: which entries are held and at which value. A held entry is either fixed
        (owned by an earlier task, or a shared parameter after task 0: back to `stored`) or
        zeroed (free while retraining: back to 0)."""
        self._held, self._moving, self._held_values, self._grad_keep = [], [], [], {}
        retraining = self.phase in (Phase.PRUNED, Phase.RETRAINING)
        for name, p, prunable in self._params(backbone):
            zeroed = None
            if prunable:
                owner = self.owner[name]
                if retraining:
                    fixed = (owner != FREE) & (owner != self.task)
                    zeroed = owner == FREE
                else:
                    fixed = owner != FREE
            elif self.shared_frozen and name in self.stored:
                # A parameter that became trainable after the last freeze (e.g. experts a
                # mixture activated later) trains until the next freeze stores it.
                fixed = torch.ones(p.shape, dtype=torch.bool, device=p.device)
            else:
                continue
            moving = (~fixed if zeroed is None else ~(fixed | zeroed)).to(p.dtype)
            self._grad_keep[name] = moving
            # Every masked parameter is enforced, held entries or not: no host round trip.
            self._held.append(p)
            self._moving.append(moving)
            stored = self.stored.get(name)  # none yet while task 0 retrains
            self._held_values.append(
                torch.zeros_like(p)
                if stored is None
                else torch.where(fixed, stored, 0.0).to(p.dtype)
            )

    @torch.no_grad()
    def _enforce(self) -> None:
        """Held entries back to their values (Adam's momentum moves entries whose gradient
        the hook zeroed): p <- p * moving + held value, fused over all parameters."""
        if self._held:
            torch._foreach_mul_(self._held, self._moving)
            torch._foreach_add_(self._held, self._held_values)

    @torch.no_grad()
    def _prune(self, backbone: nn.Module) -> None:
        for name, p, prunable in self._params(backbone):
            if not prunable:
                continue
            owner = self.owner[name]
            free = (owner == FREE).reshape(-1)
            n_free = int(free.sum())
            n_keep = int(round(self.cfg.keep_fraction * n_free))
            free_idx = free.nonzero().squeeze(1)
            magnitude = p.detach().reshape(-1)[free_idx].abs()
            keep_idx = free_idx[torch.topk(magnitude, n_keep, sorted=False).indices]
            owner.view(-1)[keep_idx] = self.task
            p.masked_fill_(owner == FREE, 0.0)

    @torch.no_grad()
    def _freeze(self, backbone: nn.Module) -> None:
        if self.task == 0:
            self.shared_frozen = True
        self.stored = {}
        for name, p, prunable in self._params(backbone):
            if prunable or self.shared_frozen:
                self.stored[name] = p.detach().clone()
        self.phase = Phase.FROZEN
        self._update_masks(backbone)
        if self.task == self.num_tasks - 1:
            self._detach_hooks()

    def _detach_hooks(self) -> None:
        for handle in self._hooked.values():
            handle.remove()
        self._hooked = {}

    # ------------------------------------------------------------------ hooks
    def before_task(self, task_index: int, backbone: nn.Module) -> None:
        expected = self.task + 1
        if task_index != expected:
            raise RuntimeError(f"packnet: expected task {expected}, got {task_index}")
        if self.phase not in (Phase.IDLE, Phase.FROZEN):
            raise RuntimeError(
                f"packnet: task {task_index} started while task {self.task} is "
                f"{self.phase.value} ({self.wants_retrain_steps} retrain steps still owed)"
            )
        if task_index >= self.num_tasks:
            raise RuntimeError(f"packnet: task {task_index} but num_tasks={self.num_tasks}")
        self.task = task_index
        self.phase = Phase.TRAINING
        self.retrain_done = 0
        self._attach(backbone)

    def penalty(self, backbone: nn.Module, backbone_loss) -> torch.Tensor:
        if not self._hooked and self.phase in (Phase.TRAINING, Phase.PRUNED, Phase.RETRAINING):
            self._attach(backbone)  # after load_state_dict, hooks must exist before backward
        return super().penalty(backbone, backbone_loss)

    def after_step(self, backbone: nn.Module) -> None:
        if self.phase in (Phase.IDLE, Phase.FROZEN):
            raise RuntimeError(f"packnet: update outside training (phase {self.phase.value})")
        if not self._hooked:
            self._attach(backbone)
        if self.phase is Phase.PRUNED:
            self.phase = Phase.RETRAINING
        self._enforce()
        if self.phase is Phase.RETRAINING:
            self.retrain_done += 1
            if self.retrain_done >= self.cfg.retrain_steps:
                self._freeze(backbone)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index != self.task or self.phase is not Phase.TRAINING:
            raise RuntimeError(
                f"packnet: after_task({task_index}) but task {self.task} is {self.phase.value}"
            )
        self._attach(backbone)
        if task_index == self.num_tasks - 1:
            # The last task keeps every free entry; nothing is pruned.
            for owner in self.owner.values():
                owner.masked_fill_(owner == FREE, task_index)
            self._freeze(backbone)
            return
        self._prune(backbone)
        self.phase = Phase.PRUNED
        self._update_masks(backbone)
        if self.cfg.retrain_steps == 0:
            self._freeze(backbone)

    @property
    def wants_retrain_steps(self) -> int:
        if self.phase in (Phase.PRUNED, Phase.RETRAINING):
            return self.cfg.retrain_steps - self.retrain_done
        return 0

    @contextlib.contextmanager
    def evaluating(self, task_index: int, backbone: nn.Module) -> Iterator[None]:
        if not 0 <= task_index <= self.task:
            raise ValueError(f"packnet: cannot evaluate task {task_index}; tasks 0..{self.task}")
        self._align(backbone)
        saved: dict[str, torch.Tensor] = {}
        params = {name: p for name, p, prunable in self._params(backbone) if prunable}
        with torch.no_grad():
            for name, p in params.items():
                owner = self.owner[name]
                unused = owner > task_index
                if task_index < self.task:
                    unused |= owner == FREE  # free entries belong to the task now training
                saved[name] = p.detach().clone()
                p.masked_fill_(unused, 0.0)
        try:
            yield
        finally:
            with torch.no_grad():
                for name, value in saved.items():
                    params[name].copy_(value)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "phase": self.phase.value,
            "task": self.task,
            "retrain_done": self.retrain_done,
            "owner": {k: v.clone() for k, v in self.owner.items()},
            "stored": {k: v.clone() for k, v in self.stored.items()},
            "shared_frozen": self.shared_frozen,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.phase = Phase(state["phase"])
        self.task = int(state["task"])
        self.retrain_done = int(state["retrain_done"])
        self.owner = {k: v.clone() for k, v in state["owner"].items()}
        self.stored = {k: v.clone() for k, v in state["stored"].items()}
        self.shared_frozen = bool(state["shared_frozen"])
        # Masks and hooks are rebuilt on the next hook call, which sees the backbone.
        self._held, self._moving, self._held_values, self._grad_keep = [], [], [], {}
        self._detach_hooks()
