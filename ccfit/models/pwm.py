"""PWM (prismatic world model, Li et al. 2025): TD-MPC2 whose latent dynamics is a mixture of
experts, with the benchmark's progressive (continual) variant in mind; its config `PWMConfig`
(registered as model 'pwm').

Everything but the dynamics is TD-MPC2's (losses, heads, planning are inherited). The dynamics
`MixtureDynamics` computes

    feature_k = expert_k([z, a])                     2 NormedLinear layers per expert
    feature   = GramSchmidt(feature_1..K)            optional, orthonormal, activation order
    w         = softmax(router([gate_input, tau]) / tau)   over the active experts only
    z'        = SimNorm(head(sum_k w_k feature_k))   shared head

Experts come in groups of K = `experts_per_task`, allocated up front for `max_tasks` groups so
the parameter set never changes shape (checkpoints and optimisers stay valid); only the first
`num_groups` groups are active (computed, routable); inactive experts get weight exactly 0
(masked logits) and have requires_grad False. Group 0 is active from the start, so under
FT / ER / EWC / PackNet PWM is a fixed mixture of K experts; the 'experts' continual method
(ccfit.continual.experts) activates one group per task and freezes the earlier ones.

Gate input, `router`:
- 'task' (default, as in the authors' code): the one-hot task identity over `max_tasks`,
  followed by tau. With a bias-free router this is a learnt per-task logit table (one column
  per task) plus a shared tau column: training task t only moves column t (and the tau
  column), so earlier tasks' routing is left alone. A one-hot is used instead of a learnt
  embedding because it keeps that separation exact and needs no extra parameters.
- 'state': [z, a, tau], routing that can change within an episode.

The task of every sample is known: batches carry `task` per row and a window routes with
the task of its row 0 (where its rollout starts); heads are stamped with the task they
belong to (`PWMHeads.task_index`), which routes planning. A task's routing therefore never
depends on which task is being trained.

Temperature: one tau per task (a buffer, checkpointed). A task's tau starts at `tau_init`, is
held for max(tau_hold_min, tau_hold_frac * task steps) training updates of that task, then
after every update moves as tau <- clip(tau + tau_rate * tanh(H_target - H(w)), tau_min,
tau_max), H_target = tau_target_frac * log(active experts), H(w) the mean routing entropy over
the update's batch (all rollout steps). The authors keep a single tau reset at each new task;
as tau enters every task's routing, that silently re-routes finished tasks (they added a
switch to freeze it). One tau per task follows the same schedule while training a task and
keeps finished tasks' routing a function of parameters only (what PackNet protects).

Continual use, per task i: `model.begin_task(i, task_steps)`, then `model.new_heads()`
(stamped with task i); `with model.routing_override("prior" | "new" | "uniform")` ablates the
routing for analysis, `model.routing_weights(z, a, task)` reads it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ccfit.models.base import Batch, LossOutput
from ccfit.models.encoders import FrozenEncoder
from ccfit.models.layers import NormedLinear, SimNorm, init_weights
from ccfit.models.registry import check, register_model
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config, TDMPC2Heads

PWM_ROUTERS: tuple[str, ...] = ("task", "state")
"""Gate inputs of PWM's router: the task identity, or the latent and action."""

_PWM_EXTRAS: dict[str, dict] = {
    # Short runs get a short hold, so that the entropy feedback runs at all.
    "smoke": dict(tau_hold_min=100),
    "cpu": dict(tau_hold_min=1000),
    "paper": dict(),
}
"""PWM settings on top of the TD-MPC2 preset of the same name (sizes: the paper's settings)."""


