"""Algorithm 1's outer loop, one for both tracks: a suite's tasks learnt in order by one
backbone under one continual method, every task seen so far measured as it goes, and the
composition task learnt from scratch once (the FWT reference) for BWT and FWT.

How a task is learnt and measured is the track's: online (`ccfit.curriculum.OnlineTrack`)
trains in the environment and evaluates returns; offline (`ccfit.offline.run.OfflineTrack`)
fits the task's dataset episodes and scores predictions. What both share is here: resuming
after the last finished task, the state saved after each task, the order in which a task is
begun and closed, the from-scratch reference's key and lock, and the metrics at the end. A
third track is one new `Track`.

For each task t not yet finished: `model.begin_task`, the method's `before_task`, the track's
`learn_task` (which ends with the method closing the task on its replay:
`ccfit.continual.base.close_task`), the backbone's optimiser state carried over where asked,
the state saved, the task's checkpoint folder removed.
"""

from __future__ import annotations

import abc
import functools
import hashlib
import json
import shutil
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import torch

from ccfit import metrics as M
from ccfit.config import with_encoder
from ccfit.config_base import ENCODER_RECORD, identity, without_setting
from ccfit.continual.base import ContinualMethod, make_method
from ccfit.io import (
    atomic_torch_save,
    atomic_write_json,
    folder_lock,
    load_checkpoint,
    rng_state,
    seed_everything,  # fmt: skip
    set_rng_state,
)
from ccfit.models.base import WorldModel
from ccfit.replay_store import ROWS_DIR
from ccfit.run_files import CHECKPOINT, METRICS_JSON, REFERENCE_DONE, reference_name, task_dir
from ccfit.settings import Execution, resolve_execution
from ccfit.train.cost import RunCost
from ccfit.train.records import RunLogger, record_stage
from ccfit.train.run import check_same_encoder, encoder_record
from ccfit.train.update import backbone_optimizer_state


class Restored(NamedTuple):
    """A run directory's saved state after its finished tasks (`restore`)."""

    model: WorldModel
    method: ContinualMethod
    stored_heads: list[torch.nn.Module]
    """Each finished task's frozen heads (online; the offline track fits the backbone alone)."""
    completed: int
    """Tasks finished."""
    pending: list[dict]
    """Evaluation requests in flight when the state was saved (online)."""
    backbone_optim: dict | None
    """The backbone's optimiser state the next task starts from (None: fresh)."""


