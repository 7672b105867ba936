"""Actor-critic learning in imagination (and the 2025 replay-value loss).

From each start (a detached posterior), the actor rolls the prior forward `horizon` steps:
s_0 .. s_H with actions a_0 .. a_{H-1}. Rewards and continue flags of arriving at s_1..s_H
come from the task's heads, values from the critic, and lambda-returns R_0..R_{H-1} are the
targets. Losses are weighted by the chance of still being alive, cumprod(discount * c) /
discount, with c_0 = 1 unless the start is a terminal observation.

- Actor ('dynamics', the recipe): maximise (R - v) / scale by backpropagating through the
  imagined dynamics, rewards and values (only the actor's parameters are stepped).
  ('reinforce', 2025): log pi(a) * sg((R - v) / scale) -- the *normalised* advantage
  (NM512/dreamerv3-torch forgets the normalisation). Both add an entropy bonus.
- Critic: two-hot cross-entropy toward sg(R) on detached states, plus a regulariser toward
  the slow critic's predictions.
- Demonstration cloning (an option, not the recipe's): the actor's mean pulled toward the
  actions of replayed demonstrations at their posteriors.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.heads import DreamerV3Heads
from ccfit.models.dreamerv3.math import lambda_return
from ccfit.models.dreamerv3.networks import normal_entropy, normal_log_prob
from ccfit.models.dreamerv3.rssm import RSSM


@dataclass
class Trajectory:
    """An imagined rollout from N starts."""

    feat: torch.Tensor
    """Model states s_0..s_H, (H + 1, N, F)."""
    action: torch.Tensor
    """Actions a_0..a_{H-1} as sampled (before the dynamics' clipping), (H, N, A)."""
    cont: torch.Tensor
    """Continue flags of s_0..s_H (c_0 from the start, then the continue head's mode or
    probability, `imag_cont`)."""
    weight: torch.Tensor
    """Loss weights cumprod(discount * c) / discount, (H + 1, N, 1), no gradient."""
    mean: torch.Tensor
    """The actor's mean at s_0..s_{H-1} (H, N, A), with a graph when imagined with one."""
    std: torch.Tensor
    """The actor's standard deviation at s_0..s_{H-1} (H, N, A)."""


def imagine(
    rssm: RSSM,
    heads: DreamerV3Heads,
    deter: torch.Tensor,
    stoch: torch.Tensor,
    start_cont: torch.Tensor,
    horizon: int,
    discount: float,
    cont_from: str = "mode",
) -> Trajectory:
    """Roll the actor through the prior from starts (N, D), (N, S, C); gradients flow from
    the actor's reparameterised samples through the dynamics (use no_grad when not needed).
    The actor reads detached states, as in the recipe: its gradient is the path through
    its sampled actions only. `cont_from`: the continue flags of s_1..s_H are the continue
    head's mode ('mode', the recipe) or its probability ('prob'), without gradient."""
    feats = [rssm.feat(deter, stoch)]
    actions, means, stds = [], [], []
    for _ in range(horizon):
        mean, std = heads.actor(feats[-1].detach())
        action = mean + std * torch.randn_like(mean)
        deter, stoch = rssm.img_step(deter, stoch, action)
        actions.append(action)
        means.append(mean)
        stds.append(std)
        feats.append(rssm.feat(deter, stoch))
    feat = torch.stack(feats)
    with torch.no_grad():
        logit = heads.cont(feat[1:])
        cont = torch.sigmoid(logit) if cont_from == "prob" else (logit > 0).to(feat.dtype)
        cont = torch.cat([start_cont[None], cont])
        weight = torch.cumprod(discount * cont, 0) / discount
    stack = torch.stack
    return Trajectory(feat, stack(actions), cont, weight, stack(means), stack(stds))


def imagined_returns(
    cfg: DreamerV3Config,
    heads: DreamerV3Heads,
    traj: Trajectory,
    critic_logits: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(lambda-returns R_0..R_{H-1} (H, N, 1), values v(s_0..s_H) (H + 1, N, 1)); with a
    graph only when the trajectory has one (the 'dynamics' actor gradient needs it).
    `critic_logits`: the critic's logits at s_0..s_H when the caller has them."""
    with torch.set_grad_enabled(traj.feat.requires_grad):
        reward = heads.reward_mean(traj.feat[1:])
        if critic_logits is None:
            critic_logits = heads.critic(traj.feat)
        value = heads.twohot.logits_to_scalar(critic_logits)
    return lambda_return(reward, traj.cont[1:], value, cfg.discount, cfg.return_lambda), value


def behavior_losses(
    cfg: DreamerV3Config, heads: DreamerV3Heads, traj: Trajectory, update_retnorm: bool = True
) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """(actor loss, critic loss, detached logs); updates the return normaliser first, as the
    recipe does, then scales the advantage with the updated statistics.

    One critic pass serves the returns (the actor's path through the values) and the critic's
    loss: the critic's parameter gradient does not depend on whether its inputs are detached,
    and each loss is differentiated for its own module only (`DreamerV3._step`). Likewise the
    actor's outputs from imagination are reused when they carry a graph."""
    logits = heads.critic(traj.feat)
    ret, value = imagined_returns(cfg, heads, traj, logits)
    if update_retnorm:
        heads.retnorm.update(ret)
    scale = heads.retnorm.scale()
    adv = (ret - value[:-1]) / scale
    states = traj.feat[:-1].detach()
    weight = traj.weight[:-1]
    mean, std = (traj.mean, traj.std) if traj.std.requires_grad else heads.actor(states)
    entropy = normal_entropy(std)
    if cfg.actor_grad == "dynamics":
        objective = adv
    else:
        objective = normal_log_prob(traj.action.detach(), mean, std) * adv.detach()
    actor_loss = -((objective + cfg.actor_entropy * entropy) * weight).mean()

    logits = logits[:-1]
    target = ret.detach()
    critic = heads.twohot.cross_entropy(logits, target)
    reg = heads.twohot.cross_entropy(logits, heads.slow_value(states))
    critic_loss = ((critic + cfg.slow_critic_reg * reg) * weight).mean()
    logs = {
        "actor_loss": actor_loss.detach(),
        "critic_loss": critic_loss.detach(),
        "return": ret.detach().mean(),
        "value": value.detach().mean(),
        "advantage": adv.detach().mean(),
        "return_scale": scale.detach(),
        "actor_entropy": entropy.detach().mean(),
        "actor_std": std.detach().mean(),
        "imag_cont": traj.cont[1:].mean(),
    }
    return actor_loss, critic_loss, logs


def demo_cloning(
    heads: DreamerV3Heads,
    feat: torch.Tensor,
    action: torch.Tensor,
    valid: torch.Tensor,
    loss: str = "mse",
) -> torch.Tensor:
    """Mean over the rows with a real transition (`valid` (T, k, 1)) of the squared distance
    of the actor's mean at posteriors `feat` (T, k, F) to the demonstrated `action` (T, k, A)
    taken from each row (its posterior has read the row's observation and the action before);
    `loss='nll'`: of -log N(action; mean, std) under the actor's distribution instead."""
    mean, std = heads.actor(feat)
    if loss == "nll":
        err = -normal_log_prob(action, mean, std)
    else:
        err = (mean - action).pow(2).sum(-1, keepdim=True)
    return (err * valid).sum() / valid.sum().clamp(min=1.0)


# ---------------------------------------------------------------------- 2025: replay value


def replay_lambda_return(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    valid: torch.Tensor,
    boot: torch.Tensor,
    discount: float,
    lam: float,
) -> torch.Tensor:
    """lambda-returns along replayed rows (K, B, 1), bootstrapped from each row's imagined
    return `boot` (K, B, 1) (the 2025 recipe's replay-value target):
        G_t = r_t + discount (1 - term_t) ((1 - lam) boot_{t+1} + lam G_{t+1})
    where row t's transition is real (`valid`), else (and on the last row) G_t = boot_t."""
    out = [boot[-1]]
    for t in reversed(range(boot.shape[0] - 1)):
        nxt = (1.0 - lam) * boot[t + 1] + lam * out[-1]
        g = reward[t] + discount * (1.0 - terminated[t]) * nxt
        out.append(torch.where(valid[t] > 0, g, boot[t]))
    return torch.stack(out[::-1])


def replay_value_loss(
    cfg: DreamerV3Config,
    heads: DreamerV3Heads,
    critic_logits: torch.Tensor,
    feat: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
) -> torch.Tensor:
    """CE(critic, target) + slow regulariser on the unmasked rows, averaged over all rows
    (masked ones count 0, as in the 2025 code's plain mean), unscaled."""
    reg = heads.twohot.cross_entropy(critic_logits, heads.slow_value(feat.detach()))
    loss = heads.twohot.cross_entropy(critic_logits, target) + cfg.slow_critic_reg * reg
    return (loss * mask).mean()
