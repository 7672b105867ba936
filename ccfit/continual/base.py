"""The continual-method interface and its registry.

A continual method acts on the task-agnostic backbone only (heads are never regularised,
replayed or pruned) through five hooks, called by the training loop (ccfit.train):

    method.before_task(t, backbone)                    # a new task starts
    loss = out.total + method.penalty(backbone, model.backbone_loss)
    loss.backward(); clip; opt.step(); method.after_step(backbone)
    ...
    method.after_task(t, backbone, task_data)          # task t's training ended
    for _ in range(method.wants_retrain_steps): <one more update as above>   # PackNet only
    with method.evaluating(i, backbone): <evaluate task i with its stored heads>

A method never sees the trainer, the optimiser or the heads. It may keep state between hooks
and exposes it through `state_dict` / `load_state_dict` so runs can resume.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import draccus
import torch
from torch import nn

from ccfit.config_base import ChoiceConfig, ConfigError, check, check_types
from ccfit.models.base import Batch, WorldModel
from ccfit.replay import ReplayBuffer


@dataclass
class TaskData:
    """What a method may read about a task when it ends (given to `after_task`)."""

    task_index: int
    """Curriculum index of the task that just ended."""
    sample: Callable[[], Batch]
    """Draws a fresh training batch from this task's replay buffer (EWC's Fisher batches)."""
    num_transitions: int
    """n, the number of real transitions of this task in replay (ER keeps a share of them)."""
    num_rows: int
    """Rows of this task's replay (an episode of T transitions is T + 1 rows)."""
    windows: Callable[[torch.Tensor], Batch]
    """The windows of `seq_len` consecutive rows starting at the given rows (counted from the
    oldest, in [0, num_rows - seq_len]), on the CPU: lets ER keep a subset of this task's
    windows after the trainer's buffer for it is gone."""
    seq_len: int
    """Rows per training window of the model (ER cuts its replay windows to this length)."""
    batch_size: int
    """Windows per training batch of the model (ER's default replay batch)."""
    backbone_loss: Callable[[Batch], torch.Tensor]
    """The model's task-agnostic loss (`WorldModel.backbone_loss`)."""

    @classmethod
    def from_buffer(
        cls,
        task_index: int,
        buffer: ReplayBuffer,
        *,
        batch_size: int,
        seq_len: int,
        backbone_loss: Callable[[Batch], torch.Tensor],
        device: torch.device | str = "cpu",
    ) -> TaskData:
        """The view of a task's replay buffer: training batches of `batch_size` x `seq_len`
        rows on `device`, and windows of it on the CPU."""
        return cls(
            task_index=task_index,
            sample=lambda: buffer.sample(batch_size, seq_len).to(device),
            num_transitions=buffer.num_transitions,
            num_rows=buffer.size,
            windows=lambda starts: buffer.gather(starts, seq_len),
            seq_len=seq_len,
            batch_size=batch_size,
            backbone_loss=backbone_loss,
        )


@dataclass
class ReplayLosses:
    """What a method's `penalty` may evaluate on replayed data. Calling it gives the
    backbone loss, so a method can treat it as `WorldModel.backbone_loss`."""

    backbone: Callable[[Batch], torch.Tensor]
    """The model's task-agnostic loss (`WorldModel.backbone_loss`)."""
    stored_heads: Callable[[Batch, int], torch.Tensor] | None = None
    """The model's whole loss of a batch through finished task i's stored heads, which are
    frozen, so its gradient reaches the backbone only; None outside a curriculum."""

    def __call__(self, batch: Batch) -> torch.Tensor:
        return self.backbone(batch)


class ContinualMethod:
    """Base class: every hook is a no-op, so it is also plain fine-tuning."""

    name: str = "base"
    """Registry name, set by `register_method`."""
    config_class: type[MethodConfig]
    """Its options, set by `register_method`."""
    shares_first_task: bool = False
    """Its hooks leave the first task's training as plain fine-tuning leaves it, up to
    `after_task` (no state changes, no random numbers drawn), so runs of it may start from a
    first task trained once for every such method (`ccfit.first_task`; the contract test
    runs each method that says so both ways)."""

    def __init__(self, cfg: MethodConfig, num_tasks: int, seed: int = 0) -> None:
        if num_tasks < 1:
            raise ValueError(f"num_tasks must be >= 1, got {num_tasks}")
        self.cfg = cfg
        self.num_tasks = num_tasks
        """Tasks in the curriculum (PackNet does not prune the last one)."""
        self.seed = seed
        """The run's seed (methods that draw random numbers derive their streams from it)."""

    # ---- the five hooks
    def before_task(self, task_index: int, backbone: nn.Module) -> None:
        """Task `task_index` starts (before its fresh heads are made)."""

    def penalty(self, backbone: nn.Module, backbone_loss: ReplayLosses) -> torch.Tensor:
        """Extra differentiable loss added to the update's total loss; zero by default."""
        return zero_like_backbone(backbone)

    def after_step(self, backbone: nn.Module) -> None:
        """Called right after each optimiser step."""

    def after_task(self, task_index: int, backbone: nn.Module, task_data: TaskData) -> None:
        """Task `task_index`'s training ended."""

    def evaluating(self, task_index: int, backbone: nn.Module) -> contextlib.AbstractContextManager:
        """Context in which task `task_index` is evaluated with its stored heads."""
        return contextlib.nullcontext()

    # ---- a request to the trainer (not a hook)
    @property
    def wants_retrain_steps(self) -> int:
        """Extra updates the trainer must run now, after `after_task` (PackNet's retraining);
        every one goes through `penalty` and `after_step` as usual."""
        return 0

    # ---- checkpointing
    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state:
            raise ValueError(f"{self.name}: unexpected state keys {sorted(state)}")


