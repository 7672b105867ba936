"""Algorithm 1: a suite's curriculum learnt continually, evaluated on every task seen so far.

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
    metrics.json         BWT, FWT and the standard metrics of this run
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import shutil
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch

from ccdata.env import make_env
from ccdata.processes import worker_pool
from ccfit import metrics as M
from ccfit.branch import RECORD as BRANCH_RECORD
from ccfit.branch import STAGES, Branch, keep_stage, read_branch, start_branch
from ccfit.config import CurriculumConfig
from ccfit.config_base import ENCODER_RECORD, identity, resolve_device, without_setting
from ccfit.continual.base import ContinualMethod, make_method
from ccfit.io import (
    atomic_torch_save,
    atomic_write_json,
    load_checkpoint,
    rng_state,
    seed_everything,  # fmt: skip
    set_rng_state,
)
from ccfit.models.base import WorldModel
from ccfit.replay_store import ROWS_DIR
from ccfit.train.cost import RunCost
from ccfit.train.eval_worker import parallel_on
from ccfit.train.loop import Trainer
from ccfit.train.records import RunLogger, record_stage
from ccfit.train.resources import check_disk
from ccfit.train.run import (
    CONFIG,
    build_model,
    check_same_encoder,
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
from ccfit.train.update import backbone_optimizer_state

STATE = "curriculum.pt"
STATE_KIND = "ccfit-curriculum"
STATE_VERSION = 3
METRICS_JSON = "metrics.json"
REFERENCE_DONE = "done.json"
"""A from-scratch reference's records, written when it is finished (online and offline)."""


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


def scratch_config(cfg: CurriculumConfig) -> dict:
    """config.json of the from-scratch reference: the run's, less what it does not depend
    on (the method, the output directory, where the run logs)."""
    resolved = identity(resolved_config(cfg, cfg.suite, record_dataset=False))
    # A single task has no optimiser state to carry over.
    resolved = without_setting(resolved, "train.keep_backbone_optimizer")
    return {k: v for k, v in resolved.items() if k not in ("method", "out")}


def scratch_key(cfg: CurriculumConfig) -> str:
    """Runs with equal keys share one from-scratch reference: everything but the method and
    the output directory (the device it ran on included)."""
    digest = hashlib.sha1(json.dumps(scratch_config(cfg), sort_keys=True).encode()).hexdigest()
    return f"{cfg.suite}-{cfg.model.type}-{cfg.obs}-{cfg.preset}-s{cfg.seed}-{digest[:8]}"


# ============================================================================ the run


def run_scratch(cfg: CurriculumConfig, out: Path, progress: bool = True) -> list[dict]:
    """The composition task learnt from scratch with the curriculum's per-task budget.

    Shared by every method's run: concurrent local runs take a file lock, so the first
    trains it and the others wait and read its records (a cluster orders them by job
    dependency instead)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = out / REFERENCE_DONE
    with open(out.parent / f".{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            # A finished reference made through another encoder file is refused.
            if done.is_file():
                check_same_encoder(out, cfg.encoder, encoder_record(cfg).get(ENCODER_RECORD))
                return json.loads(done.read_text())
            n = len(cfg.tasks)
            # Its config.json also records what the seed dataset and the encoder held (not
            # part of the key).
            meta = resolved_config(cfg, cfg.suite)["resolved_seed_dataset_meta"]
            saved = {**scratch_config(cfg), **encoder_record(cfg),
                     "resolved_seed_dataset_meta": meta}  # fmt: skip
            evals = train_task(cfg, out, task_id=cfg.tasks[-1], task_index=n - 1, saved=saved,
                               progress=progress)  # fmt: skip
            atomic_write_json(done, evals)
            (out / "checkpoint.pt").unlink(missing_ok=True)
            shutil.rmtree(out / ROWS_DIR, ignore_errors=True)
            return evals
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _scratch_worker(cfg: CurriculumConfig, out: Path, episode_steps: int) -> None:
    """`run_scratch` in a worker process (it sees the parent's episode length)."""
    import ccdata.env

    ccdata.env.EPISODE_STEPS = episode_steps
    run_scratch(cfg, out, progress=False)


def start_scratch(cfg: CurriculumConfig, out: Path) -> Future | None:
    """The from-scratch reference trained in a worker process beside the curriculum
    (`--train.parallel`), unless it is done already; its evaluation stays in that worker."""
    if (out / REFERENCE_DONE).is_file() or not parallel_on(cfg.train.parallel):
        return None
    import ccdata.env

    alone = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, parallel="off"))
    pool = worker_pool(1)
    future = pool.submit(_scratch_worker, alone, out, ccdata.env.EPISODE_STEPS)
    pool.shutdown(wait=False)  # the worker ends with its one job
    return future


