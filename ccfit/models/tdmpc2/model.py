"""TD-MPC2: the model (its verbs, losses and acting) over its networks (`networks`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ccfit.models.base import LATENT_KEY, Batch, LossOutput, OpenLoop, Prediction, WorldModel
from ccfit.models.encoders import FrozenEncoder
from ccfit.models.layers import (
    TwoHot,
    adam,
    polyak,
    quantiles,
)
from ccfit.models.mppi import mppi_plan
from ccfit.models.registry import register_model
from ccfit.models.tdmpc2.config import Q_RETURN_TYPES, TDMPC2Config
from ccfit.models.tdmpc2.networks import TDMPC2Backbone, TDMPC2Heads, modules_in_eval

# =================================================================================== model


@register_model("tdmpc2", TDMPC2Config)
class TDMPC2(WorldModel, Prediction):
    """TD-MPC2 world model with the benchmark's backbone/heads split."""

    cfg: TDMPC2Config
    capabilities = frozenset({"pixel-encoder", "prediction"})  # the shared `build_encoder`
    hot_paths = ("loss", "pi_loss", "plan")
    # bench/update_rate.py, cpu preset, 1 thread, Mish in closed form (layers.mish): update
    # (loss + backward + head_update) ~15 -> ~10 ms compiled, plan 5.2 -> 2.3 ms.
    compile_pays = {"cpu": hot_paths}
    compile_pays_from = {"cpu": 5_000}  # bench/startup.py: see docs/performance.md

    def __init__(
        self,
        cfg: TDMPC2Config,
        device: torch.device,
        encoder: FrozenEncoder | None = None,
    ) -> None:
        """`device`: where it lives (resolved by the caller: `ccfit.settings`). `encoder`: a
        pretrained encoder from `load_frozen_encoder` to use (frozen) instead
        of a trainable one; it stays in the backbone but has no trainable parameters."""
        if not isinstance(cfg, TDMPC2Config):
            raise ValueError(f"{type(self).__name__} needs a TDMPC2Config, got {type(cfg)}")
        super().__init__()
        self.cfg = cfg
        self.device = torch.device(device)
        self.backbone = TDMPC2Backbone(cfg, encoder)
        self.two_hot = TwoHot(cfg.num_bins, cfg.vmin, cfg.vmax)
        self.discount = cfg.discount
        self.to(self.device)

    # ---------------------------------------------------------------- structure, optimisers

    def new_heads(self) -> TDMPC2Heads:
        return TDMPC2Heads(self.cfg).to(self.device)

    def _backbone_groups(self) -> list[dict]:
        """Named Adam groups of the backbone (the encoder at lr * enc_lr_scale)."""
        cfg = self.cfg
        return [
            {"name": "encoder", "params": list(self.backbone.encoder.parameters()),
             "lr": cfg.lr * cfg.enc_lr_scale},
            {"name": "dynamics", "params": list(self.backbone.dynamics.parameters()),
             "lr": cfg.lr},
        ]  # fmt: skip

    def _param_groups(self, heads: nn.Module) -> list[dict]:
        """Named Adam groups of `world_model_optimizer`: the backbone's, then the heads'."""
        h = _heads(heads)
        value_params = [*h.reward.parameters(), *h.termination.parameters(), *h.qs.parameters()]
        heads_group = {"name": "heads", "params": value_params, "lr": self.cfg.lr}
        return _trainable([*self._backbone_groups(), heads_group])

    def world_model_optimizer(self, heads: nn.Module) -> torch.optim.Optimizer:
        return adam(self._param_groups(heads), lr=self.cfg.lr)

    def backbone_optimizer(self) -> torch.optim.Optimizer:
        return adam(_trainable(self._backbone_groups()), lr=self.cfg.lr)

    def head_optimizers(self, heads: nn.Module) -> dict[str, torch.optim.Optimizer]:
        """{'pi': the policy's Adam} (the official recipe: lr, eps `policy_adam_eps`)."""
        pi = _heads(heads).pi.parameters()
        return {"pi": adam(pi, lr=self.cfg.lr, eps=self.cfg.policy_adam_eps)}

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
        # The squashed Gaussian in float32 under any autocast: in bfloat16, tanh rounds a
        # near-saturated action to exactly +-1, where its gradient (and so Q's pull on the
        # policy) is zero and the log-prob's squash correction is off.
        mean, log_std = heads.pi(z).float().chunk(2, dim=-1)
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
            "mean": mean,
            "log_std": log_std,
            "entropy": entropy,
            # The bonus scales with the action dimension, as TD-MPC2's does. Unlike either of
            # its releases, the tanh correction is scaled with it (the first added it unscaled,
            # the current one leaves it out); at entropy_coef 1e-4 the difference is small, and
            # the published runs were made with this form.
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
        # Only the two randomly chosen members are evaluated. (argsort of uniforms, not
        # randperm(n)[:2]: Inductor's randperm-index pattern breaks on that (torch 2.11).)
        pair = torch.rand(self.cfg.num_q, device=z.device).argsort()[:2]
        q = self.two_hot.logits_to_scalar(net(za, detach=detach, members=pair))
        return torch.minimum(q[0], q[1]) if return_type == "min" else 0.5 * (q[0] + q[1])

    # ---------------------------------------------------------------- losses

    def _rollout(self, batch: Batch) -> tuple[torch.Tensor, ...]:
        """Latent rollout from row 0 over the window's T = seq_len - 1 transitions: (zs with
        grad (T+1, B, L), detached next-row latents (T, B, L), consistency loss, rollout mask
        (T, B, 1))."""
        cfg, steps = self.cfg, batch.seq_len - 1
        mask = batch.rollout_mask()
        with torch.no_grad():
            next_z = self.encode({k: v[1:] for k, v in batch.obs.items()})
        z = self.encode({k: v[0] for k, v in batch.obs.items()})
        zs, consistency = [z], z.new_zeros(())
        for t in range(steps):
            z = self.next(z, batch.action[t])
            err = (z - next_z[t]).pow(2).mean(-1, keepdim=True) * mask[t]
            consistency = consistency + err.mean() * cfg.rho**t
            zs.append(z)
        return torch.stack(zs), next_z, consistency / steps, mask

    @torch.no_grad()
    def _td_target(
        self, next_z: torch.Tensor, reward: torch.Tensor, terminated: torch.Tensor, heads
    ) -> torch.Tensor:
        action, _ = self.pi(next_z, heads)
        q = self.Q(next_z, action, heads, "min", target=True)
        return reward + self.discount * (1 - terminated) * q

    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        cfg, h = self.cfg, _heads(heads)
        zs, next_z, consistency, mask = self._rollout(batch)
        steps = zs.shape[0] - 1
        action, reward, terminated = batch.action[:-1], batch.reward[:-1], batch.terminated[:-1]
        td = self._td_target(next_z, reward, terminated, h)

        rho = cfg.rho ** torch.arange(steps, device=zs.device, dtype=zs.dtype)
        w = rho.view(steps, 1, 1) * mask  # (T, B, 1)
        _zs = zs[:-1]
        reward_ce = self.two_hot.cross_entropy(self.reward(_zs, action, h), reward)
        reward_loss = (reward_ce * w).sum(0).mean() / steps
        q_logits = self.Q(_zs, action, h, "all")  # (num_q, T, B, bins)
        value_ce = self.two_hot.cross_entropy(q_logits, td.expand(cfg.num_q, -1, -1, -1))
        value_loss = (value_ce * w).sum((0, 1)).mean() / (steps * cfg.num_q)
        term_bce = F.binary_cross_entropy_with_logits(
            self.termination(zs[1:], h), terminated, reduction="none"
        )
        term_loss = (term_bce * mask).mean()

        total = (
            cfg.consistency_coef * consistency
            + cfg.reward_coef * reward_loss
            + cfg.value_coef * value_loss
            + cfg.termination_coef * term_loss
        )
        logs = {
            "consistency": consistency.detach(),
            "reward": reward_loss.detach(),
            "value": value_loss.detach(),
            "termination": term_loss.detach(),
            "total": total.detach(),
        }
        # Latent t is meaningful when the rollout reached it inside row 0's episode.
        latent_mask = torch.cat([torch.ones_like(mask[:1]), mask], dim=0)
        return LossOutput(total=total, logs=logs, aux={"zs": zs.detach(), "mask": latent_mask})

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """consistency_coef x consistency: the same scale as that term inside `loss`."""
        return self.cfg.consistency_coef * self._rollout(batch)[2]

    def head_update(
        self,
        batch: Batch,
        heads: nn.Module,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        """Policy step on the detached rollout latents of `out`, then the Polyak step of the
        target Qs."""
        h = _heads(heads)
        demo_actions = None
        if self.cfg.demo_bc_coef > 0 and batch.demos > 0:
            demo_actions = batch.action[:-1, : batch.demos]
        pi_loss, logs = self.pi_loss(out.aux["zs"].detach(), out.aux["mask"], h, demo_actions)
        optim = optimizers["pi"]
        optim.zero_grad(set_to_none=True)
        pi_loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(h.pi.parameters(), self.cfg.grad_clip)
        optim.step()
        optim.zero_grad(set_to_none=True)
        polyak(list(h.target_qs.parameters()), list(h.qs.parameters()), self.cfg.tau)
        return {"pi_loss": pi_loss.detach(), "pi_grad_norm": grad_norm.detach(), **logs}

    def pi_loss(
        self, zs: torch.Tensor, mask: torch.Tensor, h: TDMPC2Heads,
        demo_actions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:  # fmt: skip
        """The policy's objective on latents zs (T+1, B, L): entropy-regularised Q of its own
        actions, scaled by the running 5-95% range of Q (moved here, by tau), weighted rho^t
        and masked past an episode's end; with `demo_actions` (T, k, A), the actions of the
        first k windows (demonstrations), plus `demo_bc_coef` x the squared distance of the
        policy's mean to them. Pure tensor code (no optimiser), so it compiles into one graph
        that fits every task's heads."""
        cfg = self.cfg
        action, info = self.pi(zs, h)
        q = self.Q(zs, action, h, "avg", detach=True)
        with torch.no_grad():
            lo, hi = quantiles(q[0].float().flatten(), (0.05, 0.95))
            h.q_scale.lerp_((hi - lo).clamp(min=1.0).reshape(1), cfg.tau)
        q = q / h.q_scale
        rho = cfg.rho ** torch.arange(zs.shape[0], device=zs.device, dtype=zs.dtype)
        per_step = (-(cfg.entropy_coef * info["scaled_entropy"] + q) * mask).mean(dim=(1, 2))
        logs = {"pi_entropy": info["entropy"].mean().detach(),
                "q_scale": h.q_scale.detach().clone().reshape(())}  # fmt: skip
        if demo_actions is not None:
            k = demo_actions.shape[1]
            # Row t's action is real where transition t is (the latent mask of row t + 1).
            err = (info["mean"][:-1, :k] - demo_actions).pow(2).sum(-1, keepdim=True)
            bc = (err * mask[1:, :k]).sum(dim=(1, 2)) / k  # (T,)
            per_step = per_step + cfg.demo_bc_coef * F.pad(bc, (0, 1))
            logs["pi_demo_bc"] = bc.mean().detach()
        return (per_step * rho).mean(), logs

    # ---------------------------------------------------------------- prediction

    @classmethod
    def measurement_space(cls, cfg: TDMPC2Config, frozen_encoder: bool) -> str | None:
        """Only a frozen encoder's latent: TD-MPC2 decodes nothing, and its own latent space is
        its encoder's, which moves as it trains."""
        return "frozen-encoder latent" if frozen_encoder else None

    @torch.no_grad()
    def open_loop(self, batch: Batch, context: int, horizon: int) -> OpenLoop:
        """The last context row's latent rolled through `next` with the given actions, against
        the frozen encoder's latents of the rows that follow (the dynamics has no memory)."""
        if not isinstance(self.backbone.encoder, FrozenEncoder):
            raise ValueError("open-loop prediction needs a frozen encoder")
        batch, end = batch.to(self.device), context + horizon
        zs = self.encode({k: v[context - 1 : end] for k, v in batch.obs.items()}).float()
        z, predicted = zs[0], []
        for t in range(context - 1, end - 1):
            predicted.append(z := self.next(z, batch.action[t]))
        return OpenLoop({LATENT_KEY: torch.stack(predicted)}, {LATENT_KEY: zs[1:]},
                        {LATENT_KEY: zs[0]})  # fmt: skip

    # ---------------------------------------------------------------- acting

    @torch.no_grad()
    def act(
        self, obs: Mapping[str, torch.Tensor], heads: nn.Module, state, *, eval_mode: bool
    ) -> tuple[np.ndarray, torch.Tensor]:
        """MPPI actions (n, A) for n observations; `state` is the previous plans' means
        (n, horizon, A) for the warm start, or None at the start of the episodes; the new
        means are returned as the next state."""
        h = _heads(heads)
        with modules_in_eval(self.backbone, h):
            z = self.encode(obs)
            if state is None:
                # A plan warm-started from zero means is the cold start, exactly: one
                # compiled plan serves both.
                state = z.new_zeros(z.shape[0], self.cfg.horizon, self.cfg.action_dim)
            if z.shape[0] > 1:
                # Evaluation batches shrink as their episodes end: one plan for every size.
                torch._dynamo.maybe_mark_dynamic(z, 0)
                torch._dynamo.maybe_mark_dynamic(state, 0)
            action, mean = self.plan(z, h, state, eval_mode=eval_mode)
        return action.float().cpu().numpy(), mean

    @torch.no_grad()
    def plan(
        self, z: torch.Tensor, heads: TDMPC2Heads, prev_mean: torch.Tensor | None, *,
        eval_mode: bool,
    ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """MPPI from latents z (n, L): (actions (n, A) in [-1, 1], plan means (n, horizon, A))."""
        return mppi_plan(self, z, heads, prev_mean, eval_mode=eval_mode)


def _trainable(groups: list[dict]) -> list[dict]:
    """`groups` without frozen parameters (a frozen encoder contributes nothing)."""
    groups = [{**g, "params": [p for p in g["params"] if p.requires_grad]} for g in groups]
    return [g for g in groups if g["params"]]


def _heads(heads: nn.Module) -> TDMPC2Heads:
    if not isinstance(heads, TDMPC2Heads):
        raise TypeError(f"expected TDMPC2Heads from TDMPC2.new_heads(), got {type(heads)}")
    return heads
