"""DreamerV3's numerical pieces, each testable on its own.

- symlog / symexp and the two-hot encoding over bins evenly spaced in symlog space (shared
  with TD-MPC2 through `ccfit.models.layers`).
- Categorical latents: unimix logits, straight-through samples, KL, and the balanced KL loss
  with free nats.
- lambda-returns and the return normaliser (EMA of return percentiles).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ccfit.models.layers import TwoHot, quantiles, symexp, symlog

__all__ = [
    "TwoHot",
    "symlog",
    "symexp",
    "unimix_logits",
    "sample_onehot",
    "mode_onehot",
    "categorical_kl",
    "kl_loss",
    "lambda_return",
    "ReturnNormalizer",
]


def unimix_logits(logits: torch.Tensor, unimix: float) -> torch.Tensor:
    """Log-probabilities of (1 - unimix) softmax(logits) + unimix / classes (last dim).

    Every class keeps a probability of at least unimix / classes, so KLs stay finite and the
    latents never become deterministic."""
    probs = F.softmax(logits, dim=-1)
    if unimix > 0:
        probs = (1.0 - unimix) * probs + unimix / logits.shape[-1]
    return torch.log(probs)


def sample_onehot(logits: torch.Tensor) -> torch.Tensor:
    """One-hot sample with straight-through gradients of the probabilities. Sampled as an
    exponential race, argmax p_i / E_i with E_i ~ Exp(1) (Gumbel-max in another form: the
    same distribution in fewer operations)."""
    probs = F.softmax(logits, dim=-1)
    index = (probs.detach() / torch.empty_like(probs).exponential_()).argmax(-1)
    onehot = F.one_hot(index, logits.shape[-1]).to(probs.dtype)
    return onehot + probs - probs.detach()


def mode_onehot(logits: torch.Tensor) -> torch.Tensor:
    """The most likely class as a one-hot (no gradient)."""
    return F.one_hot(logits.argmax(-1), logits.shape[-1]).to(logits.dtype)


def categorical_kl(p_logits: torch.Tensor, q_logits: torch.Tensor) -> torch.Tensor:
    """KL(p || q) of categoricals given normalised log-probabilities (..., latents, classes),
    summed over classes and latents -> (...)."""
    p = p_logits.exp()
    return (p * (p_logits - q_logits)).sum((-2, -1))


def kl_loss(
    post_logits: torch.Tensor, prior_logits: torch.Tensor, free_nats: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(dyn, rep) per row, each max(free_nats, KL) with KL summed over the latents.

    dyn = KL(sg(post) || prior) trains the prior toward the posterior; rep = KL(post ||
    sg(prior)) trains the representation toward predictability. Both have the same value;
    the clamp zeroes the gradient of a row whose KL is below `free_nats`. Scales (0.5 / 0.1
    in the recipe) are applied by the caller."""
    dyn = categorical_kl(post_logits.detach(), prior_logits)
    rep = categorical_kl(post_logits, prior_logits.detach())
    return dyn.clamp(min=free_nats), rep.clamp(min=free_nats)


def lambda_return(
    reward: torch.Tensor, cont: torch.Tensor, value: torch.Tensor, discount: float, lam: float
) -> torch.Tensor:
    """lambda-returns R_0..R_{H-1} of an imagined trajectory s_0..s_H.

    reward[i], cont[i]: reward and continue flag of arriving at s_{i+1} (H, ...);
    value: v(s_0..s_H) (H + 1, ...). R_i = r_{i+1} + discount c_{i+1} ((1 - lam) v_{i+1} +
    lam R_{i+1}), R_H = v_H. lam = 1 gives discounted Monte Carlo returns bootstrapped at
    the horizon; c = 0 stops bootstrapping."""
    horizon = reward.shape[0]
    if cont.shape[0] != horizon or value.shape[0] != horizon + 1:
        raise ValueError(
            f"need H rewards/conts and H+1 values, got {reward.shape[0]}, "
            f"{cont.shape[0]}, {value.shape[0]}"
        )
    disc = discount * cont
    interm = reward + disc * (1.0 - lam) * value[1:]
    out = [value[-1]]
    for i in reversed(range(horizon)):
        out.append(interm[i] + disc[i] * lam * out[-1])
    return torch.stack(out[::-1][:-1])


class ReturnNormalizer(nn.Module):
    """Scale of the returns for the actor's advantage: max(1, P_high - P_low), with the
    percentiles (5th, 95th) tracked by an EMA (rate 0.01) started at zero, as in the
    recipe. Buffers, so the statistics live in (and are stored with) the heads."""

    low: torch.Tensor
    high: torch.Tensor

    def __init__(self, rate: float, q_low: float, q_high: float) -> None:
        super().__init__()
        self.rate, self.q_low, self.q_high = rate, q_low, q_high
        self.register_buffer("low", torch.zeros(()))
        self.register_buffer("high", torch.zeros(()))

    @torch.no_grad()
    def update(self, returns: torch.Tensor) -> None:
        x = returns.detach().float().flatten()
        q = quantiles(x, (self.q_low, self.q_high))
        self.low.mul_(1.0 - self.rate).add_(self.rate * q[0])
        self.high.mul_(1.0 - self.rate).add_(self.rate * q[1])

    def scale(self) -> torch.Tensor:
        """max(1, high - low): returns spanning less than 1 are not scaled up."""
        return (self.high - self.low).clamp(min=1.0)
