"""The one interface every world model implements (TD-MPC2, DreamerV3, PWM).

A world model splits into
- `backbone`: the task-agnostic part (observation encoder, dynamics, decoder if any). It is
  the only thing continual-learning methods ever see or touch.
- heads: the task-specific part (reward, termination, value/Q ensemble with targets, policy),
  made fresh per task by `new_heads()`, frozen and stored after the task, and usable on any
  later backbone to evaluate that task.

The shared training loop (ccfit.train) drives a model only through this interface:

    groups = model.param_groups(heads)          # main optimiser: backbone + non-policy heads
    out = model.loss(batch, heads)              # world-model + reward + value (+ term.) loss
    total = out.total + method.penalty(backbone, model.backbone_loss)
    total.backward(); clip; opt.step(); method.after_step(backbone)
    model.head_update(batch, heads, out)        # policy/actor + target nets; never the backbone
    action = model.act(obs, heads, t0=..., eval_mode=...)
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

LATENT_KEY = "latent"
"""Observation key of a frozen encoder's output cached in replay (`WorldModel.replay_obs`)."""


@dataclass
class Batch:
    """Subsequences of length H+1 sampled from replay, time-major.

    obs: dict of tensors shaped (H+1, B, ...); keys 'state' (float32, 39) in state mode, or
    'pixels' (uint8, 9 x S x S: topview, frontview, gripperPOV channel-stacked) and
    'proprio' (float32, 7) in pixel mode, or 'latent' (float32) when a frozen encoder's
    outputs are cached in the buffer.
    action: (H, B, 4); reward: (H, B, 1) in [-1, 0]; terminated: (H, B, 1) float {0, 1}.
    task: (B,) long, the curriculum index of the task each sample belongs to.
    """

    obs: dict[str, torch.Tensor]
    action: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    task: torch.Tensor

    def to(self, device: torch.device | str) -> Batch:
        return Batch(
            obs={k: v.to(device, non_blocking=True) for k, v in self.obs.items()},
            action=self.action.to(device),
            reward=self.reward.to(device),
            terminated=self.terminated.to(device),
            task=self.task.to(device),
        )

    @property
    def horizon(self) -> int:
        return self.action.shape[0]

    @property
    def size(self) -> int:
        return self.action.shape[1]


@dataclass
class LossOutput:
    """What `WorldModel.loss` returns."""

    total: torch.Tensor
    """Scalar to backpropagate through backbone and (non-policy) heads."""
    logs: dict[str, float] = field(default_factory=dict)
    """Detached scalars for logging (e.g. consistency, reward, value, termination)."""
    aux: Any = None
    """Model-specific values reused by `head_update` (e.g. detached latents)."""


class WorldModel(nn.Module, ABC):
    """Base class; subclasses set `self.backbone` (an nn.Module) in __init__."""

    backbone: nn.Module

    @abstractmethod
    def new_heads(self) -> nn.Module:
        """Fresh task-specific heads on the model's device."""

    @abstractmethod
    def param_groups(self, heads: nn.Module) -> list[dict]:
        """Parameter groups for the main optimiser (backbone + heads except the policy)."""

    @abstractmethod
    def policy_parameters(self, heads: nn.Module) -> list[nn.Parameter]:
        """Parameters of the policy/actor, trained by `head_update`'s own optimiser."""

    @abstractmethod
    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        """World-model loss with this task's heads (differentiable)."""

    @abstractmethod
    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """Task-agnostic terms only (dynamics consistency, reconstruction): what continual
        methods replay (ER) or take Fisher information from (EWC)."""

    @abstractmethod
    def head_update(
        self, batch: Batch, heads: nn.Module, out: LossOutput, policy_optim: torch.optim.Optimizer
    ) -> dict[str, float]:
        """Policy/actor step and target-network updates; must not change the backbone."""

    def replay_obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What replay stores for an episode's observations (T+1, ...): by default the
        observations themselves; `encode` must accept whatever this returns."""
        return obs

    @abstractmethod
    def act(
        self, obs: dict[str, torch.Tensor], heads: nn.Module, *, t0: bool, eval_mode: bool
    ) -> np.ndarray:
        """One action (4,) in [-1, 1] for an unbatched observation (tensors without batch dim)."""
