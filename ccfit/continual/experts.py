"""Progressive experts (the paper's continual PWM, after Wang et al. 2024) on a PWM backbone.

At `before_task(t)` the mixture gets K new trainable experts (group t; group 0 is active from
the start) and the experts of groups 0..t-1 are frozen: requires_grad False, and, since Adam's
momentum (or a stale zero gradient) can still move a parameter without gradient, written back
exactly from a stored copy after every optimiser step. Frozen experts stay routable: the
router spans every expert activated so far.

What keeps training: the router (so earlier experts can be reused and new ones weighted), the
shared output head, and the encoder. The paper freezes previous experts only, so the shared
head is not frozen; finished tasks' dynamics can therefore still drift through the head, the
router and the encoder (the frozen-encoder diagnostic removes the last one).

The method sees only the backbone; it finds the `MixtureDynamics` inside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ccfit.continual.base import ContinualMethod, MethodConfig, TaskData, register_method
from ccfit.models.pwm import MixtureDynamics, find_mixture


def _mixture(backbone: nn.Module) -> MixtureDynamics:
    mixture = find_mixture(backbone)
    if mixture is None:
        raise ValueError(
            f"method 'experts' needs a PWM model (a backbone with MixtureDynamics); got a "
            f"{type(backbone).__name__} backbone. Use model 'pwm', or ft / er / ewc / packnet"
        )
    return mixture


@register_method("experts")
class ProgressiveExperts(ContinualMethod):
    """K new experts per task; earlier experts frozen but routable."""

    def __init__(self, num_tasks: int | None = None) -> None:
        super().__init__(num_tasks)
        self.task = -1
        """Index of the current (or last finished) task."""
        self.stored: dict[str, torch.Tensor] = {}
        """Frozen experts' parameters (by name inside the mixture) at the time of freezing."""

    def before_task(self, task_index: int, backbone: nn.Module) -> None:
        mixture = _mixture(backbone)
        if task_index != self.task + 1:
            raise RuntimeError(f"experts: expected task {self.task + 1}, got {task_index}")
        if self.num_tasks is not None and task_index >= self.num_tasks:
            raise RuntimeError(f"experts: task {task_index} but num_tasks={self.num_tasks}")
        groups = int(mixture.num_groups)
        if groups == task_index:
            mixture.add_group()
        elif groups != task_index + 1:
            raise RuntimeError(
                f"experts: task {task_index} needs {task_index + 1} expert groups, the model "
                f"has {groups}"
            )
        mixture.freeze_groups(task_index)
        frozen = mixture.named_expert_parameters(range(task_index))
        self.stored = {name: p.detach().clone() for name, p in frozen}
        self.task = task_index

    @torch.no_grad()
    def after_step(self, backbone: nn.Module) -> None:
        if not self.stored:
            return
        params = dict(_mixture(backbone).named_parameters())
        for name, value in self.stored.items():
            params[name].copy_(value)

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        if task_index != self.task:
            raise RuntimeError(f"experts: after_task({task_index}) during task {self.task}")

    def state_dict(self) -> dict[str, Any]:
        return {"task": self.task, "stored": {k: v.clone() for k, v in self.stored.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.task = int(state["task"])
        self.stored = {k: v.clone() for k, v in state["stored"].items()}


@MethodConfig.register_subclass("experts")
@dataclass
class ProgressiveExpertsConfig(MethodConfig):
    """Progressive experts has no options; the expert count per task is PWM's
    `--model.experts_per_task`."""
    MODELS = ("pwm",)
