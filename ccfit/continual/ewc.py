"""Elastic weight consolidation (Kirkpatrick et al. 2017) on the backbone.

After each task the diagonal Fisher information is estimated from squared gradients of the
backbone loss over `fisher_batches` (50) batches of that task, each gradient being the
batch-mean loss's (the "empirical Fisher" at batch level, as in the authors' setting). The
penalty is

    lambda * sum_j F_j * (theta_j - theta*_j)^2

with no 1/2, as in the authors' code (their lambda * sum_t F_t (theta - theta*_t)^2), so that
`lam` means what their lambda meant; Kirkpatrick et al.'s lambda / 2 form would halve it.

Accumulation across tasks: a single anchor theta* = the parameters after the latest task,
and F <- fisher_decay * F + F_task. With fisher_decay = 1 (default) the Fisher of all
finished tasks is summed ("online EWC" of Schwarz et al. 2018 with gamma = 1); it keeps one
copy of the parameters instead of one per task. `lam` defaults to 5000 (the authors'); its
scale depends on the loss, so it is exposed.

Parameters are matched by name; a parameter absent when the Fisher was taken (e.g. added
later) is not penalised. Frozen parameters (requires_grad False) are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ccfit.continual.base import (
    ContinualMethod,
    MethodConfig,
    TaskData,
    register_method,
    trainable_parameters,
    zero_like_backbone,
)


@register_method("ewc")
class EWC(ContinualMethod):
    """Quadratic penalty anchoring important backbone parameters."""

    def __init__(
        self,
        num_tasks: int | None = None,
        lam: float = 5000.0,
        fisher_batches: int = 50,
        fisher_decay: float = 1.0,
    ) -> None:
        super().__init__(num_tasks)
        if lam < 0:
            raise ValueError(f"lam must be >= 0, got {lam}")
        if fisher_batches < 1:
            raise ValueError(f"fisher_batches must be >= 1, got {fisher_batches}")
        if not 0.0 <= fisher_decay <= 1.0:
            raise ValueError(f"fisher_decay must be in [0, 1], got {fisher_decay}")
        self.lam = lam
        """Penalty strength lambda: the penalty is lambda * sum F (theta - theta*)^2 (no 1/2)."""
        self.fisher_batches = fisher_batches
        """Batches of squared gradients averaged per task."""
        self.fisher_decay = fisher_decay
        """Factor on the previous tasks' Fisher before adding the new one (1 = sum)."""
        self.fisher: dict[str, torch.Tensor] = {}
        """Accumulated diagonal Fisher per parameter name."""
        self.anchor: dict[str, torch.Tensor] = {}
        """Parameters after the latest finished task."""

    def estimate_fisher(self, backbone: nn.Module, task_data: TaskData) -> dict[str, torch.Tensor]:
        """Mean over `fisher_batches` batches of the squared backbone-loss gradient."""
        params = dict(trainable_parameters(backbone))
        names = list(params)
        fisher = {name: torch.zeros_like(p) for name, p in params.items()}
        with torch.enable_grad():
            for _ in range(self.fisher_batches):
                loss = task_data.backbone_loss(task_data.sample())
                grads = torch.autograd.grad(
                    loss, [params[n] for n in names], allow_unused=True
                )
                for name, grad in zip(names, grads, strict=True):
                    if grad is not None:
                        fisher[name] += grad.detach() ** 2
        return {name: f / self.fisher_batches for name, f in fisher.items()}

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        new = self.estimate_fisher(backbone, task_data)
        for name, f in new.items():
            old = self.fisher.get(name)
            self.fisher[name] = f if old is None else self.fisher_decay * old + f
        self.anchor = {name: p.detach().clone() for name, p in trainable_parameters(backbone)}

    def penalty(self, backbone: nn.Module, backbone_loss) -> torch.Tensor:
        total = zero_like_backbone(backbone)
        if not self.fisher or self.lam == 0:
            return total
        for name, p in trainable_parameters(backbone):
            f = self.fisher.get(name)
            if f is None:
                continue
            if f.shape != p.shape:
                raise ValueError(f"EWC: {name} changed shape {tuple(f.shape)} -> {tuple(p.shape)}")
            total = total + (f * (p - self.anchor[name]) ** 2).sum()
        return self.lam * total

    def state_dict(self) -> dict[str, Any]:
        return {"fisher": dict(self.fisher), "anchor": dict(self.anchor)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.fisher = dict(state["fisher"])
        self.anchor = dict(state["anchor"])


@MethodConfig.register_subclass("ewc")
@dataclass
class EWCConfig(MethodConfig):
    """Options of EWC (`--method.type=ewc`)."""

    lam: float = 5000.0
    """Penalty strength lambda (the paper's 5000)."""
    fisher_batches: int = 50
    """Batches of squared gradients averaged per task."""
    fisher_decay: float = 1.0
    """Factor on the previous tasks' Fisher before adding the new one (1 = sum)."""