class Track(abc.ABC):
    """One way of learning a curriculum: what the runner asks of it, in the order it asks.

    Made with the run's config, which it completes with what the run's start reads (the
    frozen encoder's sizes: `with_encoder`); `begin` hands it the run directory. Its config
    has `suite`, `tasks`, `seed`, `method`, `model`, `obs`, `preset`, `encoder` and the loop's
    settings under `loop` (`train` online, `fit` offline), among them how the run executes
    (`execution`)."""

    name: ClassVar[str]
    """What metrics.json records as the run's track (`ccfit.run_files`)."""
    loop: ClassVar[str]
    """The config's field holding the per-task loop's settings."""
    state_file: ClassVar[str]
    state_kind: ClassVar[str]
    state_version: ClassVar[int]
    score_key: ClassVar[str] = "normalized_return"
    """What a record's curve is made of (`ccfit.metrics.compute_metrics`)."""
    config_class: ClassVar[type]
    """The run config it takes (`ccfit run`'s, `ccfit fit`'s)."""

    def __init__(self, cfg: Any) -> None:
        self.cfg = with_encoder(cfg)
        self.out = Path()
        self.progress = True

    @classmethod
    def in_sweep(cls, cfg: Any, keep_stages: bool = False, callbacks: list = (),
                 first_root: Path | None = None) -> Track:  # fmt: skip
        """The track of one run of a sweep (`ccfit.sweep.jobs`); `keep_stages`: the run keeps
        its state after each task, and `callbacks` (`ccfit.analysis.stage_callbacks`) are
        called after each, where the track can; `first_root`: its first task starts from the
        one its seed's runs share there (`ccfit.first_task`), where the track can."""
        return cls(cfg)

    @property
    def settings(self) -> Any:
        """The per-task loop's settings (`TrainConfig`, `FitConfig`)."""
        return getattr(self.cfg, self.loop)

    @functools.cached_property
    def execution(self) -> Execution:
        """How the run executes here (device, compile mode, precision, threads), resolved
        once from its loop's settings and handed to all that builds or steps the model."""
        return resolve_execution(self.settings)

    @property
    @abc.abstractmethod
    def budget(self) -> int:
        """Steps (online) or updates (offline) per task: the step axis of the metrics."""

    # ------------------------------------------------------------------------ identity

    @abc.abstractmethod
    def resolved_config(self, *, record_dataset: bool = True) -> dict:
        """config.json of a run: its config plus what it resolved to where it runs;
        `record_dataset=False` leaves out what its dataset holds (no part of the identity)."""

    def reference_config(self) -> dict:
        """config.json of the from-scratch reference: the run's, less what a single task
        learnt without a method does not depend on."""
        resolved = identity(self.resolved_config(record_dataset=False))
        # A single task has no optimiser state to carry over.
        resolved = without_setting(resolved, f"{self.loop}.keep_backbone_optimizer")
        return {k: v for k, v in resolved.items() if k not in ("method", "out")}

    def reference_key(self) -> str:
        """Runs with equal keys share one from-scratch reference: everything but the method
        and the output directory (the device it ran on included)."""
        text = json.dumps(self.reference_config(), sort_keys=True)
        digest = hashlib.sha1(text.encode()).hexdigest()
        cfg = self.cfg
        return reference_name(cfg.suite, cfg.model.type, cfg.obs, cfg.preset, cfg.seed, digest,
                              track=self.name)  # fmt: skip

    # ------------------------------------------------------------------------- a run

    @abc.abstractmethod
    def begin(self, out: Path, progress: bool) -> dict:
        """The run's resolved config, checked against what `out` holds (before anything is
        restored)."""

    @abc.abstractmethod
    def build_model(self, device: torch.device, resolved: dict | None) -> WorldModel:
        """The run's world model (`resolved`: its config.json, None when read back)."""

    def prepare(self, resolved: dict, restored: Restored, reference: Path) -> None:
        """After the state is restored, before a task is learnt: what must fail before the
        run writes anything, and config.json written. Nothing by default."""
        return None

    @abc.abstractmethod
    def open(self, resolved: dict, restored: Restored) -> RunLogger:
        """Start what the tasks share (the logger whose records the metrics read)."""

    @abc.abstractmethod
    def learn_task(self, index: int, folder: Path, resumed: bool,
                   backbone_optim: dict | None) -> torch.optim.Optimizer:  # fmt: skip
        """Task `index` learnt (begun already; its checkpoint in `folder`, from which it
        resumes when `resumed`) and closed; the optimiser that stepped the backbone."""

    def close_task(self, index: int) -> dict:
        """After task `index` is learnt, before the state is saved: what the state holds
        besides the model, method, RNG and optimiser."""
        return {}

    def saved(self, state: Path, completed: int) -> None:
        """After the state after `completed` tasks is written to `state`."""
        return None

    def finish(self) -> None:
        """After the last task (records still in flight logged)."""
        return None

    @abc.abstractmethod
    def close(self) -> None:
        """Release what `open` started (also when it, or a task, failed part way)."""

    @abc.abstractmethod
    def describe(self) -> dict:
        """What metrics.json records of the run besides the metrics."""

    # ---------------------------------------------------------------------- reference

    @abc.abstractmethod
    def learn_reference(self, out: Path, progress: bool) -> list[dict]:
        """The composition task learnt from scratch into `out`, resuming what it holds; its
        records."""


def restore(track: Track, run_dir: Path, device: torch.device,
            resolved: dict | None = None) -> Restored:  # fmt: skip
    """The saved state of `run_dir` (fresh when it has none yet). Global RNGs are seeded, or
    restored from the saved state."""
    cfg = track.cfg
    seed_everything(cfg.seed)
    model = track.build_model(device, resolved)
    method = make_method(cfg.method, len(cfg.tasks), cfg.seed)
    path = Path(run_dir) / track.state_file
    if not path.exists():
        return Restored(model, method, [], 0, [], None)
    state = load_checkpoint(path, track.state_kind, track.state_version)
    # Model structure never changes shape (expert groups are allocated up front), so the
    # states load directly; the next task's before_task continues from them.
    model.load_state_dict(state["model"])
    method.load_state_dict(state["method"])
    stored = []
    for heads_state in state.get("heads", []):
        heads = model.new_heads()
        heads.load_state_dict(heads_state)
        heads.requires_grad_(False)
        heads.eval()
        stored.append(heads)
    set_rng_state(state["rng"])
    # Older states were saved once their evaluations had finished.
    return Restored(model, method, stored, int(state["completed"]),
                    list(state.get("pending_evals", [])),
                    state.get("backbone_optim"))  # fmt: skip


