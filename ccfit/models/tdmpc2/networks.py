"""TD-MPC2's networks: the backbone continual methods see, the per-task heads, and the eval
mode acting enters once per env step."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from ccfit.models.encoders import FrozenEncoder, build_encoder
from ccfit.models.layers import EnsembleMLP, SimNorm, init_weights, mlp
from ccfit.models.tdmpc2.config import TDMPC2Config


class TDMPC2Backbone(nn.Module):
    """Encoder + latent dynamics: the only part continual methods see."""

    def __init__(self, cfg: TDMPC2Config, encoder: FrozenEncoder | None = None) -> None:
        super().__init__()
        self.dynamics = mlp(
            cfg.latent_dim + cfg.action_dim,
            [cfg.mlp_dim] * 2,
            cfg.latent_dim,
            act=SimNorm(cfg.simnorm_dim),
        )
        if encoder is None:
            self.encoder: nn.Module = build_encoder(cfg)
            self.apply(init_weights)
        else:
            if (encoder.obs_mode, encoder.latent_dim) != (cfg.obs_mode, cfg.latent_dim):
                raise ValueError(
                    f"frozen encoder is ({encoder.obs_mode}, latent {encoder.latent_dim}) but "
                    f"the config asks for ({cfg.obs_mode}, latent {cfg.latent_dim})"
                )
            self.dynamics.apply(init_weights)
            self.encoder = encoder


class TDMPC2Heads(nn.Module):
    """Task-specific part: reward, termination, Q ensemble (+ target), policy, Q scale."""

    q_scale: torch.Tensor

    def __init__(self, cfg: TDMPC2Config) -> None:
        super().__init__()
        za, h = cfg.latent_dim + cfg.action_dim, [cfg.mlp_dim] * 2
        self.reward = mlp(za, h, cfg.num_bins)
        self.termination = mlp(cfg.latent_dim, h, 1)
        self.qs = EnsembleMLP(cfg.num_q, za, h, cfg.num_bins, dropout=cfg.dropout)
        self.pi = mlp(cfg.latent_dim, h, 2 * cfg.action_dim)
        self.apply(init_weights)
        # Zero last layers: reward and values start at exactly 0 (TD-MPC2).
        nn.init.zeros_(self.reward[-1].weight)
        nn.init.zeros_(self.qs.out.weight)
        self.target_qs = copy.deepcopy(self.qs).requires_grad_(False)
        self.target_qs.train(False)
        # Running 5th-95th percentile range of Q (policy-loss normaliser).
        self.register_buffer("q_scale", torch.ones(1))

    def train(self, mode: bool = True) -> TDMPC2Heads:
        super().train(mode)
        self.target_qs.train(False)  # targets never use dropout
        return self


@contextmanager
def modules_in_eval(*modules: nn.Module) -> Iterator[None]:
    """Modules (and their submodules) in eval mode inside the block, each submodule's previous
    mode restored after it."""
    # Acting enters this once per env step. `Module.train` sets the flag through
    # `Module.__setattr__` (~10 us a module, about a quarter of a smoke PWM act); the flag is a
    # plain instance attribute, so it is set directly. Only modules now training are touched,
    # so what a `train` override keeps in eval (target Qs, frozen encoders) stays so.
    training = [sub for m in modules for sub in m.modules() if sub.training]
    try:
        for sub in training:
            object.__setattr__(sub, "training", False)
        yield
    finally:
        for sub in training:
            object.__setattr__(sub, "training", True)
