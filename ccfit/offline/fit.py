"""The offline loop on one task: the backbone alone fitted on the task's dataset replay.

`TaskFitter` mirrors the online `Trainer` without an environment and without heads: each
update samples the task's replay, takes the model's `backbone_loss` plus the continual
method's `penalty` (ER's replayed windows, EWC's anchor), clips to the model's `grad_clip`,
steps the model's `backbone_optimizer`, then calls the model's `after_backbone_update` (PWM's
temperature) and the method's `after_step` (PackNet's and progressive experts' masks). Every
`score_interval` updates each task with held-out windows is scored
(`ccfit.offline.score`), inside the method's `evaluating(i, backbone)` view. When the task's
updates are done the method closes it as online (`ccfit.continual.base.close_task`):
`after_task` on the task's training replay, then the updates it asks for (PackNet's
retraining); then every task is scored once more (the end-of-task score C_i).

Checkpoints (atomic, every `checkpoint_interval` updates, every `checkpoint_minutes` and at the
end) hold the model, the optimiser, the method, the replay's sampling generator and every RNG:
the replay's rows are rebuilt from the dataset (the same split, checked), so a checkpoint stays
small. Scoring draws no random numbers of the training's, so a resumed task continues exactly
as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import json
import time
from contextlib import nullcontext
from pathlib import Path

import torch

from ccdata.errors import InputError
from ccfit.continual.base import ContinualMethod, ReplayLosses, close_task
from ccfit.io import atomic_torch_save, load_checkpoint, rng_state, set_rng_state
from ccfit.models.base import Batch, WorldModel
from ccfit.offline.config import FitConfig
from ccfit.offline.score import score_windows
from ccfit.replay import ReplayBuffer
from ccfit.run_files import CHECKPOINT, OFFLINE
from ccfit.settings import Execution, resolve_execution
from ccfit.train.records import RunLogger
from ccfit.train.update import load_backbone_optimizer_state

CHECKPOINT_KIND = "ccfit-offline-task"
CHECKPOINT_VERSION = 1
TRACK = OFFLINE
SCORE_KEY = "score"
"""What an offline record's curve is made of (online records: normalised returns)."""


class OfflineLogger(RunLogger):
    """Score records in metrics.jsonl (one line per task scored), scalars as a run's."""

    def log_score(self, record: dict) -> None:
        with self.jsonl.open("a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")
        if record[SCORE_KEY] is not None:
            self.log_scalars({f"offline/{record['task']}/score": record[SCORE_KEY]},
                             record["global_step"])  # fmt: skip