class Curriculum:
    """Runs (or resumes) one continual run into `out`."""

    def __init__(self, cfg: CurriculumConfig, out: str | Path, scratch_root: str | Path | None,
                 progress: bool = True, callbacks: list[StageCallback] = (),
                 keep_stages: bool = False, branch: Branch | None = None) -> None:  # fmt: skip
        """`keep_stages`: keep the state after each task (`ccfit.branch`; a run that kept some
        keeps the rest when resumed without it); `branch`: start `out` as a branch of another
        run (a new `out`; a resumed branch needs no `branch`)."""
        self.cfg = cfg
        self.out = Path(out)
        self.scratch_root = Path(scratch_root) if scratch_root else self.out.parent / "scratch"
        self.progress = progress
        self.callbacks = list(callbacks)
        self.keep_stages = keep_stages or (self.out / STAGES).is_dir()
        self.branch = branch
        self.device = resolve_device(cfg.train.device)

    def run(self) -> dict:
        """The curriculum to its end (resuming what `out` holds); what this call cost is
        added to `out/cost.json` (the from-scratch reference's included when it ran here)."""
        with RunCost(self.out):
            return self._run()

    def _run(self) -> dict:
        cfg, train = self.cfg, self.cfg.train
        resolved = compile_as_begun(self.out, resolved_config(cfg, cfg.suite))
        if train.torch_threads > 0:
            torch.set_num_threads(train.torch_threads)
        tasks = cfg.tasks
        if self.branch is not None:
            start_branch(self.branch, resolved, self.out, len(tasks), STATE)
        known = read_branch(self.out)
        if known is not None:
            resolved[BRANCH_RECORD] = known
        if (self.out / CONFIG).exists():  # another run's state is refused, not restored
            check_saved_config(self.out, resolved)
        model, method, stored, completed, pending, carried = restore(
            cfg, self.out, self.device, resolved["resolved_compile"]
        )
        source = resolved["resolved_seed_dataset"]
        note_no_seed_dataset(cfg, cfg.suite, source)
        # What does not fit fails here, before anything runs.
        plan = plan_run_replay(cfg, model, list(tasks), source)
        check_disk(plan, self.out)
        self.out.mkdir(parents=True, exist_ok=True)
        check_saved_config(self.out, resolved)
        for i in range(completed):  # a run killed between saving a task and removing its folder
            shutil.rmtree(self.out / "tasks" / f"{i}-{tasks[i]}", ignore_errors=True)
        scratch_dir = (self.scratch_root / scratch_key(cfg)).resolve()
        # With compiled hot paths and tasks left after this one, the reference starts when this
        # process has trained its first task: the compiled graphs are then in Inductor's cache,
        # which the reference's process reads instead of compiling them beside this one.
        defer_scratch = bool(resolved["resolved_compile"]) and len(tasks) - completed > 1
        scratch_job = None if defer_scratch else start_scratch(cfg, scratch_dir)
        logger = RunLogger(self.out, cfg.log, resolved)
        evaluator = make_evaluator(cfg, model, dict(enumerate(tasks)), method,
                                   compiled=resolved["resolved_compile"])  # fmt: skip
        evaluator.heads.update(enumerate(stored))
        try:
            for request in logger.settle(pending)[1]:  # the saved weights are those it had
                evaluator.submit(request["tasks"], stage=request["stage"],
                                 global_step=request["global_step"],
                                 task_step=request["task_step"])  # fmt: skip
            for i in range(completed, len(tasks)):
                task_dir = self.out / "tasks" / f"{i}-{tasks[i]}"
                resumed = (task_dir / "checkpoint.pt").exists()
                if not resumed:  # forget stages a killed run had started but not checkpointed
                    logger.keep(lambda r, i=i: record_stage(r) < i)
                model.begin_task(i, train.steps)
                method.before_task(i, model.backbone)
                heads = model.new_heads()
                buffer = make_replay(cfg, model, tasks[i], i, None if resumed else source, plan)
                env = make_env(tasks[i], render=cfg.obs == "pixels", image_size=cfg.image_size)
                trainer = Trainer(
                    env=env, model=model, heads=heads, buffer=buffer, evaluator=evaluator,
                    config=train, seed=cfg.seed, obs_mode=cfg.obs, task_id=tasks[i],
                    task_index=i, logger=logger, method=method, run_dir=task_dir,
                    global_offset=i * train.steps, progress=self.progress,
                    stored_heads_loss=lambda batch, j: model.loss(batch, stored[j]).total,
                    backbone_optim=carried,
                )  # fmt: skip
                try:
                    # The task's last evaluation runs on while the next task trains.
                    trainer.run(wait=False)
                finally:
                    env.close()
                if defer_scratch:
                    scratch_job, defer_scratch = start_scratch(cfg, scratch_dir), False
                if train.keep_backbone_optimizer:
                    carried = backbone_optimizer_state(trainer.step.optim, model.backbone)
                heads.requires_grad_(False)
                heads.eval()
                stored.append(heads)
                for callback in self.callbacks:
                    callback(Stage(self.out, cfg, model, stored, method, self.device))
                self._save(i + 1, model, method, stored, evaluator.pending, carried)
                shutil.rmtree(task_dir, ignore_errors=True)
                # Release this task's replay before the next task allocates its own: held here,
                # the two rings would coexist while the next one is seeded (twice the memory
                # `plan_replay` checked).
                del trainer, buffer
            for record in evaluator.results(until=None):
                logger.log_eval(record)
        finally:
            evaluator.close()
            logger.close()
        if scratch_job is not None:
            scratch_job.result()  # raises what the worker raised
        scratch = run_scratch(cfg, scratch_dir, self.progress)
        result = M.compute_metrics(logger.read_evals(), scratch, len(tasks), train.steps)
        # Absolute: `ccfit report` may run from another working directory.
        result.update(suite=cfg.suite, model=cfg.model.type, method=cfg.method.type,
                      seed=cfg.seed, obs=cfg.obs, preset=cfg.preset,
                      scratch_dir=str(scratch_dir))  # fmt: skip
        atomic_write_json(self.out / METRICS_JSON, result)
        return result

    def _save(self, completed: int, model, method, stored, pending: list[dict],
              backbone_optim: dict | None) -> None:  # fmt: skip
        """The state after `completed` tasks; `pending`: evaluation requests still running,
        all submitted with these weights (the task's checkpoint waited for earlier ones);
        `backbone_optim`: the optimiser state the next task starts from (None: fresh)."""
        atomic_torch_save({
            "kind": STATE_KIND,
            "version": STATE_VERSION,
            "completed": completed,
            "model": model.state_dict(),
            "method": method.state_dict(),
            "heads": [h.state_dict() for h in stored],
            "pending_evals": pending,
            "backbone_optim": backbone_optim,
            "rng": rng_state(),
        }, self.out / STATE)  # fmt: skip
        if self.keep_stages:
            keep_stage(self.out, self.out / STATE, completed)


