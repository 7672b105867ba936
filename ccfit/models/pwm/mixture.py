"""The mixture-of-experts latent dynamics with its router and temperature schedule."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import nn

from ccfit.models.base import ExpertGroups, ExpertLayout, check_on_device
from ccfit.models.layers import NormedLinear, SimNorm, init_weights
from ccfit.models.pwm.config import PWMConfig

OVERRIDES: tuple[str | None, ...] = (None, "prior", "new", "uniform")
"""Routing ablations, relative to the routed task t: learnt (None); only the experts of the
groups before t ('prior') or of t's own group ('new'), both renormalised from the learnt
weights; uniform over the groups 0..t ('uniform')."""


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


class MixtureDynamics(nn.Module, ExpertGroups):
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
        # Python copies of the group counters (the buffers are what checkpoints hold): shapes
        # and loops depend on them, and reading a buffer would sync with the GPU every forward.
        self._groups, self._frozen = 1, 0
        self.apply_trainability()
        # Loading a checkpoint restores the group counters; the copies and flags follow them.
        self.register_load_state_dict_post_hook(lambda module, _: module._read_counters())

    # ------------------------------------------------------------------ groups
    @property
    def active_groups(self) -> int:
        return self._groups

    @property
    def num_active(self) -> int:
        return self._groups * self.k

    def layout(self) -> ExpertLayout:
        return ExpertLayout(self.k, self._groups, self.max_experts)

    def group_of(self, expert: int) -> int:
        return expert // self.k

    def named_expert_parameters(self, groups: range) -> Iterator[tuple[str, nn.Parameter]]:
        """(name within this module, parameter) of the experts of `groups`."""
        for e in range(groups.start * self.k, groups.stop * self.k):
            for name, p in self.experts[e].named_parameters():
                yield f"experts.{e}.{name}", p

    def shared_tensors(self, finished: int) -> dict[str, torch.Tensor]:
        shared = {f"head.{name}": p.detach() for name, p in self.head.named_parameters()}
        weight = self.router.weight.detach()
        shared["router.weight[:, tau]"] = weight[:, -1]
        if self.cfg.router == "task" and finished > 0:
            # No gradient reaches a finished task's column, but Adam's moments carried over
            # from its own training (`keep_backbone_optimizer`) would still move it.
            shared["router.weight[:, :finished]"] = weight[:, :finished]
        return shared

    def apply_trainability(self) -> None:
        """requires_grad: True for active, unfrozen experts; False for frozen and inactive."""
        for e, expert in enumerate(self.experts):
            g = self.group_of(e)
            expert.requires_grad_(self._frozen <= g < self._groups)

    def _read_counters(self) -> None:
        """The Python copies from the buffers (after a checkpoint load, the one read of them)."""
        self._groups, self._frozen = int(self.num_groups), int(self.num_frozen)
        self.apply_trainability()

    def add_group(self) -> None:
        """Activate the next K experts (fresh, trainable)."""
        if self._groups >= self.max_tasks:
            raise ValueError(f"PWM: all {self.max_tasks} expert groups are active; raise max_tasks")
        self._groups += 1
        self.num_groups.fill_(self._groups)
        self.apply_trainability()

    def freeze_groups(self, n: int) -> None:
        """Freeze the experts of groups 0..n-1 (they stay routable)."""
        if not 0 <= n <= self._groups:
            raise ValueError(f"PWM: cannot freeze {n} groups, {self._groups} active")
        self._frozen = n
        self.num_frozen.fill_(n)
        self.apply_trainability()

    def optimizer_parameters(self) -> list[nn.Parameter]:
        """Router, head and every expert not frozen that trains now: inactive experts do not
        (`requires_grad` off), so the optimiser is built again once a task's group is added."""
        unfrozen = self.named_expert_parameters(range(self._frozen, self.max_tasks))
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

    def target_entropy(self, task: int) -> float:
        """H_target of `task`: tau_target_frac * log(the experts it routes over)."""
        scope = self.num_active
        if self.cfg.routing_scope == "own":
            scope = min(scope, (task + 1) * self.k)
        return self.cfg.tau_target_frac * math.log(scope)

    @torch.no_grad()
    def step_temperature(self, entropies: torch.Tensor, task: int) -> None:
        """The temperature schedule of task `task` over one training update: one step per
        dynamics forward of the update, `entropies` (one mean routing entropy per forward, in
        rollout order), as the authors' router steps on every training forward. Tensor
        arithmetic on the buffers, so a GPU update never waits for the host."""
        cfg, task = self.cfg, self.check_task(task)
        entropies = torch.as_tensor(entropies, dtype=self.tau.dtype, device=self.tau.device)
        target = self.target_entropy(task)
        for entropy in entropies.reshape(-1).unbind():
            moved = self.tau[task] + cfg.tau_rate * torch.tanh(target - entropy)
            held = self.tau_updates[task] < self.tau_hold[task]
            self.tau[task] = torch.where(held, self.tau[task],
                                         moved.clamp(cfg.tau_min, cfg.tau_max))  # fmt: skip
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
        if mode == "prior" and self._groups < 2:
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
        """Routing weights over the active experts (..., num_active). With `routing_scope`
        'own' a task routes over the groups up to its own (0..task): experts added for later
        tasks get weight exactly 0, so a finished task's dynamics never mixes in experts
        trained after it; with 'all' over every active group."""
        n = self.num_active
        tau = self.tau[task].unsqueeze(-1)  # a copy: later in-place tau updates are safe
        if self.cfg.router == "task":
            gate = F.one_hot(task, self.max_tasks).to(za.dtype)
        else:
            gate = za
        logits = F.linear(torch.cat([gate, tau], -1), self.router.weight[:n]) / tau
        group = torch.arange(n, device=za.device) // self.k
        own = task.unsqueeze(-1)
        keep = (group <= own) | (self.cfg.routing_scope == "all")
        if self.override == "uniform":
            logits = torch.zeros_like(logits)
        elif self.override == "prior":
            check_on_device((task > 0).all(), "routing override 'prior': task 0 has no earlier "
                            "experts")  # fmt: skip
            keep = keep & (group < own)
        elif self.override == "new":
            check_on_device((task < self._groups).all(), "routing override 'new': the routed "
                            "task's expert group is not active")  # fmt: skip
            keep = group == own
        return F.softmax(logits.masked_fill(~keep, float("-inf")), dim=-1)

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