def close_task(method: ContinualMethod | None, task_index: int, model: WorldModel,
               buffer: ReplayBuffer, retrain: Callable[[int], None]) -> None:  # fmt: skip
    """The method closes a task, online and offline alike: `after_task` on the task's replay,
    then the updates it asks for (`retrain(n)`: PackNet's retraining), each a normal update."""
    if method is None:
        return
    mcfg = model.cfg
    data = TaskData.from_buffer(task_index, buffer, batch_size=mcfg.batch_size,
                                seq_len=mcfg.seq_len, backbone_loss=model.backbone_loss,
                                device=model.device)  # fmt: skip
    method.after_task(task_index, model.backbone, data)
    retrain(method.wants_retrain_steps)


def zero_like_backbone(backbone: nn.Module) -> torch.Tensor:
    """A scalar 0 on the backbone's device (what a method without a penalty returns)."""
    param = next(backbone.parameters(), None)
    return torch.zeros((), device=param.device if param is not None else "cpu")


def trainable_parameters(backbone: nn.Module) -> Iterator[tuple[str, nn.Parameter]]:
    """The backbone's parameters that train (a frozen pretrained encoder is skipped)."""
    for name, param in backbone.named_parameters():
        if param.requires_grad:
            yield name, param


# ----------------------------------------------------------------------------- registry


@dataclass
class MethodConfig(ChoiceConfig, draccus.ChoiceRegistry):
    """A method's options (`--method.type=NAME --method.OPTION=...`): one dataclass per
    method, beside it, registered with the method by `register_method(NAME, ConfigClass)` and
    validated in `__post_init__` (bad values: `ConfigError`)."""

    REQUIRES: ClassVar[frozenset[str]] = frozenset()
    """Capabilities the world model must declare (`WorldModel.capabilities`), e.g. 'experts'."""

    def __post_init__(self) -> None:
        check_types(self, finite=True)

    def check_curriculum(self, num_tasks: int) -> None:
        """ConfigError if the method cannot run a curriculum of `num_tasks` tasks."""


METHODS: dict[str, type[ContinualMethod]] = {}
"""Registered continual methods by name."""


def register_method(
    name: str, config_class: type[MethodConfig]
) -> Callable[[type[ContinualMethod]], type[ContinualMethod]]:
    """Class decorator: registers the method under `name` and its config as the `name` choice
    of `--method.type`. The method's constructor is `(cfg, num_tasks, seed)`."""

    def decorate(cls: type[ContinualMethod]) -> type[ContinualMethod]:
        if name in METHODS:
            raise ValueError(f"continual method {name!r} is already registered")
        if not (isinstance(cls, type) and issubclass(cls, ContinualMethod)):
            raise TypeError(f"{cls!r} is not a ContinualMethod subclass")
        MethodConfig.register_subclass(name)(config_class)
        METHODS[name] = cls
        cls.name = name
        cls.config_class = config_class
        return cls

    return decorate


def method_names() -> list[str]:
    return sorted(METHODS)


def method_config_class(name: str) -> type[MethodConfig]:
    """The config class of registered method `name` (ConfigError listing valid names)."""
    check(name in METHODS, f"unknown continual method {name!r}; valid: {', '.join(method_names())}")
    return METHODS[name].config_class


def method_config(name: str, **options: Any) -> MethodConfig:
    """The validated config of method `name` with `options` (what `--method.type=NAME
    --method.OPTION=...` gives); unknown names and options are a ConfigError."""
    cls = method_config_class(name)
    try:
        return cls(**options)
    except TypeError as e:  # an unknown option
        valid = ", ".join(f.name for f in dataclasses.fields(cls)) or "none"
        raise ConfigError(f"method {name!r}: {e}; its options: {valid}") from None


def make_method(cfg: MethodConfig, num_tasks: int, seed: int = 0) -> ContinualMethod:
    """The method of `cfg` for a curriculum of `num_tasks` tasks; `seed` reaches methods that
    draw random numbers (ER's reservoir and sampler)."""
    cfg.check_curriculum(num_tasks)
    return METHODS[cfg.type](cfg, num_tasks=num_tasks, seed=seed)
