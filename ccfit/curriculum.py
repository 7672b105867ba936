"""Algorithm 1 online: a suite's curriculum learnt in the environment, evaluated on every
task seen so far (the track `ccfit.runner.CurriculumRunner` runs).

For each task t in order: fresh heads; the continual method acts on the backbone only
(`before_task`, `penalty`, `after_step`, `after_task`, `evaluating`); the heads train normally
through the shared `Trainer`; after the task its heads are frozen and stored. At every
evaluation point (a fixed interval of global steps) the current task and every earlier task
(with its stored heads on the current backbone) are evaluated, so each earlier task has a curve
through the rest of the curriculum (the BWT integral needs it). The composition task is also
learnt from scratch with the same budget (the FWT reference), once per config without the
method, and shared by every method's run.

Analyses plug in as `StageCallback`s, called after each task (the routing record of a model
offering 'routing'; `ccfit.analysis.stage_callbacks`).

Run directory:
    config.json          the resolved CurriculumConfig, plus what it resolved to where it ran
                         (seed dataset, device, render settings)
    metrics.jsonl        evaluation records: task, task_index, stage (task being trained),
                         global_step, task_step, discounted/normalised return, success rate
    tasks/<i>-<task>/    the trainer's checkpoint while task i trains (removed when it is done)
    curriculum.pt        state after the last finished task (model, stored heads, method, RNG)
    stages/after-<k>.pt  with --keep-stages, that state after each task k (`ccfit.branch`)
    branch.json          a run branched from another after its first tasks (`ccfit.branch`)
    first_task.json      a run that started from its sweep's shared first task
                         (`ccfit.first_task`)
    metrics.json         BWT, FWT and the standard metrics of this run
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch

from ccdata.env import make_env
from ccdata.processes import worker_pool
from ccfit.branch import RECORD as BRANCH_RECORD
from ccfit.branch import STAGES, Branch, keep_stage, read_branch, start_branch
from ccfit.config import CurriculumConfig
from ccfit.continual.base import ContinualMethod, method_config
from ccfit.first_task import first_task_done, mark_done, start_from_first_task
from ccfit.io import folder_lock
from ccfit.models.base import WorldModel
from ccfit.run_files import CHECKPOINT, METRICS_JSON, ONLINE, ONLINE_STATE, REFERENCE_DONE, task_dir
from ccfit.runner import CurriculumRunner, Restored, Track, run_reference
from ccfit.runner import restore as restore_run
from ccfit.settings import resolve_execution
from ccfit.train.eval_worker import parallel_on, yield_to_training
from ccfit.train.evaluate import submit_request
from ccfit.train.loop import Trainer
from ccfit.train.records import RunLogger
from ccfit.train.resources import check_disk
from ccfit.train.run import (
    CONFIG,
    build_model,
    check_saved_config,
    compile_as_begun,
    encoder_record,
    make_evaluator,
    make_replay,
    note_no_seed_dataset,
    plan_run_replay,
    resolved_config,
    train_task,
)

STATE = ONLINE_STATE
STATE_KIND = "ccfit-curriculum"
STATE_VERSION = 3

__all__ = ["METRICS_JSON", "REFERENCE_DONE", "STATE", "Curriculum", "OnlineTrack",
           "load_run"]  # fmt: skip


@dataclass
class Stage:
    """What a `StageCallback` sees after task `completed - 1` of a run finished."""

    run_dir: Path
    cfg: CurriculumConfig
    model: WorldModel
    stored_heads: list[torch.nn.Module]
    method: ContinualMethod
    device: torch.device


StageCallback = Callable[[Stage], None]
"""Called after each finished task (before its state is saved), e.g. the routing record."""


class OnlineTrack(Track):
    """Each task trained in its environment by the shared `Trainer`, with fresh heads that are
    frozen and stored when it ends; every task seen so far evaluated (in line, or in a worker
    beside training with `--train.parallel`)."""

    name = ONLINE
    loop = "train"
    state_file, state_kind, state_version = STATE, STATE_KIND, STATE_VERSION
    config_class = CurriculumConfig

    def __init__(self, cfg: CurriculumConfig, callbacks: list[StageCallback] = (),
                 keep_stages: bool = False, branch: Branch | None = None,
                 first_root: Path | None = None, first_only: bool = False) -> None:  # fmt: skip
        """`keep_stages`: keep the state after each task (`ccfit.branch`; a run that kept some
        keeps the rest when resumed without it); `branch`: start the run as a branch of
        another run (a new run directory; a resumed branch needs no `branch`); `first_root`:
        start the first task from the one shared in `first_root/<key>`, trained there first
        if no run has (`ccfit.first_task`; where the method shares it); `first_only`: this is
        that shared first task (`CurriculumRunner.run_first_task`)."""
        super().__init__(cfg)
        self.callbacks = list(callbacks)
        self.keep_stages = keep_stages
        self.branch = branch
        self.first_root = None if first_root is None else Path(first_root)
        self.first_only = first_only
        self.evaluator = self.logger = None
        self.scratch_job: ReferenceJob | None = None

    @classmethod
    def in_sweep(cls, cfg: CurriculumConfig, keep_stages: bool = False,
                 callbacks: list[StageCallback] = (),
                 first_root: Path | None = None) -> OnlineTrack:  # fmt: skip
        return cls(cfg, callbacks, keep_stages, first_root=first_root)

    @property
    def budget(self) -> int:
        return self.cfg.train.steps

    def resolved_config(self, *, record_dataset: bool = True) -> dict:
        return resolved_config(self.cfg, self.cfg.suite, self.execution,
                               record_dataset=record_dataset)  # fmt: skip

    def begin(self, out: Path, progress: bool) -> dict:
        cfg = self.cfg
        self.out, self.progress = out, progress
        self.keep_stages = self.keep_stages or (out / STAGES).is_dir()
        resolved = compile_as_begun(out, self.resolved_config())
        self.execution.set_threads()
        if self.branch is not None:
            start_branch(self.branch, resolved, out, len(cfg.tasks), STATE)
        known = read_branch(out)
        if known is not None:
            resolved[BRANCH_RECORD] = known
        if (out / CONFIG).exists():  # another run's state is refused, not restored
            check_saved_config(out, resolved)
        return resolved

    def build_model(self, device: torch.device, resolved: dict | None) -> WorldModel:
        compiled = None if resolved is None else resolved["resolved_compile"]
        return build_model(self.cfg, device, compiled)

    def prepare(self, resolved: dict, restored: Restored, reference: Path) -> None:
        cfg, out = self.cfg, self.out
        self.restored, self.reference = restored, reference
        self.source = resolved["resolved_seed_dataset"]
        note_no_seed_dataset(cfg, cfg.suite, self.source)
        # What does not fit fails here, before anything runs.
        self.plan = plan_run_replay(cfg, restored.model, list(cfg.tasks), self.source)
        check_disk(self.plan, out)
        out.mkdir(parents=True, exist_ok=True)
        check_saved_config(out, resolved)
        if self.first_only:  # the shared first task: no reference of its own
            self.defer_scratch, self.scratch_job = False, None
            return
        if self._starts_from_shared_first_task(restored):
            self._start_from_shared_first_task()
        # With compiled hot paths and tasks left after this one, the reference starts when this
        # process has trained its first task: the compiled graphs are then in Inductor's cache,
        # which the reference's process reads instead of compiling them beside this one.
        self.defer_scratch = (bool(resolved["resolved_compile"])
                              and len(cfg.tasks) - restored.completed > 1)  # fmt: skip
        self.scratch_job = None if self.defer_scratch else start_scratch(cfg, reference)

    def _starts_from_shared_first_task(self, restored: Restored) -> bool:
        """A run given `first_root` whose method shares the first task, before it began it."""
        cfg = self.cfg
        return (self.first_root is not None and restored.completed == 0
                and type(restored.method).shares_first_task and cfg.train.stop_score is None
                and not (task_dir(self.out, 0, cfg.tasks[0]) / CHECKPOINT).exists())  # fmt: skip

    def _start_from_shared_first_task(self) -> None:
        """The shared first task trained if no run or job has, then copied into this run's
        first task folder."""
        shared = self.first_root / self.reference_key()
        train_shared_first_task(self.cfg, shared, self.progress)
        start_from_first_task(shared, self.out, task_dir(self.out, 0, self.cfg.tasks[0]))

    def open(self, resolved: dict, restored: Restored) -> RunLogger:
        cfg = self.cfg
        self.stored = list(restored.stored_heads)
        self.logger = RunLogger(self.out, cfg.log, resolved)
        self.evaluator = make_evaluator(cfg, restored.model, dict(enumerate(cfg.tasks)),
                                        restored.method, compiled=resolved["resolved_compile"],
                                        execution=self.execution)  # fmt: skip
        self.evaluator.heads.update(enumerate(self.stored))
        # With the weights it saved with; a task's end evaluation keeps its own episode count.
        for request in self.logger.settle(restored.pending)[1]:
            submit_request(self.evaluator, request)
        return self.logger

    def learn_task(self, index: int, folder: Path, resumed: bool,
                   backbone_optim: dict | None) -> torch.optim.Optimizer:  # fmt: skip
        cfg, train, model = self.cfg, self.cfg.train, self.restored.model
        task = cfg.tasks[index]
        heads = model.new_heads()
        buffer = make_replay(cfg, model, task, index, None if resumed else self.source,
                             self.plan)  # fmt: skip
        env = make_env(
            task,
            render=cfg.obs == "pixels",
            image_size=cfg.image_size,
            episode_steps=train.episode_steps,
        )
        stored = self.stored
        trainer = Trainer(
            env=env, model=model, heads=heads, buffer=buffer, evaluator=self.evaluator,
            config=train, execution=self.execution, seed=cfg.seed, obs_mode=cfg.obs,
            task_id=task, task_index=index,
            logger=self.logger, method=self.restored.method, run_dir=folder,
            global_offset=index * train.steps, progress=self.progress,
            stored_heads_loss=lambda batch, j: model.loss(batch, stored[j]).total,
            backbone_optim=backbone_optim, stop_before_close=self.first_only,
        )  # fmt: skip
        try:
            # The task's last evaluation runs on while the next task trains.
            trainer.run(wait=False)
        finally:
            env.close()
        if self.first_only:
            return trainer.step.optim
        if self.defer_scratch:
            self.scratch_job, self.defer_scratch = start_scratch(cfg, self.reference), False
        heads.requires_grad_(False)
        heads.eval()
        self.stored.append(heads)
        # Only the optimiser leaves: this task's replay is released before the next task
        # allocates its own (held, the two rings would coexist while the next one is seeded:
        # twice the memory `plan_replay` checked).
        return trainer.step.optim

    def close_task(self, index: int) -> dict:
        restored = self.restored
        for callback in self.callbacks:
            callback(Stage(self.out, self.cfg, restored.model, self.stored, restored.method,
                           restored.model.device))  # fmt: skip
        # The evaluation requests still running were all submitted with these weights (the
        # task's checkpoint waited for earlier ones).
        return {"heads": [h.state_dict() for h in self.stored],
                "pending_evals": self.evaluator.pending}  # fmt: skip

    def saved(self, state: Path, completed: int) -> None:
        if self.keep_stages:
            keep_stage(self.out, state, completed)

    def finish(self) -> None:
        for record in self.evaluator.results(until=None):
            self.logger.log_eval(record)
        if self.scratch_job is not None:
            self.scratch_job.result()  # raises what the worker raised

    def close(self) -> None:
        try:
            if self.scratch_job is not None:  # done, unless the curriculum stopped early
                self.scratch_job.stop()
            if self.evaluator is not None:
                self.evaluator.close()
        finally:
            if self.logger is not None:
                self.logger.close()

    def describe(self) -> dict:
        cfg = self.cfg
        return dict(suite=cfg.suite, model=cfg.model.type, method=cfg.method.type,
                    seed=cfg.seed, obs=cfg.obs, preset=cfg.preset)  # fmt: skip

    def learn_reference(self, out: Path, progress: bool) -> list[dict]:
        cfg = self.cfg
        # Its config.json also records what the seed dataset and the encoder held (not part
        # of the key).
        meta = self.resolved_config()["resolved_seed_dataset_meta"]
        saved = {**self.reference_config(), **encoder_record(cfg),
                 "resolved_seed_dataset_meta": meta}  # fmt: skip
        return train_task(cfg, out, task_id=cfg.tasks[-1], task_index=len(cfg.tasks) - 1,
                          saved=saved, execution=self.execution, progress=progress)  # fmt: skip


class Curriculum(CurriculumRunner):
    """Runs (or resumes) one online continual run into `out` (`OnlineTrack`)."""

    def __init__(self, cfg: CurriculumConfig, out: str | Path, scratch_root: str | Path | None,
                 progress: bool = True, callbacks: list[StageCallback] = (),
                 keep_stages: bool = False, branch: Branch | None = None) -> None:  # fmt: skip
        super().__init__(OnlineTrack(cfg, callbacks, keep_stages, branch), out, scratch_root,
                         progress)  # fmt: skip


def _scratch_worker(cfg: CurriculumConfig, out: Path) -> None:
    """The from-scratch reference in a worker process, behind the curriculum's own."""
    yield_to_training()
    run_reference(OnlineTrack(cfg), out, progress=False)


