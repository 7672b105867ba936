"""The one interface every world model implements (TD-MPC2, PWM, DreamerV3, ...).

A world model splits into
- `backbone`: the task-agnostic part (observation encoder, dynamics, decoder if any). It is
  the only thing continual-learning methods ever see or touch.
- heads: the task-specific part (reward, termination/continue, value/critic, policy/actor and
  their statistics), made fresh per task by `new_heads()`, frozen and stored after the task,
  and usable on any later backbone to evaluate that task.

The shared training loop (ccfit.train) drives a model only through this interface:

    model.begin_task(i, steps)                  # a task starts (PWM: routing, temperature)
    heads = model.new_heads()
    opt = model.world_model_optimizer(heads)    # backbone + heads trained by `loss`
    head_opts = model.head_optimizers(heads)    # what `head_update` steps (policy, critic)
    batch = replay.sample(model.cfg.batch_size, model.cfg.seq_len)
    out = model.loss(batch, heads)
    total = out.total + method.penalty(backbone, losses)
    total.backward(); clip to model.cfg.grad_clip; opt.step(); method.after_step(backbone)
    model.head_update(batch, heads, out, head_opts)   # never changes the backbone
    # `model.cfg.train_ratio` updates per env step (fractional ratios accumulate), after a
    # one-off burst of `model.cfg.pretrain_updates` on a fresh model (the run's first task)

    state = model.initial_state(heads)          # per episode, per set of heads
    action, state = model.act(obs, heads, state, eval_mode=...)
    state = model.observe(obs, action, heads, state)  # a step the model did not choose

Acting state is an explicit value owned by whoever plays the episode, so stored heads of
earlier tasks evaluated mid-episode of the current task never disturb each other.
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
    """Windows of `seq_len` consecutive replay rows, time-major; one transition per row.

    Row t holds observation o_t and the transition taken from it: action a_t, reward r_t and
    terminated_t (arriving at o_{t+1} ended the episode by success). The last row of an
    episode holds its final observation and a filler transition (zeros). A window may cross
    episode boundaries: `is_first[t]` = 1 where row t starts an episode, so transition t is
    real only when row t+1 exists and `is_first[t+1]` = 0 (see `valid` and `rollout_mask`).

    obs: dict of tensors (L, B, ...); 'state' (float32, 39) in state mode, or 'pixels' (uint8,
        9 x S x S: topview, frontview, gripperPOV channel-stacked) and 'proprio' (float32, 7)
        in pixel mode, or 'latent' (float32) when a frozen encoder's outputs are cached.
    action: (L, B, A); reward: (L, B, 1) in [-1, 0]; terminated: (L, B, 1) in {0, 1};
    is_first: (L, B, 1) in {0, 1}; task: (L, B) long, curriculum index of each row's task.
    """

    obs: dict[str, torch.Tensor]
    action: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    is_first: torch.Tensor
    task: torch.Tensor

    def to(self, device: torch.device | str) -> Batch:
        return Batch(
            obs={k: v.to(device, non_blocking=True) for k, v in self.obs.items()},
            action=self.action.to(device),
            reward=self.reward.to(device),
            terminated=self.terminated.to(device),
            is_first=self.is_first.to(device),
            task=self.task.to(device),
        )

    @property
    def seq_len(self) -> int:
        return self.action.shape[0]

    @property
    def size(self) -> int:
        return self.action.shape[1]

    def valid(self) -> torch.Tensor:
        """(L-1, B, 1): 1 where transition t (row t -> row t+1) is a real transition."""
        return 1.0 - self.is_first[1:]

    def rollout_mask(self) -> torch.Tensor:
        """(L-1, B, 1): 1 for transitions reachable from row 0 without crossing into another
        episode (a latent rollout started at o_0 is meaningful only there)."""
        return self.valid().cumprod(0)

    def select(self, rows: torch.Tensor) -> Batch:
        """The windows at batch indices `rows` (any order, repeats allowed)."""
        return Batch(
            obs={k: v[:, rows] for k, v in self.obs.items()},
            action=self.action[:, rows],
            reward=self.reward[:, rows],
            terminated=self.terminated[:, rows],
            is_first=self.is_first[:, rows],
            task=self.task[:, rows],
        )


@dataclass
class LossOutput:
    """What `WorldModel.loss` returns."""

    total: torch.Tensor
    """Scalar to backpropagate through the world-model optimiser's parameters."""
    logs: dict[str, float] = field(default_factory=dict)
    """Detached scalars for logging (e.g. consistency, reward, value, termination)."""
    aux: Any = None
    """Model-specific values reused by `head_update` (e.g. detached latents)."""


class WorldModel(nn.Module, ABC):
    """Base class; subclasses set `self.cfg` (their registered config), `self.device` and
    `self.backbone` (an nn.Module) in __init__. Register with `ccfit.models.register_model`."""

    cfg: Any
    device: torch.device
    backbone: nn.Module

    # ------------------------------------------------------------------ structure
    @abstractmethod
    def new_heads(self) -> nn.Module:
        """Fresh task-specific heads on the model's device."""

    def begin_task(self, task_index: int, task_steps: int) -> None:  # noqa: B027 - optional
        """Task `task_index` (curriculum order) starts and trains for `task_steps` env steps;
        heads made after this call belong to it. No-op unless the model has per-task state."""

    # ------------------------------------------------------------------ optimisation
    @abstractmethod
    def world_model_optimizer(self, heads: nn.Module) -> torch.optim.Optimizer:
        """Optimiser over everything `loss` trains: the backbone's trainable parameters and the
        heads trained with it (reward, termination, value). Gradients are clipped to
        `cfg.grad_clip` (global norm over this optimiser's parameters) before each step."""

    @abstractmethod
    def head_optimizers(self, heads: nn.Module) -> dict[str, torch.optim.Optimizer]:
        """Optimisers `head_update` steps (policy, actor, critic), by name; checkpointed."""

    @abstractmethod
    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        """World-model loss with this task's heads (differentiable)."""

    @abstractmethod
    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """Task-agnostic terms only (dynamics consistency, reconstruction, KL): what continual
        methods replay (ER) or take Fisher information from (EWC)."""

    @abstractmethod
    def head_update(
        self,
        batch: Batch,
        heads: nn.Module,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        """Policy/actor/critic steps and target updates after the world-model step; must not
        change the backbone. Returns scalars to log."""

    def replay_obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What replay stores for an episode's observations (T+1, ...): by default the
        observations themselves; `loss` must accept whatever this returns."""
        return obs

    # ------------------------------------------------------------------ acting
    def initial_state(self, heads: nn.Module) -> Any:
        """Acting state at the start of an episode (None for a stateless model)."""
        return None

    @abstractmethod
    def act(
        self, obs: dict[str, torch.Tensor], heads: nn.Module, state: Any, *, eval_mode: bool
    ) -> tuple[np.ndarray, Any]:
        """One action (A,) in [-1, 1] for an unbatched observation on the model's device, and
        the acting state after it (which remembers the action)."""

    def observe(
        self, obs: dict[str, torch.Tensor], action: np.ndarray, heads: nn.Module, state: Any
    ) -> Any:
        """The acting state after a step the model did not choose (random seed steps): o_t
        was seen and `action` taken. Stateless models return `state` unchanged."""
        return state
