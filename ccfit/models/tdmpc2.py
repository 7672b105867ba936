"""TD-MPC2 (Hansen et al., 2024) split into a continual backbone and per-task heads.

Backbone (task-agnostic): observation encoder + latent dynamics `next(z, a)` (SimNorm output).
Heads (per task): two-hot reward, termination logit, Q ensemble (+ Polyak target copy),
tanh-Gaussian policy, and the running Q scale used to normalise the policy loss.

Training follows the paper: the latent rollout over the horizon is matched to the detached
encodings of the next observations (consistency), rewards and TD targets (from two random
target Q members, masked after termination) are learnt by two-hot cross-entropy, termination by
binary cross-entropy; per-step weights rho**t. The policy maximises scale-normalised Q plus an
entropy bonus on detached latents with its own optimiser. Acting is MPPI in latent space,
warm-started from the previous plan and seeded with policy rollouts.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ccfit.config import TDMPC2Config
from ccfit.models.base import LATENT_KEY, Batch, LossOutput, WorldModel
from ccfit.models.encoders import FrozenEncoder, build_encoder
from ccfit.models.layers import EnsembleMLP, SimNorm, TwoHot, init_weights, mlp

Q_RETURN_TYPES = ("all", "min", "avg")


def default_device() -> torch.device:
    """CUDA when available, else CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class TDMPC2Backbone(nn.Module):
    """Encoder + latent dynamics: the only part continual methods see."""

    def __init__(self, cfg: TDMPC2Config, encoder: FrozenEncoder | None = None) -> None:
        super().__init__()
        self.dynamics = mlp(
            cfg.latent_dim + cfg.action_dim, [cfg.mlp_dim] * 2, cfg.latent_dim,
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
    prev_mean: torch.Tensor

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
        # Previous MPPI mean, for warm starts; not part of the saved state.
        self.register_buffer(
            "prev_mean", torch.zeros(cfg.horizon, cfg.action_dim), persistent=False
        )

    def train(self, mode: bool = True) -> TDMPC2Heads:
        super().train(mode)
        self.target_qs.train(False)  # targets never use dropout
        return self


@contextmanager
def _eval_mode(*modules: nn.Module) -> Iterator[None]:
    flags = [m.training for m in modules]
    try:
        for m in modules:
            m.train(False)
        yield
    finally:
        for m, f in zip(modules, flags, strict=True):
            m.train(f)


class TDMPC2(WorldModel):
    """TD-MPC2 world model with the benchmark's backbone/heads split."""

    def __init__(
        self,
        cfg: TDMPC2Config,
        device: torch.device | str | None = None,
        encoder: FrozenEncoder | None = None,
    ) -> None:
        """`encoder`: a pretrained encoder from `load_frozen_encoder` to use (frozen) instead
        of a trainable one; it stays in the backbone but has no trainable parameters."""
        super().__init__()
        self.cfg = cfg
        self.device = torch.device(device) if device is not None else default_device()
        self.backbone = TDMPC2Backbone(cfg, encoder)
        self.two_hot = TwoHot(cfg.num_bins, cfg.vmin, cfg.vmax)
        self.discount = cfg.discount
        self.to(self.device)

    # ---------------------------------------------------------------- construction / params

    def new_heads(self) -> TDMPC2Heads:
        return TDMPC2Heads(self.cfg).to(self.device)

    def param_groups(self, heads: nn.Module) -> list[dict]:
        cfg = self.cfg
        h = _heads(heads)
        value_params = [*h.reward.parameters(), *h.termination.parameters(), *h.qs.parameters()]
        groups = [
            {"name": "encoder", "params": list(self.backbone.encoder.parameters()),
             "lr": cfg.lr * cfg.enc_lr_scale},
            {"name": "dynamics", "params": list(self.backbone.dynamics.parameters()),
             "lr": cfg.lr},
            {"name": "heads", "params": value_params, "lr": cfg.lr},
        ]  # fmt: skip
        for g in groups:  # a frozen encoder contributes nothing
            g["params"] = [p for p in g["params"] if p.requires_grad]
        return [g for g in groups if g["params"]]

    def policy_parameters(self, heads: nn.Module) -> list[nn.Parameter]:
        return list(_heads(heads).pi.parameters())

    def make_policy_optimizer(self, heads: nn.Module) -> torch.optim.Optimizer:
        """The policy optimiser of the official recipe (Adam, lr, eps 1e-5)."""
        return torch.optim.Adam(
            self.policy_parameters(heads), lr=self.cfg.lr, eps=self.cfg.policy_adam_eps
        )

    def num_parameters(self, heads: nn.Module | None = None) -> dict[str, int]:
        """Trainable parameter counts: backbone, heads (without target copies), total."""
        out = {"backbone": sum(p.numel() for p in self.backbone.parameters() if p.requires_grad)}
        if heads is not None:
            h = _heads(heads)
            out["heads"] = sum(
                p.numel() for n, p in h.named_parameters() if not n.startswith("target_qs.")
            )
        out["total"] = sum(out.values())
        return out

    # ---------------------------------------------------------------- verbs

    def encode(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Observation dict (leading dims ...) -> latent (..., latent_dim). A dict holding
        LATENT_KEY carries a frozen encoder's output already (see `replay_obs`)."""
        if LATENT_KEY in obs:
            if not isinstance(self.backbone.encoder, FrozenEncoder):
                raise ValueError(f"{LATENT_KEY!r} observations need a frozen encoder")
            return obs[LATENT_KEY]
        return self.backbone.encoder(obs)

    @torch.no_grad()
    def replay_obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """With a frozen encoder, replay stores its latents instead of the frames: the encoder
        never changes and never augments, so encoding once at insertion gives the same latents
        as encoding every sampled batch, for a fraction of the compute and memory."""
        encoder = self.backbone.encoder
        if not isinstance(encoder, FrozenEncoder):
            return obs
        z = encoder({k: v.to(self.device) for k, v in obs.items()})
        return {LATENT_KEY: z.float().cpu()}

    def next(self, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Latent dynamics."""
        return self.backbone.dynamics(torch.cat([z, a], dim=-1))

    def reward(self, z: torch.Tensor, a: torch.Tensor, heads: TDMPC2Heads) -> torch.Tensor:
        """Reward logits (..., num_bins)."""
        return heads.reward(torch.cat([z, a], dim=-1))

    def termination(self, z: torch.Tensor, heads: TDMPC2Heads) -> torch.Tensor:
        """Termination logit (..., 1) of arriving in latent z."""
        return heads.termination(z)

    def pi(self, z: torch.Tensor, heads: TDMPC2Heads) -> tuple[torch.Tensor, dict]:
        """Sample a tanh-squashed Gaussian action; info has mean, log_std, entropy terms."""
        cfg = self.cfg
        mean, log_std = heads.pi(z).chunk(2, dim=-1)
        # Smoothly bound the log-std to [log_std_min, log_std_max].
        log_std = cfg.log_std_min + 0.5 * (cfg.log_std_max - cfg.log_std_min) * (
            torch.tanh(log_std) + 1
        )
        eps = torch.randn_like(mean)
        action = mean + eps * log_std.exp()
        log_prob = (-0.5 * eps.pow(2) - log_std).sum(-1, keepdim=True) - 0.5 * math.log(
            2 * math.pi
        ) * eps.shape[-1]
        mean, action = torch.tanh(mean), torch.tanh(action)
        log_prob = log_prob - torch.log(F.relu(1 - action.pow(2)) + 1e-6).sum(-1, keepdim=True)
        entropy = -log_prob
        info = {
            "mean": mean, "log_std": log_std, "entropy": entropy,
            # As TD-MPC2: the entropy bonus scales with the action dimension.
            "scaled_entropy": entropy * eps.shape[-1],
        }
        return action, info

    def Q(  # noqa: N802 - the paper's name
        self,
        z: torch.Tensor,
        a: torch.Tensor,
        heads: TDMPC2Heads,
        return_type: str = "min",
        target: bool = False,
        detach: bool = False,
    ) -> torch.Tensor:
        """'all': logits (num_q, ..., num_bins); 'min'/'avg': scalar (..., 1) over two random
        members. `target` uses the Polyak copy; `detach` blocks gradients into the Qs."""
        if return_type not in Q_RETURN_TYPES:
            raise ValueError(f"unknown return_type {return_type!r}; valid: {Q_RETURN_TYPES}")
        net = heads.target_qs if target else heads.qs
        za = torch.cat([z, a], dim=-1)
        if return_type == "all":
            return net(za, detach=detach)
        # Only the two randomly chosen members are evaluated.
        pair = torch.randperm(self.cfg.num_q, device=z.device)[:2]
        q = self.two_hot.logits_to_scalar(net(za, detach=detach, members=pair))
        return torch.minimum(q[0], q[1]) if return_type == "min" else 0.5 * (q[0] + q[1])

    # ---------------------------------------------------------------- losses

    def _rollout(self, batch: Batch) -> tuple[torch.Tensor, ...]:
        """Latent rollout from obs[0]: (zs with grad (H+1, B, L), detached next-obs latents
        (H, B, L), consistency loss, alive mask (H, B, 1))."""
        cfg, horizon = self.cfg, batch.horizon
        with torch.no_grad():
            next_z = self.encode({k: v[1:] for k, v in batch.obs.items()})
        # Transition t is valid if no termination happened before it (guards subsequences that
        # run past an absorbing success into another episode).
        alive = torch.cat(
            [torch.ones_like(batch.terminated[:1]), 1 - batch.terminated[:-1]], dim=0
        ).cumprod(0)
        z = self.encode({k: v[0] for k, v in batch.obs.items()})
        zs, consistency = [z], z.new_zeros(())
        for t in range(horizon):
            z = self.next(z, batch.action[t])
            err = (z - next_z[t]).pow(2).mean(-1, keepdim=True) * alive[t]
            consistency = consistency + err.mean() * cfg.rho**t
            zs.append(z)
        return torch.stack(zs), next_z, consistency / horizon, alive

    @torch.no_grad()
    def _td_target(
        self, next_z: torch.Tensor, reward: torch.Tensor, terminated: torch.Tensor, heads
    ) -> torch.Tensor:
        action, _ = self.pi(next_z, heads)
        q = self.Q(next_z, action, heads, "min", target=True)
        return reward + self.discount * (1 - terminated) * q

    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        cfg, h = self.cfg, _heads(heads)
        horizon = batch.horizon
        zs, next_z, consistency, alive = self._rollout(batch)
        td = self._td_target(next_z, batch.reward, batch.terminated, h)

        rho = cfg.rho ** torch.arange(horizon, device=zs.device, dtype=zs.dtype)
        w = rho.view(horizon, 1, 1) * alive  # (H, B, 1)
        _zs = zs[:-1]
        reward_ce = self.two_hot.cross_entropy(self.reward(_zs, batch.action, h), batch.reward)
        reward_loss = (reward_ce * w).sum(0).mean() / horizon
        q_logits = self.Q(_zs, batch.action, h, "all")  # (num_q, H, B, bins)
        value_ce = self.two_hot.cross_entropy(q_logits, td.expand(cfg.num_q, -1, -1, -1))
        value_loss = (value_ce * w).sum((0, 1)).mean() / (horizon * cfg.num_q)
        term_bce = F.binary_cross_entropy_with_logits(
            self.termination(zs[1:], h), batch.terminated, reduction="none"
        )
        term_loss = (term_bce * alive).mean()

        total = (
            cfg.consistency_coef * consistency
            + cfg.reward_coef * reward_loss
            + cfg.value_coef * value_loss
            + cfg.termination_coef * term_loss
        )
        logs = {
            "consistency": consistency.item(), "reward": reward_loss.item(),
            "value": value_loss.item(), "termination": term_loss.item(), "total": total.item(),
        }
        return LossOutput(total=total, logs=logs, aux={"zs": zs.detach()})

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """consistency_coef x consistency: the same scale as that term inside `loss`."""
        return self.cfg.consistency_coef * self._rollout(batch)[2]

    def head_update(
        self, batch: Batch, heads: nn.Module, out: LossOutput, policy_optim: torch.optim.Optimizer
    ) -> dict[str, float]:
        cfg, h = self.cfg, _heads(heads)
        zs = out.aux["zs"] if out.aux is not None else None
        if zs is None:
            with torch.no_grad():
                zs = self._rollout(batch)[0]
        zs = zs.detach()
        action, info = self.pi(zs, h)
        q = self.Q(zs, action, h, "avg", detach=True)
        with torch.no_grad():
            lo, hi = torch.quantile(q[0].float().flatten(), q.new_tensor([0.05, 0.95]))
            h.q_scale.lerp_((hi - lo).clamp(min=1.0).reshape(1), cfg.tau)
        q = q / h.q_scale
        rho = cfg.rho ** torch.arange(zs.shape[0], device=zs.device, dtype=zs.dtype)
        pi_loss = (-(cfg.entropy_coef * info["scaled_entropy"] + q).mean(dim=(1, 2)) * rho).mean()
        policy_optim.zero_grad(set_to_none=True)
        pi_loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.policy_parameters(h), cfg.grad_clip_norm)
        policy_optim.step()
        policy_optim.zero_grad(set_to_none=True)
        with torch.no_grad():
            for p, tp in zip(h.qs.parameters(), h.target_qs.parameters(), strict=True):
                tp.lerp_(p, cfg.tau)
        return {
            "pi_loss": pi_loss.item(), "pi_grad_norm": grad_norm.item(),
            "pi_entropy": info["entropy"].mean().item(), "q_scale": h.q_scale.item(),
        }

    # ---------------------------------------------------------------- planning

    @torch.no_grad()
    def act(
        self, obs: Mapping[str, torch.Tensor], heads: nn.Module, *, t0: bool, eval_mode: bool
    ) -> np.ndarray:
        h = _heads(heads)
        batched = {k: torch.as_tensor(v, device=self.device).unsqueeze(0) for k, v in obs.items()}
        with _eval_mode(self.backbone, h):
            z = self.encode(batched)
            return self.plan(z, h, t0=t0, eval_mode=eval_mode).cpu().numpy()

    @torch.no_grad()
    def _estimate_value(self, z: torch.Tensor, actions: torch.Tensor, heads) -> torch.Tensor:
        """Discounted model return over the horizon + bootstrapped Q; (N, 1)."""
        ret = z.new_zeros(z.shape[0], 1)
        ended = z.new_zeros(z.shape[0], 1)
        discount = 1.0
        for t in range(actions.shape[0]):
            r = self.two_hot.logits_to_scalar(self.reward(z, actions[t], heads))
            z = self.next(z, actions[t])
            ret = ret + discount * (1 - ended) * r
            discount *= self.discount
            ended = (ended + (self.termination(z, heads) > 0).float()).clamp(max=1)
        action, _ = self.pi(z, heads)
        return ret + discount * (1 - ended) * self.Q(z, action, heads, "avg")

    @torch.no_grad()
    def plan(self, z: torch.Tensor, heads: TDMPC2Heads, *, t0: bool, eval_mode: bool):
        """MPPI from latent z (1, L) -> action (action_dim,) in [-1, 1]. Eval returns the first
        step of the final MPPI mean; training samples an elite by score and adds std noise."""
        cfg = self.cfg
        hor, n, npi, d = cfg.horizon, cfg.num_samples, cfg.num_pi_trajs, cfg.action_dim
        actions = z.new_empty(hor, n, d)
        if npi > 0:
            zp = z.expand(npi, -1)
            for t in range(hor):
                actions[t, :npi] = self.pi(zp, heads)[0]
                if t < hor - 1:
                    zp = self.next(zp, actions[t, :npi])
        z = z.expand(n, -1)
        mean = z.new_zeros(hor, d)
        std = z.new_full((hor, d), cfg.max_std)
        if not t0:
            mean[:-1] = heads.prev_mean[1:]
        for _ in range(cfg.iterations):
            noise = torch.randn(hor, n - npi, d, device=z.device)
            actions[:, npi:] = (mean.unsqueeze(1) + std.unsqueeze(1) * noise).clamp(-1, 1)
            value = self._estimate_value(z, actions, heads).nan_to_num(0).squeeze(1)
            elite = torch.topk(value, cfg.num_elites).indices
            elite_value, elite_actions = value[elite], actions[:, elite]
            score = torch.exp(cfg.temperature * (elite_value - elite_value.max()))
            score = score / score.sum()
            mean = (score[None, :, None] * elite_actions).sum(1)
            var = (score[None, :, None] * (elite_actions - mean.unsqueeze(1)).pow(2)).sum(1)
            std = var.sqrt().clamp(cfg.min_std, cfg.max_std)
        heads.prev_mean.copy_(mean)
        if eval_mode:
            a = mean[0]
        else:
            pick = torch.multinomial(score, 1)[0]
            a = elite_actions[0, pick] + std[0] * torch.randn(d, device=z.device)
        return a.clamp(-1, 1)


def _heads(heads: nn.Module) -> TDMPC2Heads:
    if not isinstance(heads, TDMPC2Heads):
        raise TypeError(f"expected TDMPC2Heads from TDMPC2.new_heads(), got {type(heads)}")
    return heads