def run_reference(track: Track, out: Path, progress: bool = True) -> list[dict]:
    """The composition task learnt from scratch with the curriculum's per-task budget and no
    method (`track.learn_reference`), its records.

    Shared by every method's run: concurrent local runs take a file lock, so the first learns
    it and the others wait and read its records (a cluster orders them by job dependency
    instead)."""
    out = Path(out)
    done = out / REFERENCE_DONE
    with folder_lock(out):
        if done.is_file():  # a finished reference made through another encoder file
            cfg = track.cfg
            check_same_encoder(out, cfg.encoder, encoder_record(cfg).get(ENCODER_RECORD))
            return json.loads(done.read_text())
        records = track.learn_reference(out, progress)
        atomic_write_json(done, records)
        (out / CHECKPOINT).unlink(missing_ok=True)
        shutil.rmtree(out / ROWS_DIR, ignore_errors=True)
        return records


class CurriculumRunner:
    """Runs (or resumes) one continual run of `track` into `out`; the from-scratch
    reference goes to `scratch_root/<its key>` (default: `scratch` beside `out`)."""

    def __init__(self, track: Track, out: str | Path, scratch_root: str | Path | None = None,
                 progress: bool = True) -> None:  # fmt: skip
        self.track = track
        self.out = Path(out)
        self.scratch_root = Path(scratch_root) if scratch_root else self.out.parent / "scratch"
        self.progress = progress
        self.device = track.execution.device

    def run(self) -> dict:
        """The curriculum to its end (resuming what `out` holds); what this call cost is
        added to `out/cost.json` (the from-scratch reference's included when it ran here)."""
        with RunCost(self.out):
            return self._run()

    def _run(self) -> dict:
        track, out, tasks = self.track, self.out, self.track.cfg.tasks
        resolved = track.begin(out, self.progress)
        restored = restore(track, out, self.device, resolved)
        reference = (self.scratch_root / track.reference_key()).resolve()
        track.prepare(resolved, restored, reference)
        for i in range(restored.completed):  # killed between saving a task and removing it
            shutil.rmtree(task_dir(out, i, tasks[i]), ignore_errors=True)
        model, method, carried = restored.model, restored.method, restored.backbone_optim
        try:
            logger = track.open(resolved, restored)
            for i in range(restored.completed, len(tasks)):
                folder = task_dir(out, i, tasks[i])
                resumed = (folder / CHECKPOINT).exists()
                if not resumed:  # forget stages a killed run had started but not checkpointed
                    logger.keep(lambda r, i=i: record_stage(r) < i)
                model.begin_task(i, track.budget)
                method.before_task(i, model.backbone)
                optim = track.learn_task(i, folder, resumed, carried)
                if track.settings.keep_backbone_optimizer:
                    carried = backbone_optimizer_state(optim, model.backbone)
                del optim  # the task's optimiser, and what it holds, are not kept
                self._save(i + 1, model, method, carried, track.close_task(i))
                shutil.rmtree(folder, ignore_errors=True)
            track.finish()
        finally:
            track.close()
        scratch = run_reference(track, reference, self.progress)
        result = M.compute_metrics(logger.read_evals(), scratch, len(tasks), track.budget,
                                   key=track.score_key)  # fmt: skip
        # Absolute: `ccfit report` may run from another working directory.
        result.update(track.describe(), scratch_dir=str(reference))
        atomic_write_json(out / METRICS_JSON, result)
        return result

    def run_first_task(self) -> None:
        """Only the first task's steps, checkpointed before the method closes the task (the
        part `ccfit.first_task` shares between methods; the track stops there); resumes what
        `out` holds. No reference, no metrics."""
        track, out = self.track, self.out
        with RunCost(out):
            resolved = track.begin(out, self.progress)
            restored = restore(track, out, self.device, resolved)
            track.prepare(resolved, restored, self.scratch_root / track.reference_key())
            folder = task_dir(out, 0, track.cfg.tasks[0])
            try:
                track.open(resolved, restored)
                restored.model.begin_task(0, track.budget)
                restored.method.before_task(0, restored.model.backbone)
                track.learn_task(0, folder, (folder / CHECKPOINT).exists(), None)
            finally:
                track.close()

    def _save(self, completed: int, model: WorldModel, method: ContinualMethod,
              backbone_optim: dict | None, extra: dict) -> None:  # fmt: skip
        """The state after `completed` tasks; `backbone_optim`: the optimiser state the next
        task starts from (None: fresh); `extra`: the track's (`Track.close_task`)."""
        path = self.out / self.track.state_file
        atomic_torch_save({
            "kind": self.track.state_kind,
            "version": self.track.state_version,
            "completed": completed,
            "model": model.state_dict(),
            "method": method.state_dict(),
            "backbone_optim": backbone_optim,
            "rng": rng_state(),
            **extra,
        }, path)  # fmt: skip
        self.track.saved(path, completed)
