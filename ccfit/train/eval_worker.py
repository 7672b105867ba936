"""Evaluation beside training: `AsyncEvaluator` plays the evaluation episodes in a worker
process while the training process goes on, on a core that would otherwise idle.

Evaluating is a function of the weights alone (`Evaluator`: fixed layouts, a noise stream of
its own per task and global step), so the records are the ones the training process would
have computed: at submission the weights (model, the heads of the task being trained, the
continual method's state for its evaluation view) are copied and sent; the worker rebuilds
the same model, method and heads once, loads each request's weights into them, and evaluates.
Stored heads of finished tasks never change, so each is sent once.

The worker is one process (requests run in order, a checkpoint waits only for what it needs);
if it dies, collecting its results raises in the training process.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ccdata.processes import available_cores, worker_pool
from ccfit.models.base import WorldModel
from ccfit.settings import Execution


@dataclass
class WorkerSpec:
    """What the worker needs to build its own copy of the run's evaluator (picklable)."""

    model: Any
    """The run's model config (`ModelConfig`)."""
    encoder_path: str | None
    """The frozen pretrained encoder's file, if the run has one."""
    execution: Execution
    """The run's device, compile mode, precision and threads (`ccfit.settings`): the
    worker's are the training process's."""
    compiled: list[str]
    """The hot paths the training process compiles: the worker compiles them too."""
    method: Any
    """The run's method config (`MethodConfig`) when the method has an evaluation view (its
    state then travels with each request), else None."""
    num_tasks: int
    task_ids: dict[int, str]
    seed: int
    obs_mode: str
    image_size: int
    episodes: int
    episode_steps: int
    """Agent steps per episode (`train.episode_steps`)."""
    env_workers: int = 0
    """Processes the worker's evaluation environments run in (`EnvPool`)."""


_WORKER: dict[str, Any] = {}

HELPER_NICENESS = 10
"""How far below the training process its helpers run (`yield_to_training`)."""


def yield_to_training() -> None:
    """Run this helper process (the evaluation worker, a curriculum's from-scratch reference)
    at a lower priority than the training process it serves. Where they share too few cores
    (2 here: the training process's two threads, this one's two), the training process,
    which the run's end waits for, goes first, and the helper takes the cores it leaves idle
    (its single-threaded environment steps, its waits for compiles): measured on a Reach
    TD-MPC2 curriculum in docs/performance.md. Where cores are free, nothing changes. The
    helper's results are the same; only when they are ready moves."""
    os.nice(HELPER_NICENESS)


def _start(spec: WorkerSpec) -> None:
    from ccfit.continual.base import make_method
    from ccfit.models.encoders import load_frozen_encoder
    from ccfit.models.registry import make_model
    from ccfit.train.compiled import compile_hot_paths
    from ccfit.train.evaluate import Evaluator

    yield_to_training()
    execution = spec.execution
    execution.set_threads()
    encoder = None
    if spec.encoder_path is not None:
        encoder, _ = load_frozen_encoder(spec.encoder_path, device=execution.device)
    model = make_model(spec.model, execution.device, encoder=encoder)
    compile_hot_paths(model, execution.compile, paths=spec.compiled)
    method = make_method(spec.method, spec.num_tasks, spec.seed) if spec.method else None
    view = (lambda i: method.evaluating(i, model.backbone)) if method is not None else None
    _WORKER.update(model=model, method=method, heads={}, evaluator=Evaluator(
        model, spec.task_ids, seed=spec.seed, obs_mode=spec.obs_mode,
        image_size=spec.image_size, episodes=spec.episodes,
        episode_steps=spec.episode_steps, view=view,
        autocast=execution.autocast, env_workers=spec.env_workers))  # fmt: skip


def _heads(task: int, state: dict) -> nn.Module:
    model: WorldModel = _WORKER["model"]
    heads = _WORKER["heads"].get(task)
    if heads is None:
        heads = _WORKER["heads"][task] = model.new_heads()
        heads.requires_grad_(False)
    heads.load_state_dict(state)
    return heads