def train_shared_first_task(cfg: CurriculumConfig, shared: Path, progress: bool = False,
                            trained_by: str = "run") -> dict:  # fmt: skip
    """The first task that `cfg`'s runs of every sharing method share (`ccfit.first_task`),
    trained into `shared` unless it is there already; returns its record. FT trains it: every
    sharing method trains it alike. Whoever comes first (`trained_by`: a sweep's 'job' for it,
    or a 'run') trains it under the folder's lock while the others wait; an interrupted one
    resumes."""
    with folder_lock(shared):
        record = first_task_done(shared)
        if record is None:
            # Its scalars go to TensorBoard, copied into each run; not a W&B run of its own.
            log = dataclasses.replace(cfg.log, wandb=False)
            ft = dataclasses.replace(cfg, method=method_config("ft"), log=log)
            CurriculumRunner(OnlineTrack(ft, first_only=True), shared,
                             progress=progress).run_first_task()  # fmt: skip
            record = mark_done(shared, task_dir(shared, 0, ft.tasks[0]), trained_by)
    return record


@dataclass
class ReferenceJob:
    """The from-scratch reference training in a worker process beside the curriculum."""

    pool: ProcessPoolExecutor
    future: Future

    def result(self):
        """Wait for it; raises what the worker raised."""
        return self.future.result()

    def stop(self) -> None:
        """Kill its worker unless it has finished: the curriculum stopped early (Ctrl-C, an
        error), and the interpreter's exit would otherwise wait for the whole reference. The
        reference resumes from its last checkpoint when the run is rerun."""
        if not self.future.done():
            self.pool.kill_workers()


