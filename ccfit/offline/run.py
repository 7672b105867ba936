"""A suite's curriculum fitted offline: the backbone on each task's dataset episodes in order,
every task seen so far scored on its held-out episodes at a fixed interval of updates (the
track `ccfit.runner.CurriculumRunner` runs).

For each task t in order: `model.begin_task`, the method's `before_task`, the task's training
replay and held-out windows (`ccfit.offline.data`), then `TaskFitter` (updates, scoring, the
method's `after_task` and retraining). The composition task is also fitted from scratch with
the same budget and no method (the FWT reference), once per config and shared by every
method's run, as online. BWT and FWT come from the score curves through `ccfit.metrics`
exactly as for returns, the budget and the step axis being updates.

Run directory (as `ccfit run`'s, plus split.json):
    config.json        the resolved OfflineConfig, plus the dataset, device, render settings
                       and measurement space it resolved to
    split.json         each task's training and held-out episodes and its scored windows
    metrics.jsonl      score records: task, task_index, stage, global_step (updates),
                       task_step, score, per-quantity scores, score by horizon step, MSEs
    tasks/<i>-<task>/  the fitter's checkpoint while task i trains (removed when it is done)
    fit.pt             state after the last finished task (model, method, RNG)
    metrics.json       BWT, FWT and the standard metrics of the score curves; track: offline
"""

from __future__ import annotations

from pathlib import Path

import torch

from ccfit.data import dataset_meta
from ccfit.io import seed_everything
from ccfit.models.base import WorldModel
from ccfit.offline.config import OfflineConfig
from ccfit.offline.data import dataset_source, load_task, make_splits, write_split
from ccfit.offline.fit import SCORE_KEY, TRACK, OfflineLogger, TaskFitter
from ccfit.run_files import CHECKPOINT, CONFIG, METRICS_JSON, OFFLINE_STATE, run_name
from ccfit.runner import CurriculumRunner, Restored, Track
from ccfit.runner import restore as restore_run
from ccfit.settings import Execution, resolve_execution
from ccfit.train.run import check_saved_config, encoder_record, load_model, render_settings

STATE = OFFLINE_STATE
STATE_KIND = "ccfit-offline"
STATE_VERSION = 1


def default_out(cfg: OfflineConfig) -> Path:
    """Where an offline run goes without --out: a name made from its config."""
    return Path("runs") / run_name(cfg, track=TRACK)


def resolved_config(cfg: OfflineConfig, source: str, execution: Execution | None = None, *,
                    record_dataset: bool = True) -> dict:  # fmt: skip
    """config.json of an offline run: the config, plus what it resolved to where it runs
    (`execution`: how it executes, None: resolved here from `cfg.fit`; `record_dataset`: as
    for an online run's)."""
    meta = dataset_meta(source, cfg.dataset_endpoint) if record_dataset else None
    execution = execution or resolve_execution(cfg.fit)
    return {
        **cfg.to_dict(),
        "track": TRACK,
        "resolved_dataset": source,
        "resolved_dataset_meta": meta,
        **execution.records(),
        "measurement_space": cfg.measurement_space,
        "render": render_settings(cfg).to_dict(),
        **encoder_record(cfg),
    }


def _prepare(cfg: OfflineConfig, out: Path, saved: dict, source: str, execution: Execution):
    """Check the dataset and write config.json and split.json (bad input leaves nothing);
    the run's CPU threads set."""
    splits = make_splits(cfg, source)
    out.mkdir(parents=True, exist_ok=True)
    check_saved_config(out, saved)
    write_split(out, splits, source)
    execution.set_threads()
    return splits


