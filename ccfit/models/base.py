"""The one interface every world model implements (TD-MPC2, PWM, DreamerV3, ...).

A world model splits into
- `backbone`: the task-agnostic part (observation encoder, dynamics, decoder if any). It is
  the only thing continual-learning methods ever see or touch.
- heads: the task-specific part (reward, termination/continue, value/critic, policy/actor and
  their statistics), made fresh per task by `new_heads()`, frozen and stored after the task,
  and usable on any later backbone to evaluate that task.

The contract. The shared training loop (ccfit.train) drives a model only through this
interface, in this order, and reads nothing else from it:

    model.begin_task(i, steps)                  # a task starts (PWM: routing, temperature)
    heads = model.new_heads()
    opt = model.world_model_optimizer(heads)    # backbone + heads trained by `loss`
    head_opts = model.head_optimizers(heads)    # what `head_update` steps (policy, critic)
    batch = replay.sample(model.cfg.batch_size, model.cfg.seq_len)   # on model.device
    out = model.loss(batch, heads)
    total = out.total + method.penalty(backbone, losses)
    total.backward(); clip to model.cfg.grad_clip; opt.step(); method.after_step(backbone)
    model.head_update(batch, heads, out, head_opts)   # never changes the backbone
    # `model.cfg.train_ratio` updates per env step (fractional ratios accumulate), after a
    # one-off burst of `model.cfg.pretrain_updates` on a fresh model (the run's first task)

    state = model.initial_state(heads, n)       # acting state of n episodes played together
    action, state = model.act(obs, heads, state, eval_mode=...)      # obs batched (n, ...)
    state = model.observe(obs, action, heads, state)  # a step the model did not choose

- Devices: the model lives on `model.device` (resolved by the caller); every `Batch` and
  observation reaches it already on that device; `act` returns actions as a NumPy array.
- `loss` and `backbone_loss` have no side effects: they may be called on other tasks' data or
  with earlier tasks' stored heads (ER replays through them, EWC takes its Fisher from them,
  analyses probe with them). Anything that must change once per update (target networks,
  temperatures, running statistics) changes in `head_update`, which the loop calls exactly
  once per update with the current task's heads; the offline track (no heads) calls
  `after_backbone_update(batch)` instead.
- Optimisers are made fresh at every task (`world_model_optimizer(heads)` gets the new heads),
  so Adam's moments restart with each task; what carries over between tasks is the backbone's
  parameters and the continual method's state. A resumed task restores its optimisers.
- `capabilities` names what a model offers beyond the interface, so that a method or an
  analysis that needs it finds it without naming models: 'experts' (its backbone holds an
  `ExpertGroups`, what progressive experts grows), 'routing' (it is a `Routing` model,
  what the routing analysis and expert ablation read), 'prediction' (it is a `Prediction`
  model: open-loop prediction in a space that does not move with training, what the offline
  track scores) and 'pixel-encoder' (in pixel mode it builds the shared
  `ccfit.models.encoders` encoder, the one `ccfit pretrain-encoder` pretrains).

Acting state is an explicit value owned by whoever plays the episodes, so stored heads of
earlier tasks evaluated mid-episode of the current task never disturb each other.
"""

from __future__ import annotations

import contextlib
import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

LATENT_KEY = "latent"
"""Observation key of a frozen encoder's output cached in replay (`WorldModel.replay_obs`)."""