def start_scratch(cfg: CurriculumConfig, out: Path) -> ReferenceJob | None:
    """The from-scratch reference trained in a worker process beside the curriculum
    (`--train.parallel`), unless it is done already; its evaluation stays in that worker."""
    if (out / REFERENCE_DONE).is_file() or not parallel_on(cfg.train.parallel):
        return None
    alone = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, parallel="off"))
    pool = worker_pool(1)
    future = pool.submit(_scratch_worker, alone, out)
    pool.shutdown(wait=False)  # the worker ends with its one job
    return ReferenceJob(pool, future)


# ======================================================================= loading a run


def restore(cfg: CurriculumConfig, run_dir: Path, device: torch.device,
            compiled: list[str] | None = None) -> Restored:  # fmt: skip
    """The saved state of `run_dir` (`ccfit.runner.restore`), its model's hot paths
    `compiled` (None: the config's choice, `build_model`)."""
    resolved = None if compiled is None else {"resolved_compile": compiled}
    return restore_run(OnlineTrack(cfg), run_dir, device, resolved)


@dataclass
class LoadedRun:
    """A finished (or partly finished) run read back from its directory."""

    cfg: CurriculumConfig
    model: WorldModel
    method: ContinualMethod
    stored_heads: list[torch.nn.Module]
    completed: int
    device: torch.device


def load_run(run_dir: str | Path, device: torch.device | str | None = None) -> LoadedRun:
    """Read a run directory (config.json + curriculum.pt) back: the public run loader that
    analyses (routing, ablations) use."""
    from ccfit.config_parse import saved_config

    cfg = saved_config(CurriculumConfig, run_dir, CONFIG)
    dev = resolve_execution(cfg.train, device).device
    saved = restore(cfg, run_dir, dev)
    return LoadedRun(cfg, saved.model, saved.method, saved.stored_heads, saved.completed, dev)