@dataclass
class PWMConfig(TDMPC2Config):
    """PWM (prismatic world model): TD-MPC2 whose latent dynamics is a mixture of experts.

    Every TD-MPC2 field keeps its meaning; the fields below configure the mixture. Experts are
    allocated in groups of `experts_per_task` (one group per task under the 'experts' continual
    method, a single group otherwise); the temperature schedule follows the authors' code.
    Presets: TD-MPC2's of the same name plus the mixture settings of `_PWM_EXTRAS`.
    """

    PRESETS = {
        name: {**fields, **_PWM_EXTRAS.get(name, {})}
        for name, fields in TDMPC2Config.PRESETS.items()
    }

    experts_per_task: int = 3
    """K: experts in each group (the paper adds K = 3 per task)."""
    max_tasks: int = 8
    """Most expert groups (tasks) the model can hold; also the width of the task one-hot seen
    by the router. Groups are allocated up front; only active ones are computed and trained."""
    orthogonalize: bool = False
    """Gram-Schmidt orthonormalise the expert features across experts (in activation order)
    before mixing them."""
    router: str = "task"
    """Gate input: 'task' (one-hot task identity, as the authors) or 'state' ([z, a])."""
    tau_init: float = 1.8
    """Router temperature at the start of each task, held during the hold phase."""
    tau_min: float = 0.5
    """Lower clip of the temperature."""
    tau_max: float = 2.0
    """Upper clip of the temperature."""
    tau_rate: float = 0.02
    """Step of the entropy feedback: tau += tau_rate * tanh(H_target - H(w))."""
    tau_target_frac: float = 0.75
    """H_target = tau_target_frac * log(active experts)."""
    tau_hold_min: int = 5000
    """The temperature is held for max(tau_hold_min, tau_hold_frac * task_steps) updates."""
    tau_hold_frac: float = 0.05
    """Share of a task's steps during which the temperature is held (see tau_hold_min)."""
    task_steps: int | None = None
    """Steps of each task, for the hold length; None: tau_hold_min only.
    `PWM.begin_task(i, task_steps)` overrides it per task."""

    def __post_init__(self) -> None:
        super().__post_init__()
        name = type(self).__name__
        check(self.router in PWM_ROUTERS,
              f"{name}.router must be one of {PWM_ROUTERS}, got {self.router!r}")  # fmt: skip
        checks = [
            (self.experts_per_task >= 1, "experts_per_task must be >= 1"),
            (self.max_tasks >= 1, "max_tasks must be >= 1"),
            (0.0 < self.tau_min <= self.tau_init <= self.tau_max,
             "need 0 < tau_min <= tau_init <= tau_max"),
            (self.tau_rate >= 0.0, "tau_rate must be >= 0"),
            (self.tau_target_frac >= 0.0, "tau_target_frac must be >= 0"),
            (self.tau_hold_min >= 0, "tau_hold_min must be >= 0"),
            (0.0 <= self.tau_hold_frac <= 1.0, "tau_hold_frac must be in [0, 1]"),
            (self.task_steps is None or self.task_steps >= 1, "task_steps must be >= 1 or None"),
        ]  # fmt: skip
        for ok, msg in checks:
            check(ok, f"{name}: {msg}")

    def hold_steps(self, task_steps: int | None = None) -> int:
        """Updates during which the temperature is held for a task of `task_steps` steps."""
        steps = task_steps if task_steps is not None else self.task_steps
        frac = int(round(self.tau_hold_frac * steps)) if steps is not None else 0
        return max(self.tau_hold_min, frac)

OVERRIDES: tuple[str | None, ...] = (None, "prior", "new", "uniform")
"""Routing ablations: learnt (None); only experts of earlier groups ('prior'), only the newest
group ('new'), both renormalised from the learnt weights; uniform over active experts."""


