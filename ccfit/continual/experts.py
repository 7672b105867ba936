"""Progressive experts (the paper's continual mixture of experts, after Wang et al. 2024).

At `before_task(t)` the mixture gets K new trainable experts (group t; group 0 is active from
the start) and the experts of groups 0..t-1 are frozen: requires_grad False, and, since Adam's
momentum (or a stale zero gradient) can still move a parameter without gradient, written back
exactly from a stored copy after every optimiser step. Frozen experts stay routable: task t
routes over the groups 0..t (the model's scope), so the current task can reuse every earlier
expert while a finished task never routes into the experts added after it.

What keeps training: the router's column of the current task, the encoder, and, unless
`freeze_shared` (the default), the mixture's shared parts: its output head and the router's
temperature column, through which every task's dynamics passes (`freeze_shared` also holds the
finished tasks' router columns, which no gradient reaches but Adam's carried-over moments
would move under `keep_backbone_optimizer`). With them held from the
second task on (Wang et al.'s progressive mixture, which the paper transfers; the authors'
`sdp_freeze`), a frozen encoder and PWM's defaults (the 'task' router, whose per-task columns
no other task's update reaches, and `routing_scope='own'`), a finished task's dynamics is
exactly the one it finished with; the 'state' router is shared by every task and keeps
moving. Without (`freeze_shared=False`, the authors' driver default) the head moves under the
frozen experts, and finished tasks' dynamics drift through it.

The method sees only the backbone; it finds the `ExpertGroups` inside it (a model offering the
'experts' capability), so it names no model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ccfit.continual.base import ContinualMethod, MethodConfig, TaskData, register_method
from ccfit.models.base import ExpertGroups, find_expert_groups


def _groups(backbone: nn.Module) -> tuple[str, ExpertGroups]:
    found = find_expert_groups(backbone)
    if found is None:
        raise ValueError(
            f"method 'experts' needs a backbone with expert groups (a model offering "
            f"'experts'); got a {type(backbone).__name__} backbone"
        )
    return found


@dataclass
class ProgressiveExpertsConfig(MethodConfig):
    """Progressive experts; the expert count per task is the model's."""

    REQUIRES = frozenset({"experts"})

    freeze_shared: bool = True
    """From the second task on, also hold the mixture's shared parts (output head, the router's
    temperature column) at their values after the first task, and finished tasks' router
    columns, written back after every step like the frozen experts. False: only the experts
    are frozen."""


@register_method("experts", ProgressiveExpertsConfig)
class ProgressiveExperts(ContinualMethod):
    """K new experts per task; earlier experts frozen but routable."""

    def __init__(self, cfg: ProgressiveExpertsConfig, num_tasks: int, seed: int = 0) -> None:
        super().__init__(cfg, num_tasks, seed)
        self.task = -1
        """Index of the current (or last finished) task."""
        self.stored: dict[str, torch.Tensor] = {}
        """Frozen experts' parameters (by name inside the expert module) when frozen."""
        self._frozen: list[nn.Parameter] = []
        self._values: list[torch.Tensor] = []

    def before_task(self, task_index: int, backbone: nn.Module) -> None:
        _, groups = _groups(backbone)
        if task_index != self.task + 1:
            raise RuntimeError(f"experts: expected task {self.task + 1}, got {task_index}")
        if task_index >= self.num_tasks:
            raise RuntimeError(f"experts: task {task_index} but num_tasks={self.num_tasks}")
        active = groups.active_groups
        if active == task_index:
            groups.add_group()
        elif active != task_index + 1:
            raise RuntimeError(
                f"experts: task {task_index} needs {task_index + 1} expert groups, the model "
                f"has {active}"
            )
        groups.freeze_groups(task_index)
        self.task = task_index
        self.stored = {name: t.detach().clone() for name, t in self._held(groups).items()}
        self._frozen, self._values = [], []

    def _held(self, groups: ExpertGroups) -> dict[str, torch.Tensor]:
        """What the current task must leave as it was: earlier tasks' experts and, with
        `freeze_shared`, the shared parts once a first task has trained them."""
        held = dict(groups.named_expert_parameters(range(self.task)))
        if self.cfg.freeze_shared and self.task >= 1:
            held.update(groups.shared_tensors(self.task))
        return held

    @torch.no_grad()
    def after_step(self, backbone: nn.Module) -> None:
        if not self.stored:
            return
        if not self._frozen:  # first step of a task or after a resume: match names once
            held = self._held(_groups(backbone)[1])
            self._frozen = [held[name] for name in self.stored]
            self._values = [v.to(t.device) for v, t in zip(self.stored.values(), self._frozen,
                                                           strict=True)]  # fmt: skip
        torch._foreach_copy_(self._frozen, self._values)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index != self.task:
            raise RuntimeError(f"experts: after_task({task_index}) during task {self.task}")

    def state_dict(self) -> dict[str, Any]:
        return {"task": self.task, "stored": {k: v.clone() for k, v in self.stored.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.task = int(state["task"])
        self.stored = {k: v.clone() for k, v in state["stored"].items()}
        self._frozen, self._values = [], []
