"""PWM: TD-MPC2 with the mixture as its dynamics."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn

from ccfit.models.base import (
    Batch,
    ExpertLayout,
    LossOutput,
    OpenLoop,
    Routing,
    check_on_device,
)
from ccfit.models.encoders import FrozenEncoder
from ccfit.models.pwm.config import PWMConfig
from ccfit.models.pwm.mixture import MixtureDynamics
from ccfit.models.registry import register_model
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Heads


class PWMHeads(TDMPC2Heads):
    """TD-MPC2's heads, stamped with the task they belong to (routes their planning)."""

    task_index: torch.Tensor

    def __init__(self, cfg: PWMConfig, task: int) -> None:
        super().__init__(cfg)
        self.register_buffer("task_index", torch.tensor(int(task)))
        self.task = int(task)
        """The task as a Python int (routing without reading the buffer back)."""
        self.register_load_state_dict_post_hook(_task_from_buffer)


def _task_from_buffer(heads: PWMHeads, _) -> None:
    heads.task = int(heads.task_index)


@register_model("pwm", PWMConfig)
class PWM(TDMPC2, Routing):
    """TD-MPC2 with `MixtureDynamics` as its latent dynamics (see the module docstring)."""

    cfg: PWMConfig
    capabilities = frozenset({"experts", "routing", *TDMPC2.capabilities})
    # bench/update_rate.py, cpu preset, 1 thread: update 20.5 -> 17.1 ms and plan 7.5 ->
    # 5.1 ms compiled (the mixture's per-expert layers fuse).
    compile_pays = {"cpu": TDMPC2.hot_paths}
    compile_pays_from = TDMPC2.compile_pays_from  # its update and plan cost more: pays sooner
    reads_task_budget = True  # the temperature hold is a share of the task's steps

    def __init__(
        self,
        cfg: PWMConfig,
        device: torch.device,
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

    def expert_layout(self) -> ExpertLayout:
        return self.dynamics.layout()

    def routed_task(self, heads: nn.Module) -> int:
        return _pwm_heads(heads).task

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

    def _backbone_groups(self) -> list[dict]:
        groups = super()._backbone_groups()
        for g in groups:
            if g["name"] == "dynamics":
                g["params"] = self.dynamics.optimizer_parameters()
        return groups

    # ------------------------------------------------------------------ losses
    def _batch_task(self, batch: Batch) -> torch.Tensor:
        """(B,): each window's routing task, the task of its row 0 (where the rollout starts;
        rows of another episode after a boundary are masked out of every loss)."""
        task = batch.task[0]
        limit = self.dynamics.max_tasks
        check_on_device(((task >= 0) & (task < limit)).all(),
                        f"PWM: batch tasks outside 0..{limit - 1} (max_tasks)")  # fmt: skip
        return task

    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        h = _pwm_heads(heads)
        task = self._batch_task(batch)
        # The heads' task as a tensor, never `h.task`: a compiled loss would specialise on the
        # int and recompile for every task.
        own = h.task_index
        if self.cfg.router == "task":
            check_on_device(
                (task == own).all(),
                "PWM: heads trained on a batch of another task; call model.begin_task(i) "
                "before new_heads() and label the replay with the task index",
            )
        with self.routing_task(task), self.dynamics.recording_entropy() as record:
            out = super().loss(batch, h)
        # No side effect here (the contract): the temperature steps in `head_update`, over the
        # update of the task being trained (once per forward), never when ER replays stored heads.
        out.aux["routing_entropies"] = torch.stack(record)  # one per rollout step
        out.logs["routing_entropy"] = out.aux["routing_entropies"].mean()
        out.logs["tau"] = self.dynamics.tau[own.view(1)].squeeze(0)  # a copy, by a 1-d index
        return out

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        with self.routing_task(self._batch_task(batch)):
            return super().backbone_loss(batch)

    @torch.no_grad()
    def after_backbone_update(self, batch: Batch) -> None:
        """Offline, the temperature steps as online in `head_update`: once per dynamics forward
        of the update's rollout (seq_len - 1), each on the mean routing entropy of the batch's
        first rows under the updated router (with the 'task' router the weights depend on the
        task alone, so that is the entropy of every forward of the rollout)."""
        batch = batch.to(self.device)
        z = self.encode({k: v[0] for k, v in batch.obs.items()})
        w = self.dynamics.routing_weights(z, batch.action[0], self._batch_task(batch))
        entropy = torch.special.entr(w).sum(-1).mean()
        self.dynamics.step_temperature(entropy.expand(batch.seq_len - 1),
                                       int(self.dynamics.current_task))  # fmt: skip

    def open_loop(self, batch: Batch, context: int, horizon: int) -> OpenLoop:
        """TD-MPC2's, each window routed as its task."""
        batch = batch.to(self.device)
        with self.routing_task(self._batch_task(batch)):
            return super().open_loop(batch, context, horizon)

    def head_update(
        self,
        batch: Batch,
        heads: nn.Module,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        h = _pwm_heads(heads)
        self.dynamics.step_temperature(out.aux["routing_entropies"], h.task)
        with self.routing_task(self._batch_task(batch)):
            return super().head_update(batch, heads, out, optimizers)

    @torch.no_grad()
    def plan(
        self, z: torch.Tensor, heads: TDMPC2Heads, prev_mean: torch.Tensor | None, *,
        eval_mode: bool,
    ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """TD-MPC2's MPPI, routed with the task the heads belong to."""
        h = _pwm_heads(heads)
        # Routed by the heads' task tensor: one compiled plan serves every task.
        with self.routing_task(h.task_index):
            return super().plan(z, h, prev_mean, eval_mode=eval_mode)


def _pwm_heads(heads: nn.Module) -> PWMHeads:
    if not isinstance(heads, PWMHeads):
        raise TypeError(f"expected PWMHeads from PWM.new_heads(), got {type(heads)}")
    return heads
