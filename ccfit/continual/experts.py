"""Progressive experts (the paper's continual mixture of experts, after Wang et al. 2024).

At `before_task(t)` the mixture gets K new trainable experts (group t; group 0 is active from
the start) and the experts of groups 0..t-1 are frozen: requires_grad False, and, since Adam's
momentum (or a stale zero gradient) can still move a parameter without gradient, written back
exactly from a stored copy after every optimiser step. Frozen experts stay routable: task t
routes over the groups 0..t (the model's scope), so the current task can reuse every earlier
expert while a finished task never routes into the experts added after it.

What keeps training: the router (so earlier experts can be reused and new ones weighted), the
shared output head, and the encoder. The paper freezes previous experts only, so the shared
head is not frozen; finished tasks' dynamics can therefore still drift through the head, the
router and the encoder (the frozen-encoder diagnostic removes the last one).

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
    """Progressive experts has no options; the expert count per task is the model's."""

    REQUIRES = frozenset({"experts"})


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
        frozen = groups.named_expert_parameters(range(task_index))
        self.stored = {name: p.detach().clone() for name, p in frozen}
        self._frozen, self._values = [], []
        self.task = task_index

    @torch.no_grad()
    def after_step(self, backbone: nn.Module) -> None:
        if not self.stored:
            return
        if not self._frozen:  # first step after a resume: match names to parameters once
            params = dict(_groups(backbone)[1].named_parameters())
            self._frozen = [params[name] for name in self.stored]
            self._values = [v.to(p.device) for v, p in zip(self.stored.values(), self._frozen,
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
