"""DreamerV3's task-specific heads: one module made fresh per task, stored after it."""

from __future__ import annotations

import copy

import torch
from torch import nn

from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.math import ReturnNormalizer, TwoHot
from ccfit.models.dreamerv3.networks import Actor, Head
from ccfit.models.layers import polyak


class DreamerV3Heads(nn.Module):
    """reward and continue (trained with the world model; their gradients reach the
    backbone), actor, critic, its slow EMA copy, and the return normaliser's statistics."""

    def __init__(self, cfg: DreamerV3Config) -> None:
        super().__init__()
        self.twohot = TwoHot(cfg.reward_bins, -cfg.bin_range, cfg.bin_range)
        self.reward = Head(cfg, cfg.reward_bins, zero_init=True)
        self.cont = Head(cfg, 1)
        self.actor = Actor(cfg)
        self.critic = Head(cfg, cfg.reward_bins, zero_init=True)
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.retnorm = ReturnNormalizer(cfg.retnorm_rate, cfg.retnorm_low, cfg.retnorm_high)

    def reward_mean(self, feat: torch.Tensor) -> torch.Tensor:
        """Expected reward (..., 1) of arriving in model state `feat`."""
        return self.twohot.logits_to_scalar(self.reward(feat))

    def value(self, feat: torch.Tensor) -> torch.Tensor:
        """Critic's expected return (..., 1)."""
        return self.twohot.logits_to_scalar(self.critic(feat))

    def slow_value(self, feat: torch.Tensor) -> torch.Tensor:
        """Slow critic's expected return (..., 1), no gradient."""
        with torch.no_grad():
            return self.twohot.logits_to_scalar(self.slow_critic(feat))

    def update_slow_critic(self, fraction: float) -> None:
        """slow <- (1 - fraction) slow + fraction critic."""
        polyak(list(self.slow_critic.parameters()), list(self.critic.parameters()), fraction)