@dataclass
class Batch:
    """Windows of `seq_len` consecutive replay rows, time-major; one transition per row.

    Row t holds observation o_t and the transition taken from it: action a_t, reward r_t and
    terminated_t (arriving at o_{t+1} ended the episode by success). The last row of an
    episode holds its final observation and a filler transition (zeros). A window may cross
    episode boundaries: `is_first[t]` = 1 where row t starts an episode, so transition t is
    real only when row t+1 exists and `is_first[t+1]` = 0 (see `valid` and `rollout_mask`).

    obs: dict of tensors (L, B, ...); 'state' (float32, 39) in state mode, or 'pixels' (uint8,
        9 x S x S: topview, frontview, gripperPOV channel-stacked) and 'proprio' (float32, 7)
        in pixel mode, or 'latent' (float32) when a frozen encoder's outputs are cached.
    action: (L, B, A); reward: (L, B, 1) in [-1, 0]; terminated: (L, B, 1) in {0, 1};
    is_first: (L, B, 1) in {0, 1}; task: (L, B) long, curriculum index of each row's task.
    """

    obs: dict[str, torch.Tensor]
    action: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    is_first: torch.Tensor
    task: torch.Tensor
    demos: int = 0
    """How many windows, the first ones, start on a stored demonstration
    (`ReplayBuffer.sample(demo_fraction=)`), which a model may learn from apart (the
    `demo_bc_coef` of TD-MPC2, PWM and DreamerV3)."""

    def to(self, device: torch.device | str) -> Batch:
        """This batch on `device` (no copy if it is there). From the host to a GPU the copy
        goes through page-locked memory (made here where the tensor is not in it already, as
        replay's batches are), so that it does not make the host wait for the device."""
        to_gpu = torch.device(device).type == "cuda"

        def move(x: torch.Tensor) -> torch.Tensor:
            if to_gpu and x.device.type == "cpu" and not x.is_pinned():
                x = x.pin_memory()
            return x.to(device, non_blocking=True)

        return Batch(obs={k: move(v) for k, v in self.obs.items()}, action=move(self.action),
                     reward=move(self.reward), terminated=move(self.terminated),
                     is_first=move(self.is_first), task=move(self.task),
                     demos=self.demos)  # fmt: skip

    @property
    def seq_len(self) -> int:
        return self.action.shape[0]

    @property
    def size(self) -> int:
        return self.action.shape[1]

    def valid(self) -> torch.Tensor:
        """(L-1, B, 1): 1 where transition t (row t -> row t+1) is a real transition."""
        return 1.0 - self.is_first[1:]

    def rollout_mask(self) -> torch.Tensor:
        """(L-1, B, 1): 1 for transitions reachable from row 0 without crossing into another
        episode (a latent rollout started at o_0 is meaningful only there)."""
        return self.valid().cumprod(0)

    def select(self, rows: torch.Tensor) -> Batch:
        """The windows at batch indices `rows` (any order, repeats allowed; none counted as
        demonstrations)."""
        return Batch(
            obs={k: v[:, rows] for k, v in self.obs.items()},
            action=self.action[:, rows],
            reward=self.reward[:, rows],
            terminated=self.terminated[:, rows],
            is_first=self.is_first[:, rows],
            task=self.task[:, rows],
        )


@dataclass
class LossOutput:
    """What `WorldModel.loss` returns."""

    total: torch.Tensor
    """Scalar to backpropagate through the world-model optimiser's parameters."""
    logs: dict[str, torch.Tensor | float] = field(default_factory=dict)
    """Detached scalars for logging (e.g. consistency, reward, value, termination), as 0-d
    tensors: the loop averages them when it writes a log point, so no update waits for a
    device-to-host copy."""
    aux: Any = None
    """Model-specific values reused by `head_update` (e.g. detached latents)."""


