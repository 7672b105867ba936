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

from ccfit.config_base import check
from ccfit.continual.base import (
    ContinualMethod,
    MethodConfig,
    TaskData,
    register_method,
    trainable_parameters,
    zero_like_backbone,
)


@dataclass
class EWCConfig(MethodConfig):
    """Options of EWC (`--method.type=ewc`)."""

    lam: float = 5000.0
    """Penalty strength lambda: the penalty is lambda * sum F (theta - theta*)^2 (no 1/2; the
    paper's 5000)."""
    fisher_batches: int = 50
    """Batches of squared gradients averaged per task."""
    fisher_decay: float = 1.0
    """Factor on the previous tasks' Fisher before adding the new one (1 = sum)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.lam >= 0, f"ewc: lam must be >= 0, got {self.lam}")
        check(self.fisher_batches >= 1,
              f"ewc: fisher_batches must be >= 1, got {self.fisher_batches}")  # fmt: skip
        check(0.0 <= self.fisher_decay <= 1.0,
              f"ewc: fisher_decay must be in [0, 1], got {self.fisher_decay}")  # fmt: skip


@register_method("ewc", EWCConfig)
class EWC(ContinualMethod):
    """Quadratic penalty anchoring important backbone parameters."""

    shares_first_task = True

    cfg: EWCConfig

    def __init__(self, cfg: EWCConfig, num_tasks: int, seed: int = 0) -> None:
        super().__init__(cfg, num_tasks, seed)
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
            for _ in range(self.cfg.fisher_batches):
                loss = task_data.backbone_loss(task_data.sample())
                grads = torch.autograd.grad(loss, [params[n] for n in names], allow_unused=True)
                for name, grad in zip(names, grads, strict=True):
                    if grad is not None:
                        fisher[name] += grad.detach() ** 2
        return {name: f / self.cfg.fisher_batches for name, f in fisher.items()}

    def _align(self, backbone: nn.Module) -> None:
        """Fisher and anchor on the backbone's device (a resumed run loads them on the CPU)."""
        device = zero_like_backbone(backbone).device
        if any(f.device != device for f in self.fisher.values()):
            self.fisher = {k: v.to(device) for k, v in self.fisher.items()}
            self.anchor = {k: v.to(device) for k, v in self.anchor.items()}

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        self._align(backbone)
        new = self.estimate_fisher(backbone, task_data)
        for name, f in new.items():
            old = self.fisher.get(name)
            self.fisher[name] = f if old is None else self.cfg.fisher_decay * old + f
        self.anchor = {name: p.detach().clone() for name, p in trainable_parameters(backbone)}

    def penalty(self, backbone: nn.Module, backbone_loss) -> torch.Tensor:
        total = zero_like_backbone(backbone)
        if not self.fisher or self.cfg.lam == 0:
            return total
        self._align(backbone)
        for name, p in trainable_parameters(backbone):
            f = self.fisher.get(name)
            if f is None:
                continue
            if f.shape != p.shape:
                raise ValueError(f"EWC: {name} changed shape {tuple(f.shape)} -> {tuple(p.shape)}")
            total = total + (f * (p - self.anchor[name]) ** 2).sum()
        return self.cfg.lam * total

    def state_dict(self) -> dict[str, Any]:
        return {"fisher": dict(self.fisher), "anchor": dict(self.anchor)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.fisher = dict(state["fisher"])
        self.anchor = dict(state["anchor"])
