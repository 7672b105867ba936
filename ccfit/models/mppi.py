"""MPPI planning in a TD-MPC2-style latent space (Hansen et al., 2024), for TD-MPC2 and PWM.

The model provides `next(z, a)`, `reward(z, a, heads)` (two-hot logits), `termination(z,
heads)` (logit), `pi(z, heads)` and `Q(z, a, heads, 'avg')`; its config the MPPI settings
(horizon, iterations, num_samples, num_elites, num_pi_trajs, min_std, max_std, temperature).
Plans for n observations run as one batch: every model call sees the n x num_samples
candidate sequences at once.
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
    """MPPI from latents z (n, L) -> (actions (n, A) in [-1, 1], final means (n, horizon, A)).

    `prev_mean`: the previous step's final means; shifted by one step they warm-start this
    plan (None: start from zero, as at an episode's first step). Eval returns the first step of
    the final mean (TD-MPC's rule; the official TD-MPC2 samples an elite by score there too, so
    its evaluation also draws among diverging elites); training samples an elite by score and
    adds the final std's noise. Every published run evaluated this way.
    """
    cfg = model.cfg
    hor, num, npi, d = cfg.horizon, cfg.num_samples, cfg.num_pi_trajs, cfg.action_dim
    n, latent = z.shape
    actions = z.new_empty(hor, n, num, d)
    if npi > 0:
        zp = z.unsqueeze(1).expand(n, npi, latent).reshape(n * npi, latent)
        for t in range(hor):
            pi_actions = model.pi(zp, heads)[0]
            actions[t, :, :npi] = pi_actions.view(n, npi, d)
            if t < hor - 1:
                zp = model.next(zp, pi_actions)
    zs = z.unsqueeze(1).expand(n, num, latent).reshape(n * num, latent)
    mean = z.new_zeros(hor, n, d)
    std = z.new_full((hor, n, d), cfg.max_std)
    if prev_mean is not None:
        if tuple(prev_mean.shape) != (n, hor, d):
            shape = tuple(prev_mean.shape)
            raise ValueError(f"acting state must be plan means of shape {(n, hor, d)}, got {shape}")
        mean[:-1] = prev_mean.to(mean.device).transpose(0, 1)[1:]
    rows = torch.arange(n, device=z.device)
    for _ in range(cfg.iterations):
        noise = torch.randn(hor, n, num - npi, d, device=z.device)
        actions[:, :, npi:] = (mean.unsqueeze(2) + std.unsqueeze(2) * noise).clamp(-1, 1)
        value = estimate_value(model, zs, actions.view(hor, n * num, d), heads)
        value = value.nan_to_num(0).view(n, num)
        elite_value, elite = torch.topk(value, cfg.num_elites, dim=1)  # (n, E)
        elite_actions = actions[:, rows.unsqueeze(1), elite]  # (hor, n, E, d)
        score = torch.exp(cfg.temperature * (elite_value - elite_value.amax(1, keepdim=True)))
        score = score / score.sum(1, keepdim=True)
        weight = score.unsqueeze(0).unsqueeze(-1)  # (1, n, E, 1)
        mean = (weight * elite_actions).sum(2)
        var = (weight * (elite_actions - mean.unsqueeze(2)).pow(2)).sum(2)
        std = var.sqrt().clamp(cfg.min_std, cfg.max_std)
    if eval_mode:
        a = mean[0]
    else:
        pick = torch.multinomial(score, 1).squeeze(1)
        a = elite_actions[0, rows, pick] + std[0] * torch.randn(n, d, device=z.device)
    # In row-major strides whatever n is (a transposed view's strides depend on n, and
    # `contiguous` keeps them for n = 1): a compiled plan guards on the strides of its input.
    return a.clamp(-1, 1), mean.transpose(0, 1).clone(memory_format=torch.contiguous_format)
