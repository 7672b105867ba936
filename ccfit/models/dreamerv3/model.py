"""DreamerV3 behind the `WorldModel` interface.

Backbone (task-agnostic, what continual methods see): encoder, RSSM, decoder. Heads (per
task): reward, continue, actor, critic, slow critic, return-normaliser statistics; the
per-episode recurrent state while acting is an explicit `ActingState`.

One update: `loss` filters the replay windows through the RSSM and returns reconstruction +
KL + reward + continue (reward and continue gradients reach the backbone, as the recipe's
`grad_heads`); the loop steps the world-model optimiser; `head_update` imagines from the
detached posteriors and steps the actor and critic only (the actor's gradient passes
through the dynamics, but only actor parameters receive it).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from ccfit.config_base import check
from ccfit.models.base import LATENT_KEY, Batch, LossOutput, OpenLoop, Prediction, WorldModel
from ccfit.models.dreamerv3.behavior import (
    behavior_losses,
    demo_cloning,
    imagine,
    imagined_returns,
    replay_lambda_return,
    replay_value_loss,
)
from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.heads import DreamerV3Heads
from ccfit.models.dreamerv3.math import kl_loss
from ccfit.models.dreamerv3.networks import Decoder, Encoder, bernoulli_nll, init_weights
from ccfit.models.dreamerv3.rssm import RSSM, clip_action
from ccfit.models.layers import adam
from ccfit.models.registry import register_model


class DreamerV3Backbone(nn.Module):
    """Encoder (or a frozen pretrained one), RSSM, decoder."""

    def __init__(self, cfg: DreamerV3Config, frozen: nn.Module | None = None) -> None:
        super().__init__()
        self.encoder = Encoder(cfg, frozen)
        self.rssm = RSSM(cfg, self.encoder.out_dim)
        self.decoder = Decoder(cfg, None if frozen is None else self.encoder.out_dim)
        # A frozen encoder keeps its pretrained weights.
        for part in [self.rssm, self.decoder] + ([self.encoder] if frozen is None else []):
            part.apply(init_weights)


@dataclass
class ReplayValue:
    """What the 2025 replay-value loss needs again in `head_update` (all detached)."""

    feat: torch.Tensor
    target: torch.Tensor
    mask: torch.Tensor


@dataclass
class DreamerV3Aux:
    """Detached posteriors of a batch: imagination starts for `head_update`."""

    deter: torch.Tensor  # (L, B, D)
    stoch: torch.Tensor  # (L, B, S, C)
    start_cont: torch.Tensor  # (L, B, 1): 0 where the row is a terminal observation
    replay: ReplayValue | None = None


@dataclass
class ActingState:
    """Per-episode recurrent state: the last posterior and the action taken after it."""

    deter: torch.Tensor  # (n, D)
    stoch: torch.Tensor  # (n, S, C)
    action: torch.Tensor  # (n, A)


def _detached(logs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    # Kept as tensors: the loop reduces them when it logs, so an update never syncs.
    return {k: v.detach() for k, v in logs.items()}


@register_model("dreamerv3", DreamerV3Config)
class DreamerV3(WorldModel, Prediction):
    """DreamerV3, the authors' 2023 recipe (2025 changes as config options)."""

    capabilities = frozenset({"prediction"})
    hot_paths = ("loss", "head_update", "act")
    # bench/update_rate.py --models dreamerv3 --presets cpu --threads 1 --modes eager,auto,
    # compile:head_update,compile:loss+head_update (two rounds, quiet): update eager 73.7 /
    # 84.1 ms, loss compiled 70.5 / 67.9, head_update compiled 91.9 / 95.3 (its autograd.grad
    # and optimiser steps break the graph; each task's new optimisers retrace it, ~3.5 s), both
    # 80.5 / 73.5. Acting costs ~0.3 ms either way. Imagination and the behaviour losses alone
    # compiled, without head_update's gradients and optimiser steps (a trial at 785a658, same
    # script, one round, quiet): 106.7 ms against 106.3 for the loss alone (eager 124.5): no gain.
    compile_pays = {"cpu": ("loss",)}
    # A Reach curriculum of 2000 steps per task compiling the loss took 0.85x eager's time
    # from an empty compile cache (docs/performance.md); 10 000, Reach's budget, lies above
    # that point, not at a measured break-even.
    compile_pays_from = {"cpu": 10_000}

    def __init__(self, cfg: DreamerV3Config, device: torch.device, encoder=None) -> None:
        super().__init__()
        if encoder is not None:
            check(
                encoder.obs_mode == cfg.obs_mode,
                f"frozen encoder is for obs_mode {encoder.obs_mode!r}, model has {cfg.obs_mode!r}",
            )
        self.cfg, self.device = cfg, torch.device(device)
        self.backbone = DreamerV3Backbone(cfg, encoder).to(self.device)

    @property
    def rssm(self) -> RSSM:
        return self.backbone.rssm

    # ------------------------------------------------------------------ structure
    def new_heads(self) -> DreamerV3Heads:
        return DreamerV3Heads(self.cfg).to(self.device)

    def world_model_optimizer(self, heads: DreamerV3Heads) -> torch.optim.Optimizer:
        params = [p for p in self.backbone.parameters() if p.requires_grad]
        params += [*heads.reward.parameters(), *heads.cont.parameters()]
        return adam(params, lr=self.cfg.model_lr, eps=self.cfg.model_eps)

    def backbone_optimizer(self) -> torch.optim.Optimizer:
        params = [p for p in self.backbone.parameters() if p.requires_grad]
        return adam(params, lr=self.cfg.model_lr, eps=self.cfg.model_eps)

    def head_optimizers(self, heads: DreamerV3Heads) -> dict[str, torch.optim.Optimizer]:
        cfg = self.cfg
        return {
            "actor": adam(heads.actor.parameters(), lr=cfg.actor_lr, eps=cfg.ac_eps),
            "critic": adam(heads.critic.parameters(), lr=cfg.critic_lr, eps=cfg.ac_eps),
        }

    # ------------------------------------------------------------------ world model
    def _filter(self, batch: Batch) -> tuple[torch.Tensor, ...]:
        """Posteriors and the task-agnostic loss terms of a batch.

        Returns (feat, deter, stoch, world loss, logs) where world loss = reconstruction +
        kl_dyn * dyn + kl_rep * rep, each a mean over (time, batch) rows."""
        cfg = self.cfg
        embed = self.backbone.encoder(batch.obs)
        deter, stoch, post, prior = self.rssm.observe(embed, batch.action, batch.is_first)
        feat = self.rssm.feat(deter, stoch)
        targets = batch.obs if self.backbone.encoder.frozen is None else {LATENT_KEY: embed}
        recon, parts = self.backbone.decoder.loss(feat, targets)
        dyn, rep = kl_loss(post, prior, cfg.free_nats)
        world = recon.mean() + cfg.kl_dyn * dyn.mean() + cfg.kl_rep * rep.mean()
        logs = {
            "recon": recon.mean(),
            "dyn": dyn.mean(),
            "rep": rep.mean(),
            **{f"recon_{k}": v for k, v in parts.items()},
        }
        return feat, deter, stoch, world, logs

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """Reconstruction + dyn + rep KL, at the recipe's scales. These terms only involve the
        backbone and hold for any task, so they are what ER replays and what EWC's Fisher is
        taken from; reward and continue depend on the task's heads and stay out (the
        authors' EWC also included the finished task's reward/continue losses)."""
        return self._filter(batch.to(self.device))[3]

    def loss(self, batch: Batch, heads: DreamerV3Heads) -> LossOutput:
        cfg = self.cfg
        batch = batch.to(self.device)
        feat, deter, stoch, world, logs = self._filter(batch)
        # Transition t (row t -> t + 1) is predicted from the state at row t + 1.
        valid = batch.valid()
        count = valid.sum().clamp(min=1.0)
        reward = heads.twohot.cross_entropy(heads.reward(feat[1:]), batch.reward[:-1])
        reward = (reward * valid).sum() / count
        cont_target = 1.0 - batch.terminated[:-1]
        cont = (bernoulli_nll(heads.cont(feat[1:]), cont_target) * valid).sum() / count
        total = world + reward + cont
        logs.update(reward_loss=reward, cont_loss=cont)
        # Row t is a terminal observation when transition t - 1 ended the episode.
        terminal = batch.terminated[:-1] * valid
        start_cont = torch.cat([torch.ones_like(terminal[:1]), 1.0 - terminal])
        aux = DreamerV3Aux(deter.detach(), stoch.detach(), start_cont)
        if cfg.critic_replay_scale > 0:
            repval, aux.replay = self._replay_value(batch, heads, feat, aux)
            total = total + cfg.critic_replay_scale * repval
            logs["replay_value_loss"] = repval
        logs["total"] = total
        return LossOutput(total, _detached(logs), aux)

    def _starts(self, aux: DreamerV3Aux) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Imagination starts (N, ...) from the last `imag_last` rows (all if 0)."""
        k = self.cfg.imag_last or aux.deter.shape[0]
        deter, stoch, cont = aux.deter[-k:], aux.stoch[-k:], aux.start_cont[-k:]
        return deter.flatten(0, 1), stoch.flatten(0, 1), cont.flatten(0, 1)

    def _replay_value(
        self, batch: Batch, heads: DreamerV3Heads, feat: torch.Tensor, aux: DreamerV3Aux
    ) -> tuple[torch.Tensor, ReplayValue]:
        """2025 replay-value loss on the last `imag_last` rows: the critic on the (not
        detached) posteriors toward lambda-returns along replay, bootstrapped from imagined
        returns. Here the critic's weights are detached, so its gradient reaches the backbone
        only; `head_update` adds the same term for the critic's own gradient (from the same
        pre-step values), which together equal the 2025 joint gradient."""
        cfg = self.cfg
        k = cfg.imag_last or batch.seq_len
        with torch.no_grad():
            traj = imagine(
                self.rssm, heads, *self._starts(aux), cfg.horizon, cfg.discount, cfg.imag_cont
            )
            boot = imagined_returns(cfg, heads, traj)[0][0].reshape(k, batch.size, 1)
            valid = torch.cat([batch.valid(), torch.zeros_like(batch.valid()[:1])])[-k:]
            target = replay_lambda_return(
                batch.reward[-k:],
                batch.terminated[-k:],
                valid,
                boot,
                cfg.discount,
                cfg.return_lambda,
            )
        weights = {n: p.detach() for n, p in heads.critic.named_parameters()}
        logits = functional_call(heads.critic, weights, (feat[-k:],))
        loss = replay_value_loss(cfg, heads, logits, feat[-k:], target, valid)
        return loss, ReplayValue(feat[-k:].detach(), target, valid)

    # ------------------------------------------------------------------ prediction
    @classmethod
    def measurement_space(cls, cfg: DreamerV3Config, frozen_encoder: bool) -> str:
        """Where the decoder decodes: the state vector, the images and proprio, or (with a
        frozen encoder, whose latent the decoder reconstructs) that encoder's latent."""
        if frozen_encoder:
            return "frozen-encoder latent"
        return "state" if cfg.obs_mode == "state" else "pixels+proprio"

    @torch.no_grad()
    def open_loop(self, batch: Batch, context: int, horizon: int) -> OpenLoop:
        """Posteriors (modes) over the context rows, then prior modes with the given actions,
        decoded into the observation (`Decoder.predict`)."""
        batch = batch.to(self.device)
        seen = {k: v[:context] for k, v in batch.obs.items()}
        embed = self.backbone.encoder(seen)
        deter, stoch, _, _ = self.rssm.observe(
            embed, batch.action[:context], batch.is_first[:context], sample=False
        )
        deter, stoch, feats = deter[-1], stoch[-1], []
        for t in range(context - 1, context - 1 + horizon):
            deter, stoch = self.rssm.img_step(deter, stoch, batch.action[t], sample=False)
            feats.append(self.rssm.feat(deter, stoch))
        predicted = self.backbone.decoder.predict(torch.stack(feats))
        observed = self._measured({k: v[context - 1 : context + horizon]
                                   for k, v in batch.obs.items()})  # fmt: skip
        return OpenLoop(predicted, {k: v[1:] for k, v in observed.items()},
                        {k: v[0] for k, v in observed.items()})  # fmt: skip

    def _measured(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Observations (..., obs) as `Decoder.predict` gives them, each (..., D)."""
        if self.backbone.encoder.frozen is not None:
            return {LATENT_KEY: self.backbone.encoder(obs)}
        if self.cfg.obs_mode == "state":
            return {"state": obs["state"].float()}
        return {"proprio": obs["proprio"].float(),
                "pixels": obs["pixels"].flatten(-3).float() / 255.0}  # fmt: skip

    # ------------------------------------------------------------------ behaviour
    def head_update(
        self,
        batch: Batch,
        heads: DreamerV3Heads,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        cfg = self.cfg
        aux: DreamerV3Aux = out.aux
        with torch.set_grad_enabled(cfg.actor_grad == "dynamics"):
            traj = imagine(
                self.rssm, heads, *self._starts(aux), cfg.horizon, cfg.discount, cfg.imag_cont
            )
        actor_loss, critic_loss, logs = behavior_losses(cfg, heads, traj)
        if cfg.demo_bc_coef > 0 and batch.demos > 0:
            bc = self._demo_cloning(batch, heads, aux)
            actor_loss = actor_loss + cfg.demo_bc_coef * bc
            logs["actor_demo_bc"] = bc
        if aux.replay is not None:
            r = aux.replay
            repval = replay_value_loss(cfg, heads, heads.critic(r.feat), r.feat, r.target, r.mask)
            critic_loss = critic_loss + cfg.critic_replay_scale * repval
        # The critic's forward pass is shared by both losses: keep its graph for the second.
        logs["actor_grad_norm"] = self._step(actor_loss, heads.actor, optimizers["actor"], True)
        logs["critic_grad_norm"] = self._step(critic_loss, heads.critic, optimizers["critic"])
        heads.update_slow_critic(cfg.slow_critic_fraction)
        return _detached(logs)

    def _demo_cloning(self, batch: Batch, heads: DreamerV3Heads, aux: DreamerV3Aux) -> torch.Tensor:
        """`demo_cloning` on the batch's first `demos` windows (demonstrations): row t's
        posterior, which acting would read to choose a_t, against the demonstrated a_t."""
        k, batch = batch.demos, batch.to(self.device)
        feat = self.rssm.feat(aux.deter[:-1, :k], aux.stoch[:-1, :k])
        action = clip_action(batch.action[:-1, :k])
        return demo_cloning(heads, feat, action, batch.valid()[:, :k], self.cfg.demo_bc_loss)

    def _step(self, loss: torch.Tensor, module: nn.Module, opt: torch.optim.Optimizer,
              retain_graph: bool = False):  # fmt: skip
        """Gradient of `loss` for `module` only (autograd.grad leaves every other .grad, the
        backbone's included, untouched), clipped, one optimiser step."""
        params = list(module.parameters())
        grads = torch.autograd.grad(loss, params, retain_graph=retain_graph)
        for p, g in zip(params, grads, strict=True):
            p.grad = g
        norm = nn.utils.clip_grad_norm_(params, self.cfg.ac_grad_clip)
        opt.step()
        opt.zero_grad(set_to_none=True)
        return norm

    # ------------------------------------------------------------------ replay, acting
    @torch.no_grad()
    def replay_obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """With a frozen encoder replay stores its latents: they are both the embedding and
        the decoder's target (see `Decoder`), and the encoder never changes."""
        frozen = self.backbone.encoder.frozen
        if frozen is None:
            return obs
        z = frozen({k: v.to(self.device) for k, v in obs.items()})
        return {LATENT_KEY: z.float().cpu()}

    @torch.no_grad()
    def initial_state(self, heads: DreamerV3Heads, n: int = 1) -> ActingState:
        deter, stoch = self.rssm.initial_state(n)
        action = torch.zeros(n, self.cfg.action_dim, device=self.device)
        return ActingState(deter.clone(), stoch, action)

    def _posterior(self, obs: dict[str, torch.Tensor], state: ActingState) -> ActingState:
        embed = self.backbone.encoder(obs)
        # No step is an episode's first here: `initial_state` already is the learned start.
        is_first = torch.zeros(embed.shape[0], 1, device=self.device)
        deter, stoch, _ = self.rssm.obs_step(
            state.deter, state.stoch, state.action, embed, is_first
        )
        return ActingState(deter, stoch, state.action)

    @torch.no_grad()
    def act(
        self,
        obs: dict[str, torch.Tensor],
        heads: DreamerV3Heads,
        state: ActingState,
        *,
        eval_mode: bool,
    ) -> tuple[np.ndarray, ActingState]:
        """Posterior update with o_t and the previous actions, then the actor's mode (eval, as
        the PyTorch port dreamerv3-torch does; the JAX release samples there too) or a sample
        clipped to [-1, 1] (what the dynamics would see in imagination); n at once."""
        state = self._posterior(obs, state)
        mean, std = heads.actor(self.rssm.feat(state.deter, state.stoch))
        action = mean if eval_mode else (mean + std * torch.randn_like(std)).clamp(-1.0, 1.0)
        return action.float().cpu().numpy(), replace(state, action=action)

    @torch.no_grad()
    def observe(
        self,
        obs: dict[str, torch.Tensor],
        action: np.ndarray,
        heads: DreamerV3Heads,
        state: ActingState,
    ) -> ActingState:
        state = self._posterior(obs, state)
        a = torch.as_tensor(np.asarray(action), dtype=torch.float32, device=self.device)
        return replace(state, action=a.reshape(state.action.shape))
