"""MPPI planning in a TD-MPC2-style latent space (Hansen et al., 2024), for TD-MPC2 and PWM.

The model provides `next(z, a)`, `reward(z, a, heads)` (two-hot logits), `termination(z,
heads)` (logit), `pi(z, heads)` and `Q(z, a, heads, 'avg')`; its config the MPPI settings
(horizon, iterations, num_samples, num_elites, num_pi_trajs, min_std, max_std, temperature).
"""

from __future__ import annotations

import torch


@torch.no_grad()
def estimate_value(model, z: torch.Tensor, actions: torch.Tensor, heads) -> torch.Tensor:
    """Discounted model return of `actions` (horizon, N, A) from latents z (N, L), plus the
    bootstrapped Q at the end; no reward or bootstrap after a predicted termination. (N, 1)."""
    ret = z.new_zeros(z.shape[0], 1)
    ended = z.new_zeros(z.shape[0], 1)
    discount = 1.0
    for t in range(actions.shape[0]):
        r = model.two_hot.logits_to_scalar(model.reward(z, actions[t], heads))
        z = model.next(z, actions[t])
        ret = ret + discount * (1 - ended) * r
        discount *= model.discount
        ended = (ended + (model.termination(z, heads) > 0).float()).clamp(max=1)
    action, _ = model.pi(z, heads)
    return ret + discount * (1 - ended) * model.Q(z, action, heads, "avg")


@torch.no_grad()
def mppi_plan(
    model, z: torch.Tensor, heads, prev_mean: torch.Tensor | None, *, eval_mode: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """MPPI from latent z (1, L) -> (action (A,) in [-1, 1], final mean (horizon, A)).

    `prev_mean`: the previous step's final mean; shifted by one step it warm-starts this plan
    (None: start from zero, as at an episode's first step). Eval returns the first step of the
    final mean; training samples an elite by score and adds the final std's noise.
    """
    cfg = model.cfg
    hor, n, npi, d = cfg.horizon, cfg.num_samples, cfg.num_pi_trajs, cfg.action_dim
    actions = z.new_empty(hor, n, d)
    if npi > 0:
        zp = z.expand(npi, -1)
        for t in range(hor):
            actions[t, :npi] = model.pi(zp, heads)[0]
            if t < hor - 1:
                zp = model.next(zp, actions[t, :npi])
    z = z.expand(n, -1)
    mean = z.new_zeros(hor, d)
    std = z.new_full((hor, d), cfg.max_std)
    if prev_mean is not None:
        if tuple(prev_mean.shape) != (hor, d):
            shape = tuple(prev_mean.shape)
            raise ValueError(f"acting state must be a plan mean of shape {(hor, d)}, got {shape}")
        mean[:-1] = prev_mean[1:].to(mean.device)
    for _ in range(cfg.iterations):
        noise = torch.randn(hor, n - npi, d, device=z.device)
        actions[:, npi:] = (mean.unsqueeze(1) + std.unsqueeze(1) * noise).clamp(-1, 1)
        value = estimate_value(model, z, actions, heads).nan_to_num(0).squeeze(1)
        elite = torch.topk(value, cfg.num_elites).indices
        elite_value, elite_actions = value[elite], actions[:, elite]
        score = torch.exp(cfg.temperature * (elite_value - elite_value.max()))
        score = score / score.sum()
        mean = (score[None, :, None] * elite_actions).sum(1)
        var = (score[None, :, None] * (elite_actions - mean.unsqueeze(1)).pow(2)).sum(1)
        std = var.sqrt().clamp(cfg.min_std, cfg.max_std)
    if eval_mode:
        a = mean[0]
    else:
        pick = torch.multinomial(score, 1)[0]
        a = elite_actions[0, pick] + std[0] * torch.randn(d, device=z.device)
    return a.clamp(-1, 1), mean