class OfflineTrack(Track):
    """Each task's backbone fitted on its dataset episodes by `TaskFitter` (no heads, no
    environment); every task seen so far scored on its held-out windows."""

    name = TRACK
    loop = "fit"
    state_file, state_kind, state_version = STATE, STATE_KIND, STATE_VERSION
    score_key = SCORE_KEY
    config_class = OfflineConfig

    def __init__(self, cfg: OfflineConfig) -> None:
        super().__init__(cfg)
        self.logger = None

    @property
    def budget(self) -> int:
        return self.cfg.fit.updates

    def resolved_config(self, *, record_dataset: bool = True) -> dict:
        return resolved_config(self.cfg, dataset_source(self.cfg), self.execution,
                               record_dataset=record_dataset)  # fmt: skip

    def begin(self, out: Path, progress: bool) -> dict:
        self.out, self.progress = out, progress
        self.source = dataset_source(self.cfg)
        resolved = resolved_config(self.cfg, self.source, self.execution)
        self.splits = _prepare(self.cfg, out, resolved, self.source, self.execution)
        return resolved

    def build_model(self, device: torch.device, resolved: dict | None) -> WorldModel:
        return load_model(self.cfg, device)

    def open(self, resolved: dict, restored: Restored) -> OfflineLogger:
        cfg, tasks = self.cfg, self.cfg.tasks
        self.model, self.method = restored.model, restored.method
        self.logger = OfflineLogger(self.out, cfg.log, resolved)
        self.scored = {j: load_task(cfg, self.source, self.model, j, self.splits[tasks[j]],
                                    train=False)[1]
                       for j in range(restored.completed)}  # fmt: skip
        return self.logger

    def learn_task(self, index: int, folder: Path, resumed: bool,
                   backbone_optim: dict | None) -> torch.optim.Optimizer:  # fmt: skip
        cfg, tasks = self.cfg, self.cfg.tasks
        buffer, self.scored[index] = load_task(cfg, self.source, self.model, index,
                                               self.splits[tasks[index]])  # fmt: skip
        folder.mkdir(parents=True, exist_ok=True)
        fitter = TaskFitter(
            model=self.model, buffer=buffer, scored=self.scored, fit=cfg.fit, seed=cfg.seed,
            task_ids=tasks, task_index=index, method=self.method, logger=self.logger,
            run_dir=folder, global_offset=index * cfg.fit.updates, progress=self.progress,
            backbone_optim=backbone_optim, execution=self.execution,
        )  # fmt: skip
        fitter.run()
        return fitter.optim

    def close(self) -> None:
        if self.logger is not None:
            self.logger.close()

    def describe(self) -> dict:
        cfg = self.cfg
        return dict(track=TRACK, suite=cfg.suite, model=cfg.model.type, method=cfg.method.type,
                    seed=cfg.seed, obs=cfg.obs, preset=cfg.preset,
                    measurement_space=cfg.measurement_space)  # fmt: skip

    def learn_reference(self, out: Path, progress: bool) -> list[dict]:
        cfg, n, tasks = self.cfg, len(self.cfg.tasks), self.cfg.tasks
        source = dataset_source(cfg)
        # Its config.json also records what the dataset and the encoder held (not part of the
        # key).
        saved = {**self.reference_config(), **encoder_record(cfg),
                 "resolved_dataset_meta": dataset_meta(source, cfg.dataset_endpoint)}  # fmt: skip
        splits = _prepare(cfg, out, saved, source, self.execution)
        seed_everything(cfg.seed)
        model = load_model(cfg, self.execution.device)
        model.begin_task(n - 1, cfg.fit.updates)
        buffer, windows = load_task(cfg, source, model, n - 1, splits[tasks[-1]])
        logger = OfflineLogger(out, cfg.log, saved)
        if not (out / CHECKPOINT).exists():
            logger.keep(lambda r: False)
        try:
            return TaskFitter(
                model=model, buffer=buffer, scored={n - 1: windows}, fit=cfg.fit, seed=cfg.seed,
                task_ids=tasks, task_index=n - 1, method=None, logger=logger, run_dir=out,
                progress=progress, execution=self.execution,
            ).run()  # fmt: skip
        finally:
            logger.close()


class OfflineCurriculum(CurriculumRunner):
    """Fits (or resumes) one offline run into `out` (`OfflineTrack`)."""

    def __init__(self, cfg: OfflineConfig, out: str | Path, scratch_root: str | Path | None = None,
                 progress: bool = True) -> None:  # fmt: skip
        super().__init__(OfflineTrack(cfg), out, scratch_root, progress)


def restore(cfg: OfflineConfig, run_dir: Path, device: torch.device) -> Restored:
    """The saved state of `run_dir` (`ccfit.runner.restore`)."""
    return restore_run(OfflineTrack(cfg), run_dir, device)


__all__ = [
    "CONFIG",
    "METRICS_JSON",
    "STATE",
    "OfflineCurriculum",
    "OfflineTrack",
    "default_out",
    "restore",
]