def _evaluate(request: dict, weights: dict, heads: dict[int, dict]) -> list[dict]:
    model, method, evaluator = _WORKER["model"], _WORKER["method"], _WORKER["evaluator"]
    model.load_state_dict(weights["model"])
    if method is not None:
        method.load_state_dict(weights["method"])
    for task, state in heads.items():
        evaluator.heads[task] = _heads(task, state)
    return evaluator.evaluate(request["tasks"], stage=request["stage"],
                              global_step=request["global_step"],
                              task_step=request["task_step"],
                              episodes=request.get("episodes"))  # fmt: skip


def _copy(state: Mapping[str, Any]) -> dict:
    """A detached CPU copy (training goes on changing the originals in place)."""

    def one(v):
        if isinstance(v, torch.Tensor):
            return v.detach().to("cpu", copy=True)
        if isinstance(v, Mapping):
            return {k: one(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return type(v)(one(x) for x in v)
        return v

    return one(state)


class AsyncEvaluator:
    """`Evaluator`'s interface (`heads`, `submit`, `results`, `pending`), computed by a worker
    process. model, method: the training process's (their weights are sent at each request;
    the method's only when it has an evaluation view, see `has_view`)."""

    def __init__(self, spec: WorkerSpec, model: WorldModel, method=None) -> None:
        self.model, self.method = model, method if has_view(method) else None
        self.heads: dict[int, nn.Module] = {}
        self._sent: set[int] = set()
        self._queue: list[tuple[dict, Future]] = []
        self._pool = worker_pool(1, initializer=_start, initargs=(spec,))

    def submit(self, tasks: Sequence[int], *, stage: int, global_step: int,
               task_step: int | None, episodes: int | None = None) -> None:  # fmt: skip
        request = {"tasks": list(tasks), "stage": stage, "global_step": global_step,
                   "task_step": task_step, "episodes": episodes}  # fmt: skip
        weights = {
            "model": _copy(self.model.state_dict()),
            "method": _copy(self.method.state_dict()) if self.method else None,
        }
        # The task being trained changes its heads; finished tasks' heads are sent once.
        send = {i: _copy(self.heads[i].state_dict()) for i in tasks
                if i == stage or i not in self._sent}  # fmt: skip
        self._sent |= {i for i in send if i != stage}
        self._queue.append((request, self._pool.submit(_evaluate, request, weights, send)))

    def results(self, until: int | None = -1) -> list[dict]:
        out = []
        while self._queue:
            request, future = self._queue[0]
            must = until is None or (until >= 0 and request["global_step"] < until)
            if not (must or future.done()):
                break
            out += future.result()  # raises what the worker raised
            self._queue.pop(0)
        return out

    @property
    def pending(self) -> list[dict]:
        return [request for request, _ in self._queue]

    def close(self) -> None:
        """End the worker. With a request still in flight the run is stopping early (Ctrl-C, an
        error, a first task stopped before its end): its checkpoint lists that request for the
        resumed run to submit again, so the worker is killed instead of waited for (at nice +10
        beside busy cores an evaluation can take many minutes)."""
        if any(not future.done() for _, future in self._queue):
            self._pool.kill_workers()
        else:
            self._pool.shutdown(wait=True, cancel_futures=True)


def has_view(method) -> bool:
    """Whether `method` evaluates a task through a view of the backbone (PackNet's masks):
    whether its `evaluating` is its own."""
    from ccfit.continual.base import ContinualMethod

    return method is not None and type(method).evaluating is not ContinualMethod.evaluating


def parallel_on(setting: str) -> bool:
    """`--train.parallel`: 'on', 'off', or 'auto' (on when this process may use 2+ cores)."""
    if setting != "auto":
        return setting == "on"
    return available_cores() >= 2