# ======================================================================= loading a run


class Restored(NamedTuple):
    """A run directory's saved state after its finished tasks (`restore`)."""

    model: WorldModel
    method: ContinualMethod
    stored_heads: list[torch.nn.Module]
    completed: int
    """Tasks finished."""
    pending: list[dict]
    """Evaluation requests in flight when the state was saved."""
    backbone_optim: dict | None
    """The backbone's optimiser state the next task starts from (None: fresh)."""


def restore(cfg: CurriculumConfig, run_dir: Path, device: torch.device,
            compiled: list[str] | None = None) -> Restored:  # fmt: skip
    """The saved state of `run_dir` (fresh when it has none yet), its model's hot paths
    `compiled` (None: the config's choice, `build_model`). Global RNGs are seeded, or restored
    from the saved state."""
    seed_everything(cfg.seed)
    model = build_model(cfg, device, compiled)
    method = make_method(cfg.method, len(cfg.tasks), cfg.seed)
    stored: list[torch.nn.Module] = []
    path = Path(run_dir) / STATE
    if not path.exists():
        return Restored(model, method, stored, 0, [], None)
    state = load_checkpoint(path, STATE_KIND, STATE_VERSION)
    # Model structure never changes shape (expert groups are allocated up front), so the
    # states load directly; the next task's before_task continues from them.
    model.load_state_dict(state["model"])
    method.load_state_dict(state["method"])
    for heads_state in state["heads"]:
        heads = model.new_heads()
        heads.load_state_dict(heads_state)
        heads.requires_grad_(False)
        heads.eval()
        stored.append(heads)
    set_rng_state(state["rng"])
    # Older states were saved once their evaluations had finished.
    return Restored(
        model,
        method,
        stored,
        int(state["completed"]),
        list(state.get("pending_evals", [])),
        state.get("backbone_optim"),
    )


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
    dev = resolve_device(device if device is not None else cfg.train.device)
    saved = restore(cfg, run_dir, dev)
    return LoadedRun(cfg, saved.model, saved.method, saved.stored_heads, saved.completed, dev)
