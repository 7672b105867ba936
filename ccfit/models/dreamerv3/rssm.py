"""The recurrent state-space model: a GRU core with categorical stochastic latents.

State = (deter (..., D), stoch (..., S, C) one-hot). One step from (h, z, a):
    x = dense([z, a]);  h' = GRU(x, h);  prior(h') -> logits;  posterior(h', embed) -> logits
The GRU is the 2023 variant: one Linear over [h, x] -> LayerNorm (eps 1e-3) -> reset, cand,
update; cand = tanh(reset * cand); update gate with bias -1 (keeps memory early on). It is
built from nn.Linear so that PackNet (which prunes Linear/Conv weights) prunes it too.
Categoricals mix in 1% uniform; samples are straight-through one-hots.
"""

from __future__ import annotations

import torch
from torch import nn

from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.math import mode_onehot, sample_onehot, unimix_logits
from ccfit.models.dreamerv3.networks import NORM_EPS, dense


def clip_action(action: torch.Tensor) -> torch.Tensor:
    """Actions beyond [-1, 1] (unclipped imagined samples) scaled back elementwise, i.e.
    clipped in value, with the scale a constant for the gradient."""
    return action / action.detach().abs().clamp(min=1.0)


class RSSM(nn.Module):
    """Prior, posterior and learned initial state; time-major sequences."""

    def __init__(self, cfg: DreamerV3Config, embed_dim: int) -> None:
        super().__init__()
        self.deter, self.stoch, self.classes = cfg.deter, cfg.stoch, cfg.classes
        self.unimix = cfg.unimix
        latent = cfg.stoch * cfg.classes
        self.img_in = dense(latent + cfg.action_dim, cfg.hidden)
        self.gru = nn.Linear(cfg.hidden + cfg.deter, 3 * cfg.deter, bias=False)
        self.gru_norm = nn.LayerNorm(3 * cfg.deter, eps=NORM_EPS)
        self.img_out = nn.Sequential(dense(cfg.deter, cfg.hidden), nn.Linear(cfg.hidden, latent))
        self.obs_out = nn.Sequential(
            dense(cfg.deter + embed_dim, cfg.hidden), nn.Linear(cfg.hidden, latent)
        )
        # Learned initial state: deter = tanh(initial), stoch = the prior's mode at it.
        self.initial = nn.Parameter(torch.zeros(cfg.deter))

    # ------------------------------------------------------------------ pieces
    def _logits(self, net: nn.Module, x: torch.Tensor) -> torch.Tensor:
        logits = net(x).reshape(*x.shape[:-1], self.stoch, self.classes)
        return unimix_logits(logits, self.unimix)

    def prior(self, deter: torch.Tensor) -> torch.Tensor:
        """Normalised prior log-probabilities (..., S, C) at deterministic state `deter`."""
        return self._logits(self.img_out, deter)

    def posterior(self, deter: torch.Tensor, embed: torch.Tensor) -> torch.Tensor:
        """Normalised posterior log-probabilities (..., S, C) given the observation's embed."""
        return self._logits(self.obs_out, torch.cat([deter, embed], -1))

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(deter (n, D), stoch (n, S, C)) at the learned initial state."""
        deter = torch.tanh(self.initial).expand(n, self.deter)
        return deter, mode_onehot(self.prior(deter))

    def core(
        self, deter: torch.Tensor, stoch: torch.Tensor, action: torch.Tensor, clipped: bool = False
    ) -> torch.Tensor:
        """Next deterministic state after taking `action` from (deter, stoch); `clipped`:
        the caller has applied `clip_action` already."""
        if not clipped:
            action = clip_action(action)
        x = self.img_in(torch.cat([stoch.flatten(-2), action], -1))
        gates = self.gru_norm(self.gru(torch.cat([deter, x], -1)))
        reset, cand, update = gates.chunk(3, -1)
        cand = torch.tanh(torch.sigmoid(reset) * cand)
        update = torch.sigmoid(update - 1.0)
        return update * cand + (1.0 - update) * deter

    def feat(self, deter: torch.Tensor, stoch: torch.Tensor) -> torch.Tensor:
        """What the heads and decoder read: [deter, flattened stoch]."""
        return torch.cat([deter, stoch.flatten(-2)], -1)

    # ------------------------------------------------------------------ steps
    def img_step(
        self, deter: torch.Tensor, stoch: torch.Tensor, action: torch.Tensor, sample: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Imagined step: (deter', stoch' drawn from the prior)."""
        deter = self.core(deter, stoch, action)
        logits = self.prior(deter)
        return deter, sample_onehot(logits) if sample else mode_onehot(logits)

    def obs_step(
        self,
        deter: torch.Tensor,
        stoch: torch.Tensor,
        action: torch.Tensor,
        embed: torch.Tensor,
        is_first: torch.Tensor,
        sample: bool = True,
        initial: tuple[torch.Tensor, torch.Tensor] | None = None,
        clipped: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Filtering step: (deter', stoch' from the posterior, posterior logits).

        Where is_first (..., 1) is 1 the previous state becomes the learned initial state and
        the previous action zero before the step, as at the start of every episode.
        `initial`: `initial_state(n)` when the caller has it already (one per sequence);
        `clipped`: as in `core`."""
        first = is_first > 0
        init_deter, init_stoch = initial or self.initial_state(deter.shape[0])
        deter = torch.where(first, init_deter, deter)
        stoch = torch.where(first[..., None], init_stoch, stoch)
        action = torch.where(first, 0.0, action)
        deter = self.core(deter, stoch, action, clipped)
        logits = self.posterior(deter, embed)
        return deter, sample_onehot(logits) if sample else mode_onehot(logits), logits

    def observe(
        self,
        embed: torch.Tensor,
        action: torch.Tensor,
        is_first: torch.Tensor,
        sample: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Posteriors along replay windows (time-major, one transition per row).

        Row t's posterior reads action[t - 1]; row 0 starts from the initial state (what
        came before the window is unknown). Returns deter (L, B, D), stoch (L, B, S, C),
        posterior and prior log-probabilities (L, B, S, C)."""
        length, batch = embed.shape[:2]
        initial = self.initial_state(batch)
        deter, stoch = initial
        action = clip_action(action)  # once for the window, not at every step
        prev_action = torch.zeros_like(action[0])
        deters, stochs, posts = [], [], []
        for t in range(length):
            deter, stoch, post = self.obs_step(
                deter, stoch, prev_action, embed[t], is_first[t], sample, initial, clipped=True
            )
            prev_action = action[t]
            deters.append(deter)
            stochs.append(stoch)
            posts.append(post)
        deter = torch.stack(deters)
        # The prior only depends on deter: one batched call instead of one per step.
        return deter, torch.stack(stochs), torch.stack(posts), self.prior(deter)