def gram_schmidt(features: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Orthonormalise the K vectors of features (..., K, D) in order: vector k is made
    orthogonal to vectors 0..k-1 and scaled to unit norm, so earlier vectors never depend on
    later ones (a frozen expert's feature is unchanged when experts are added after it)."""
    basis: list[torch.Tensor] = []
    for k in range(features.shape[-2]):
        v = features[..., k, :]
        for b in basis:
            v = v - (v * b).sum(-1, keepdim=True) * b
        basis.append(v / (v.norm(dim=-1, keepdim=True) + eps))
    return torch.stack(basis, dim=-2)


class MixtureDynamics(nn.Module):
    """Mixture-of-experts latent dynamics with progressive expert groups and a soft router."""

    tau: torch.Tensor
    tau_updates: torch.Tensor
    tau_hold: torch.Tensor
    num_groups: torch.Tensor
    num_frozen: torch.Tensor
    current_task: torch.Tensor

    def __init__(self, cfg: PWMConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.k = cfg.experts_per_task
        self.max_tasks = cfg.max_tasks
        self.max_experts = self.k * cfg.max_tasks
        za = cfg.latent_dim + cfg.action_dim
        self.experts = nn.ModuleList(
            nn.Sequential(NormedLinear(za, cfg.mlp_dim), NormedLinear(cfg.mlp_dim, cfg.mlp_dim))
            for _ in range(self.max_experts)
        )
        gate_dim = cfg.max_tasks if cfg.router == "task" else za
        self.router = nn.Linear(gate_dim + 1, self.max_experts, bias=False)
        self.head = NormedLinear(cfg.mlp_dim, cfg.latent_dim, act=SimNorm(cfg.simnorm_dim))
        self.apply(init_weights)
        self.register_buffer("tau", torch.full((cfg.max_tasks,), cfg.tau_init))
        self.register_buffer("tau_updates", torch.zeros(cfg.max_tasks, dtype=torch.long))
        self.register_buffer(
            "tau_hold", torch.full((cfg.max_tasks,), cfg.hold_steps(), dtype=torch.long)
        )
        self.register_buffer("num_groups", torch.tensor(1))
        self.register_buffer("num_frozen", torch.tensor(0))
        self.register_buffer("current_task", torch.tensor(0))
        self.override: str | None = None
        self._entropy: list[torch.Tensor] | None = None
        self.apply_trainability()
        # Loading a checkpoint restores the group counters; the flags follow them.
        self.register_load_state_dict_post_hook(lambda module, _: module.apply_trainability())

    # ------------------------------------------------------------------ groups
    @property
    def num_active(self) -> int:
        return int(self.num_groups) * self.k

    def group_of(self, expert: int) -> int:
        return expert // self.k

    def named_expert_parameters(self, groups: range) -> Iterator[tuple[str, nn.Parameter]]:
        """(name within this module, parameter) of the experts of `groups`."""
        for e in range(groups.start * self.k, groups.stop * self.k):
            for name, p in self.experts[e].named_parameters():
                yield f"experts.{e}.{name}", p

    def apply_trainability(self) -> None:
        """requires_grad: True for active, unfrozen experts; False for frozen and inactive."""
        for e, expert in enumerate(self.experts):
            g = self.group_of(e)
            expert.requires_grad_(int(self.num_frozen) <= g < int(self.num_groups))

    def add_group(self) -> None:
        """Activate the next K experts (fresh, trainable)."""
        if int(self.num_groups) >= self.max_tasks:
            raise ValueError(f"PWM: all {self.max_tasks} expert groups are active; raise max_tasks")
        self.num_groups += 1
        self.apply_trainability()

    def freeze_groups(self, n: int) -> None:
        """Freeze the experts of groups 0..n-1 (they stay routable)."""
        if not 0 <= n <= int(self.num_groups):
            raise ValueError(f"PWM: cannot freeze {n} groups, {int(self.num_groups)} active")
        self.num_frozen.fill_(n)
        self.apply_trainability()

    def optimizer_parameters(self) -> list[nn.Parameter]:
        """Router, head and every expert not frozen (inactive ones included, so experts
        activated after the optimiser was built are in it; Adam skips them until they get
        gradients)."""
        unfrozen = self.named_expert_parameters(range(int(self.num_frozen), self.max_tasks))
        return [*self.router.parameters(), *self.head.parameters(), *(p for _, p in unfrozen)]

    # ------------------------------------------------------------------ tasks, temperature
    def check_task(self, task: int) -> int:
        if not 0 <= int(task) < self.max_tasks:
            raise ValueError(f"PWM: task {int(task)} outside 0..{self.max_tasks - 1} (max_tasks)")
        return int(task)

    def begin_task(self, task: int, task_steps: int | None = None) -> None:
        """Task `task` becomes the current one (default routing task, stamp of new heads);
        `task_steps` sets its temperature hold (default: the config's)."""
        self.current_task.fill_(self.check_task(task))
        self.tau_hold[task] = self.cfg.hold_steps(task_steps)

    def target_entropy(self) -> float:
        return self.cfg.tau_target_frac * math.log(self.num_active)

    @torch.no_grad()
    def step_temperature(self, entropy: float, task: int) -> None:
        """One training update of task `task` with mean routing entropy `entropy`."""
        cfg, task = self.cfg, self.check_task(task)
        if self.tau_updates[task] >= self.tau_hold[task]:
            tau = float(self.tau[task]) + cfg.tau_rate * math.tanh(self.target_entropy() - entropy)
            self.tau[task] = min(max(tau, cfg.tau_min), cfg.tau_max)
        self.tau_updates[task] += 1

    @contextlib.contextmanager
    def recording_entropy(self) -> Iterator[list[torch.Tensor]]:
        """Collects the mean routing entropy of every forward inside the block."""
        self._entropy = record = []
        try:
            yield record
        finally:
            self._entropy = None

    @contextlib.contextmanager
    def routing_override(self, mode: str | None) -> Iterator[None]:
        if mode not in OVERRIDES:
            raise ValueError(f"unknown routing override {mode!r}; valid: {OVERRIDES}")
        if mode == "prior" and int(self.num_groups) < 2:
            raise ValueError("routing override 'prior': only one expert group is active")
        previous, self.override = self.override, mode
        try:
            yield
        finally:
            self.override = previous

    # ------------------------------------------------------------------ routing, forward
    def _task_tensor(self, task, lead: torch.Size, device: torch.device) -> torch.Tensor:
        if task is None:
            task = self.current_task
        return torch.as_tensor(task, dtype=torch.long, device=device).expand(lead)

    def _weights(self, za: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
        """Routing weights over the active experts (..., num_active)."""
        n = self.num_active
        tau = self.tau[task].unsqueeze(-1)  # a copy: later in-place tau updates are safe
        if self.cfg.router == "task":
            gate = F.one_hot(task, self.max_tasks).to(za.dtype)
        else:
            gate = za
        logits = F.linear(torch.cat([gate, tau], -1), self.router.weight[:n]) / tau
        if self.override == "uniform":
            return torch.full_like(logits, 1.0 / n)
        if self.override is not None:
            newest = torch.arange(n, device=za.device) >= n - self.k
            keep = ~newest if self.override == "prior" else newest
            logits = logits.masked_fill(~keep, float("-inf"))
        return F.softmax(logits, dim=-1)

    def features(self, za: torch.Tensor) -> torch.Tensor:
        """Active experts' features (..., num_active, mlp_dim), orthonormalised if set."""
        feats = torch.stack([self.experts[e](za) for e in range(self.num_active)], dim=-2)
        return gram_schmidt(feats) if self.cfg.orthogonalize else feats

    def forward(self, z: torch.Tensor, a: torch.Tensor, task=None) -> torch.Tensor:
        """Next latent (..., latent_dim); `task`: int or LongTensor broadcastable to z's
        leading dims (None: the current task)."""
        za = torch.cat([z, a], dim=-1)
        w = self._weights(za, self._task_tensor(task, za.shape[:-1], za.device))
        if self._entropy is not None:
            self._entropy.append(torch.special.entr(w).sum(-1).mean().detach())
        return self.head((w.unsqueeze(-1) * self.features(za)).sum(-2))

    @torch.no_grad()
    def routing_weights(self, z: torch.Tensor, a: torch.Tensor, task=None) -> torch.Tensor:
        """Weights over all `max_experts` experts (..., max_experts); inactive ones are 0."""
        za = torch.cat([z, a], dim=-1)
        w = self._weights(za, self._task_tensor(task, za.shape[:-1], za.device))
        return F.pad(w, (0, self.max_experts - w.shape[-1]))


class PWMHeads(TDMPC2Heads):
    """TD-MPC2's heads, stamped with the task they belong to (routes their planning)."""

    task_index: torch.Tensor

    def __init__(self, cfg: PWMConfig, task: int) -> None:
        super().__init__(cfg)
        self.register_buffer("task_index", torch.tensor(int(task)))


def find_mixture(backbone: nn.Module) -> MixtureDynamics | None:
    """The backbone's MixtureDynamics, or None."""
    found = [m for m in backbone.modules() if isinstance(m, MixtureDynamics)]
    if len(found) > 1:
        raise ValueError(f"backbone has {len(found)} MixtureDynamics modules, expected one")
    return found[0] if found else None


@register_model("pwm", PWMConfig)
class PWM(TDMPC2):
    """TD-MPC2 with `MixtureDynamics` as its latent dynamics (see the module docstring)."""

    cfg: PWMConfig

    def __init__(
        self,
        cfg: PWMConfig,
        device: torch.device | str | None = None,
        encoder: FrozenEncoder | None = None,
    ) -> None:
        if not isinstance(cfg, PWMConfig):
            raise ValueError(f"PWM needs a PWMConfig, got {type(cfg).__name__}")
        super().__init__(cfg, device=device, encoder=encoder)
        # TD-MPC2's backbone with its dynamics MLP replaced; the encoder is built (and
        # initialised) exactly as TD-MPC2's.
        self.backbone.dynamics = MixtureDynamics(cfg).to(self.device)
        self._task: torch.Tensor | int | None = None

    @property
    def dynamics(self) -> MixtureDynamics:
        return self.backbone.dynamics

    # ------------------------------------------------------------------ tasks, routing
    def begin_task(self, task_index: int, task_steps: int | None = None) -> None:
        """Task `task_index` starts: new heads belong to it; `task_steps` (the task's env steps)
        sets its temperature hold."""
        self.dynamics.begin_task(task_index, task_steps)

    @property
    def tau(self) -> float:
        """Temperature of the current task."""
        return float(self.dynamics.tau[int(self.dynamics.current_task)])

    @contextlib.contextmanager
    def routing_task(self, task) -> Iterator[None]:
        """Within the block, `next` routes with `task` (int or LongTensor broadcastable to the
        latents' leading dims, e.g. (B,))."""
        previous, self._task = self._task, task
        try:
            yield
        finally:
            self._task = previous

    def routing_override(self, mode: str | None) -> contextlib.AbstractContextManager:
        """`with model.routing_override(mode)`: 'prior', 'new', 'uniform' or None (learnt)."""
        return self.dynamics.routing_override(mode)

    def routing_weights(self, z: torch.Tensor, a: torch.Tensor, task=None) -> torch.Tensor:
        """Routing weights (..., K * max_tasks) for latents z and actions a of `task`."""
        return self.dynamics.routing_weights(z, a, task)

    def next(self, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.dynamics(z, a, self._task)

    # ------------------------------------------------------------------ heads, params
    def new_heads(self, task: int | None = None) -> PWMHeads:
        """Fresh heads for `task` (default: the current task, set by `begin_task`)."""
        task = int(self.dynamics.current_task) if task is None else task
        return PWMHeads(self.cfg, self.dynamics.check_task(task)).to(self.device)

    def _param_groups(self, heads: nn.Module) -> list[dict]:
        groups = super()._param_groups(heads)
        for g in groups:
            if g["name"] == "dynamics":
                g["params"] = self.dynamics.optimizer_parameters()
        return groups

    # ------------------------------------------------------------------ losses
    def _batch_task(self, batch: Batch) -> torch.Tensor:
        """(B,): each window's routing task, the task of its row 0 (where the rollout starts;
        rows of another episode after a boundary are masked out of every loss)."""
        task = batch.task[0]
        self.dynamics.check_task(int(task.min()))
        self.dynamics.check_task(int(task.max()))
        return task

    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        h = _pwm_heads(heads)
        task = self._batch_task(batch)
        own = int(h.task_index)
        if self.cfg.router == "task" and not bool((task == own).all()):
            raise ValueError(
                f"PWM: heads of task {own} trained on a batch of tasks "
                f"{sorted(set(task.tolist()))}; call model.begin_task(i) before new_heads() "
                "and label the replay with the task index"
            )
        with self.routing_task(task), self.dynamics.recording_entropy() as record:
            out = super().loss(batch, h)
        entropy = float(torch.stack(record).mean())
        if self.training and torch.is_grad_enabled():
            self.dynamics.step_temperature(entropy, own)
        out.logs["routing_entropy"] = entropy
        out.logs["tau"] = float(self.dynamics.tau[own])
        return out

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        with self.routing_task(self._batch_task(batch)):
            return super().backbone_loss(batch)

    def head_update(
        self,
        batch: Batch,
        heads: nn.Module,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        with self.routing_task(self._batch_task(batch)):
            return super().head_update(batch, heads, out, optimizers)

    @torch.no_grad()
    def plan(
        self, z: torch.Tensor, heads: TDMPC2Heads, prev_mean: torch.Tensor | None, *,
        eval_mode: bool,
    ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """TD-MPC2's MPPI, routed with the task the heads belong to."""
        h = _pwm_heads(heads)
        with self.routing_task(h.task_index):
            return super().plan(z, h, prev_mean, eval_mode=eval_mode)


def _pwm_heads(heads: nn.Module) -> PWMHeads:
    if not isinstance(heads, PWMHeads):
        raise TypeError(f"expected PWMHeads from PWM.new_heads(), got {type(heads)}")
    return heads