class TaskFitter:
    """Offline fitting of one task; `run()` fits (resuming from `run_dir`'s checkpoint) and
    closes the task, and returns this stage's score records.

    scored: held-out windows by task index (this task's and every earlier one's).
    task_ids: task id by index (what records name); method: None for plain fitting.
    backbone_optim: the previous task's `backbone_optimizer_state`, which this task's
        optimiser starts from (`fit.keep_backbone_optimizer`; None: fresh).
    execution: the run's device and precision, resolved (`ccfit.settings`; None: resolved
        from `fit` on the model's device).
    """

    def __init__(self, *, model: WorldModel, buffer: ReplayBuffer, scored: dict[int, Batch],
                 fit: FitConfig, seed: int, task_ids: list[str], task_index: int,
                 method: ContinualMethod | None, logger: OfflineLogger | None,
                 run_dir: Path | None, global_offset: int = 0, progress: bool = True,
                 backbone_optim: dict | None = None,
                 execution: Execution | None = None) -> None:  # fmt: skip
        self.model, self.buffer, self.scored, self.fit = model, buffer, scored, fit
        self.seed, self.task_ids, self.task_index = seed, task_ids, task_index
        self.method, self.logger, self.run_dir = method, logger, run_dir
        self.global_offset, self.progress = global_offset, progress
        self.execution = execution or resolve_execution(fit, model.device)
        mcfg = model.cfg
        if not buffer.can_sample(mcfg.seq_len):
            raise InputError(
                f"task {task_ids[task_index]}: its training episodes hold "
                f"{buffer.size} rows, fewer than a window of {mcfg.seq_len}"
            )
        self.optim = model.backbone_optimizer()
        if backbone_optim is not None:
            load_backbone_optimizer_state(self.optim, model.backbone, backbone_optim)
        self._params = [p for g in self.optim.param_groups for p in g["params"]]
        self.losses = ReplayLosses(model.backbone_loss)
        self.update = 0
        self.last_score = -1
        self.last_checkpoint = -1
        self.finished = False
        self.records: list[dict] = []
        self._last_save = time.monotonic()

    def run(self) -> list[dict]:
        from tqdm.auto import tqdm

        fit = self.fit
        if self.run_dir is not None and (self.run_dir / CHECKPOINT).exists():
            self.load_checkpoint(self.run_dir / CHECKPOINT)
        bar = tqdm(total=fit.updates, initial=self.update, unit="upd", dynamic_ncols=True,
                   desc=f"{self.task_ids[self.task_index]} (offline)", mininterval=1.0,
                   disable=not self.progress)  # fmt: skip
        try:
            while self.update < fit.updates:
                if self.update % fit.score_interval == 0 and self.last_score != self.update:
                    self._score()
                    rec = self.records[-1]
                    if rec[SCORE_KEY] is not None:
                        bar.set_postfix(score=f"{rec[SCORE_KEY]:.1f}")
                if (self.update % fit.checkpoint_interval == 0 and self.update > 0
                        and self.last_checkpoint != self.update):  # fmt: skip
                    self._checkpoint()
                self._step()
                self.update += 1
                bar.update(1)
                # Not at an update still to be scored: a run resumed from there would score
                # it and log it a second time.
                minutes = fit.checkpoint_minutes
                if (minutes > 0 and self.update % fit.score_interval != 0
                        and time.monotonic() - self._last_save >= 60.0 * minutes):  # fmt: skip
                    self._checkpoint()
            if not self.finished:
                self._finish_task()
                self._score()
                self.finished = True
                self._checkpoint()
        finally:
            bar.close()
        return self.records

    # ------------------------------------------------------------------------------ steps

    def _step(self) -> None:
        """One update of the backbone on a batch of this task's replay."""
        model, method, mcfg = self.model, self.method, self.model.cfg
        batch = self.buffer.sample(mcfg.batch_size, mcfg.seq_len).to(model.device)
        model.train()
        with self.execution.autocast_context():
            total = model.backbone_loss(batch)
            if method is not None:
                total = total + method.penalty(model.backbone, self.losses)
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(self._params, mcfg.grad_clip)
        self.optim.step()
        model.after_backbone_update(batch)
        if method is not None:
            method.after_step(model.backbone)

    def _finish_task(self) -> None:
        """The method closes the task on its training replay (`close_task`), then the updates
        it asks for."""
        close_task(self.method, self.task_index, self.model, self.buffer, self._steps)

    def _steps(self, n: int) -> None:
        for _ in range(n):
            self._step()

    def _score(self) -> None:
        """Score at this update: at a task's first update only the task itself (the earlier
        ones were scored at this global step when the previous task ended), else every task
        with held-out windows."""
        tasks = [self.task_index] if self.update == 0 else sorted(self.scored)
        for i in tasks:
            view = nullcontext() if self.method is None else \
                self.method.evaluating(i, self.model.backbone)  # fmt: skip
            rec = score_windows(self.model, self.scored[i], self.fit.context, self.fit.horizon,
                                self.fit.score_batch, view)  # fmt: skip
            rec.update(
                track=TRACK,
                task=self.task_ids[i],
                task_index=i,
                stage=self.task_index,
                global_step=self.global_offset + self.update,
                task_step=self.update,
            )
            self.records.append(rec)
            if self.logger is not None:
                self.logger.log_score(rec)
        self.last_score = self.update

    # ------------------------------------------------------------------------- checkpoints

    def _identity(self) -> dict:
        return {"fit_config": dataclasses.asdict(self.fit), "seed": self.seed,
                "task_id": self.task_ids[self.task_index],
                "global_offset": self.global_offset}  # fmt: skip

    def _checkpoint(self) -> None:
        self.last_checkpoint = self.update
        self._last_save = time.monotonic()
        if self.run_dir is not None:
            atomic_torch_save(self.state_dict(), self.run_dir / CHECKPOINT)

    def state_dict(self) -> dict:
        state = {
            "kind": CHECKPOINT_KIND,
            "version": CHECKPOINT_VERSION,
            **self._identity(),
            "update": self.update,
            "last_score": self.last_score,
            "last_checkpoint": self.last_checkpoint,
            "finished": self.finished,
            "records": self.records,
            "model": self.model.state_dict(),
            "optim": self.optim.state_dict(),
            "replay": {
                "rows": self.buffer.size,
                "episodes": self.buffer.num_episodes,
                "generator": self.buffer.generator.get_state(),
            },  # fmt: skip
            "rng": rng_state(),
        }
        if self.method is not None:
            state["method"] = self.method.state_dict()
        return state

    def load_checkpoint(self, path: Path) -> None:
        state = load_checkpoint(path, CHECKPOINT_KIND, CHECKPOINT_VERSION)
        if {k: state[k] for k in self._identity()} != self._identity():
            raise InputError(f"{path} was written by another run (config, seed or task "
                             "differ); use another run directory or delete it")  # fmt: skip
        replay = state["replay"]
        if (replay["rows"], replay["episodes"]) != (self.buffer.size, self.buffer.num_episodes):
            raise InputError(f"{path}: the dataset no longer gives this task's training "
                             "episodes; use another run directory or delete it")  # fmt: skip
        self.model.load_state_dict(state["model"])
        self.optim.load_state_dict(state["optim"])
        self.buffer.generator.set_state(replay["generator"])
        if self.method is not None:
            self.method.load_state_dict(state["method"])
        for key in ("update", "last_score", "last_checkpoint"):
            setattr(self, key, int(state[key]))
        self.finished = bool(state["finished"])
        self.records = list(state["records"])
        set_rng_state(state["rng"])
        if self.logger is not None:
            # What was logged after the checkpoint is done again: forgotten in metrics.jsonl
            # and in TensorBoard (which re-logging the checkpoint's records would duplicate).
            self.logger.rewind(self.global_offset + self.update)