class WorldModel(nn.Module, ABC):
    """Base class; subclasses set `self.cfg` (their registered config), `self.device` and
    `self.backbone` (an nn.Module) in __init__. Register with `ccfit.models.register_model`."""

    cfg: Any
    device: torch.device
    backbone: nn.Module
    capabilities: ClassVar[frozenset[str]] = frozenset()
    """What the model offers beyond the interface ('experts', 'routing'; see the module doc)."""
    hot_paths: ClassVar[tuple[str, ...]] = ()
    """Methods that dominate a run's time: what `--train.compile=on` compiles (the eager
    methods stay the reference the tests compare the compiled ones with)."""
    compile_pays: ClassVar[dict[str, tuple[str, ...]]] = {}
    """Per device type, the hot paths measured faster compiled (`bench/update_rate.py`):
    what `--train.compile=auto` compiles. A device type not listed was never measured."""
    compile_pays_from: ClassVar[dict[str, int]] = {}
    """Per device type of `compile_pays`, the fewest steps per task (`--train.steps`) from
    which a run with those paths compiled measured faster than eager end to end, compiling
    included (`bench/startup.py`): `auto` compiles nothing in a shorter run. Not listed: 0."""
    reads_task_budget: ClassVar[bool] = False
    """Whether training reads the task's step budget (`begin_task`'s `task_steps`) before the
    task ends. Where it does not, a finished `ccfit train` run can be extended to more steps
    and ends as a run of that many steps from the start would (test_loop checks it per
    model); where it does (PWM's temperature hold), an extension would not."""

    # ------------------------------------------------------------------ structure
    @abstractmethod
    def new_heads(self) -> nn.Module:
        """Fresh task-specific heads on the model's device."""

    def begin_task(self, task_index: int, task_steps: int) -> None:  # noqa: B027 - optional
        """Task `task_index` (curriculum order) starts and trains for `task_steps` env steps;
        heads made after this call belong to it. No-op unless the model has per-task state."""

    # ------------------------------------------------------------------ optimisation
    @abstractmethod
    def world_model_optimizer(self, heads: nn.Module) -> torch.optim.Optimizer:
        """Optimiser over everything `loss` trains: the backbone's trainable parameters and the
        heads trained with it (reward, termination, value). Gradients are clipped to
        `cfg.grad_clip` (global norm over this optimiser's parameters) before each step."""

    @abstractmethod
    def head_optimizers(self, heads: nn.Module) -> dict[str, torch.optim.Optimizer]:
        """Optimisers `head_update` steps (policy, actor, critic), by name; checkpointed."""

    @abstractmethod
    def loss(self, batch: Batch, heads: nn.Module) -> LossOutput:
        """World-model loss with this task's heads (differentiable)."""

    @abstractmethod
    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """Task-agnostic terms only (dynamics consistency, reconstruction, KL): what continual
        methods replay (ER) or take Fisher information from (EWC)."""

    def after_backbone_update(self, batch: Batch) -> None:  # noqa: B027 - optional
        """The offline track's counterpart of `head_update`'s bookkeeping: called after each
        backbone-only update (`ccfit fit`) with that update's batch of the task being fitted,
        never with replayed earlier tasks. What a model advances once per update of its current
        task (PWM: its router temperature) goes here. No-op by default."""

    @abstractmethod
    def head_update(
        self,
        batch: Batch,
        heads: nn.Module,
        out: LossOutput,
        optimizers: dict[str, torch.optim.Optimizer],
    ) -> dict[str, float]:
        """Policy/actor/critic steps and target updates after the world-model step; must not
        change the backbone. Returns scalars to log."""

    def backbone_optimizer(self) -> torch.optim.Optimizer:
        """Optimiser over the backbone's trainable parameters alone, at the model's own
        learning rates: what fitting the backbone alone (`backbone_loss`, no heads: the offline
        track) steps. Gradients are clipped to `cfg.grad_clip` before each step."""
        raise NotImplementedError(f"{type(self).__name__} has no backbone_optimizer")

    def replay_obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What replay stores for an episode's observations (T+1, ...): by default the
        observations themselves; `loss` must accept whatever this returns."""
        return obs

    # ------------------------------------------------------------------ acting
    def initial_state(self, heads: nn.Module, n: int = 1) -> Any:
        """Acting state of `n` episodes at their start: None for a stateless model, else a
        pytree (tensors, or dataclasses / dicts / tuples of them) whose tensors have a leading
        dimension of n, so that whoever plays the episodes can keep some of them
        (`select_state`)."""
        return None

    @abstractmethod
    def act(
        self, obs: dict[str, torch.Tensor], heads: nn.Module, state: Any, *, eval_mode: bool
    ) -> tuple[np.ndarray, Any]:
        """Actions (n, A) in [-1, 1] for a batch of n observations (each tensor (n, ...), on
        the model's device), and the acting state after them (which remembers the actions)."""

    def observe(
        self, obs: dict[str, torch.Tensor], action: np.ndarray, heads: nn.Module, state: Any
    ) -> Any:
        """The acting state after steps the model did not choose (random seed steps): the n
        observations o_t were seen and `action` (n, A) taken. Stateless models return `state`
        unchanged."""
        return state


def check_on_device(ok: torch.Tensor, message: str) -> None:
    """ValueError(message) unless the boolean tensor `ok` is true. Off the CPU (a GPU; the
    meta device, on which the tests look for reads) the check is queued on the device
    (`torch._assert_async`) instead of read back, so an update never waits for the host; a
    failure then surfaces as a device-side assertion. Inside a compiled function it is the
    same op (a RuntimeError with the message on a CPU), which the graph holds: reading the
    value back would break the graph in two."""
    if ok.device.type != "cpu" or torch.compiler.is_compiling():
        torch._assert_async(ok, message)
    elif not bool(ok):
        raise ValueError(message)


def select_state(state: Any, keep: torch.Tensor) -> Any:
    """The acting state of the episodes `keep` (indices into the leading dimension of every
    tensor in it; dataclasses, dicts, lists and tuples are walked)."""
    if isinstance(state, torch.Tensor):
        return state[keep.to(state.device)]
    if dataclasses.is_dataclass(state) and not isinstance(state, type):
        return dataclasses.replace(state, **{f.name: select_state(getattr(state, f.name), keep)
                                             for f in dataclasses.fields(state)})  # fmt: skip
    if isinstance(state, dict):
        return {k: select_state(v, keep) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(select_state(v, keep) for v in state)
    return state


# ------------------------------------------------------------------------------ capabilities


@dataclass(frozen=True)
class ExpertLayout:
    """How a routed model's experts are laid out (what routing records state)."""

    experts_per_task: int
    """K: experts per group (one group per task under progressive experts)."""
    num_groups: int
    """Groups active now (computed and routable)."""
    max_experts: int
    """Experts allocated in all (active or not)."""

    @property
    def num_active(self) -> int:
        return self.num_groups * self.experts_per_task


class ExpertGroups(ABC):
    """Capability 'experts': a backbone module whose experts come in groups of K, allocated up
    front and activated one group at a time (PWM's mixture). Progressive experts finds it in
    the backbone (`find_expert_groups`), adds a group per task and freezes earlier ones."""

    @property
    @abstractmethod
    def active_groups(self) -> int:
        """Groups active now."""

    @abstractmethod
    def add_group(self) -> None:
        """Activate the next K experts (fresh, trainable)."""

    @abstractmethod
    def freeze_groups(self, n: int) -> None:
        """Freeze the experts of groups 0..n-1 (they stay routable)."""

    @abstractmethod
    def named_expert_parameters(self, groups: range) -> Iterator[tuple[str, nn.Parameter]]:
        """(name within this module, parameter) of the experts of `groups`."""

    @abstractmethod
    def shared_tensors(self, finished: int) -> dict[str, torch.Tensor]:
        """What the dynamics of tasks 0..finished-1 passes through besides their experts (PWM:
        the output head, the router's temperature column and those tasks' router columns), by
        name, as tensors that write through to the parameters (detached parameters or views of
        them)."""


def find_expert_groups(backbone: nn.Module) -> tuple[str, ExpertGroups] | None:
    """(its name in the backbone, the module) of the backbone's `ExpertGroups`, or None."""
    found = [(n, m) for n, m in backbone.named_modules() if isinstance(m, ExpertGroups)]
    if len(found) > 1:
        raise ValueError(f"backbone has {len(found)} ExpertGroups modules, expected one")
    return found[0] if found else None


class Routing(ABC):
    """Capability 'routing': a world model whose dynamics routes each (z, a) over experts
    with weights that can be read and ablated (PWM). The routing analysis (the paper's Fig. 5)
    and the expert ablation (Fig. 6) need only this, `encode`, `next` and the interface."""

    @abstractmethod
    def encode(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Observations (..., obs) -> latents (..., L)."""

    @abstractmethod
    def next(self, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Latent dynamics, routed as the current `routing_task`."""

    @abstractmethod
    def expert_layout(self) -> ExpertLayout:
        """The experts as they are now."""

    @abstractmethod
    def routed_task(self, heads: nn.Module) -> int:
        """The task a set of heads routes its planning as."""

    @abstractmethod
    def routing_task(self, task: int | torch.Tensor) -> contextlib.AbstractContextManager:
        """Within the block, `next` routes as `task`."""

    @abstractmethod
    def routing_override(self, mode: str | None) -> contextlib.AbstractContextManager:
        """Within the block, routing is replaced, relative to the routed task t: 'prior' (the
        groups before t only), 'new' (t's own group only), 'uniform', or None (learnt)."""

    @abstractmethod
    def routing_weights(self, z: torch.Tensor, a: torch.Tensor, task=None) -> torch.Tensor:
        """Weights (..., max_experts) of routing (z, a) as `task`; inactive experts get 0."""


@dataclass
class OpenLoop:
    """What `Prediction.open_loop` returns, per measured quantity (e.g. 'state'; 'pixels' and
    'proprio'; a frozen encoder's 'latent'), each flattened to one feature dimension D."""

    predicted: dict[str, torch.Tensor]
    """(H, B, D): the model's prediction of rows context .. context + H - 1."""
    target: dict[str, torch.Tensor]
    """(H, B, D): those rows as observed, in the same space."""
    last: dict[str, torch.Tensor]
    """(B, D): the last observed row (context - 1): what the persistence baseline predicts."""


class Prediction(ABC):
    """Capability 'prediction': open-loop prediction, measured in a space that does not move as
    the model trains (the offline track, `ccfit.offline`, scores it against persistence). The
    space is the observation where the model decodes, or a frozen pretrained encoder's latent:
    never the model's own latent space, which moves with training, so that an error measured
    there at two times compares two different spaces."""

    @classmethod
    @abstractmethod
    def measurement_space(cls, cfg: Any, frozen_encoder: bool) -> str | None:
        """The space `open_loop` measures in for config `cfg` (with a frozen pretrained encoder
        or not), in words; None when that model has none (it predicts its own latents only)."""

    @abstractmethod
    def open_loop(self, batch: Batch, context: int, horizon: int) -> OpenLoop:
        """Windows of `context + horizon` rows, each inside one episode: filter rows
        0 .. context - 1, then predict rows context .. context + horizon - 1 from the actions
        alone (action t is taken at row t) without seeing them. Deterministic (modes, not
        samples), no gradient."""
