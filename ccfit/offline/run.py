"""A suite's curriculum fitted offline: the backbone on each task's dataset episodes in order,
every task seen so far scored on its held-out episodes at a fixed interval of updates.

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

import fcntl
import hashlib
import json
import shutil
from pathlib import Path

import torch

from ccfit import metrics as M
from ccfit.config_base import ENCODER_RECORD, identity, resolve_device, without_setting
from ccfit.continual.base import ContinualMethod, make_method
from ccfit.curriculum import METRICS_JSON, REFERENCE_DONE
from ccfit.data import dataset_meta
from ccfit.io import (
    atomic_torch_save,
    atomic_write_json,
    load_checkpoint,
    rng_state,
    seed_everything,
    set_rng_state,
)
from ccfit.models.base import WorldModel
from ccfit.offline.config import OfflineConfig
from ccfit.offline.data import dataset_source, load_task, make_splits, write_split
from ccfit.offline.fit import SCORE_KEY, TRACK, OfflineLogger, TaskFitter
from ccfit.train.cost import RunCost
from ccfit.train.run import (
    CONFIG,
    check_same_encoder,
    check_saved_config,
    encoder_record,
    load_model,
    render_settings,
)
from ccfit.train.update import backbone_optimizer_state

STATE = "fit.pt"
STATE_KIND = "ccfit-offline"
STATE_VERSION = 1


def default_out(cfg: OfflineConfig) -> Path:
    """Where an offline run goes without --out: a name made from its config."""
    return Path("runs") / (f"{cfg.suite}-{cfg.model.type}-{cfg.method.type}-{cfg.obs}-"
                           f"{cfg.preset}-s{cfg.seed}-{TRACK}")  # fmt: skip


def resolved_config(cfg: OfflineConfig, source: str, *, record_dataset: bool = True) -> dict:
    """config.json of an offline run: the config, plus what it resolved to where it runs
    (`record_dataset`: as for an online run's)."""
    meta = dataset_meta(source, cfg.dataset_endpoint) if record_dataset else None
    return {
        **cfg.to_dict(),
        "track": TRACK,
        "resolved_dataset": source,
        "resolved_dataset_meta": meta,
        "resolved_device": str(resolve_device(cfg.fit.device)),
        "measurement_space": cfg.measurement_space,
        "render": render_settings(cfg).to_dict(),
        **encoder_record(cfg),
    }


def scratch_config(cfg: OfflineConfig, source: str) -> dict:
    """config.json of the from-scratch reference: the run's, less the method and `out`."""
    resolved = identity(resolved_config(cfg, source, record_dataset=False))
    # A single task has no optimiser state to carry over.
    resolved = without_setting(resolved, "fit.keep_backbone_optimizer")
    return {k: v for k, v in resolved.items() if k not in ("method", "out")}


def scratch_key(cfg: OfflineConfig) -> str:
    """Runs with equal keys share one from-scratch reference (all but method and out)."""
    text = json.dumps(scratch_config(cfg, dataset_source(cfg)), sort_keys=True)
    digest = hashlib.sha1(text.encode()).hexdigest()
    return (f"{TRACK}-{cfg.suite}-{cfg.model.type}-{cfg.obs}-{cfg.preset}-s{cfg.seed}-"
            f"{digest[:8]}")  # fmt: skip


def _prepare(cfg: OfflineConfig, out: Path, saved: dict, source: str):
    """Check the dataset and write config.json and split.json (bad input leaves nothing)."""
    splits = make_splits(cfg, source)
    out.mkdir(parents=True, exist_ok=True)
    check_saved_config(out, saved)
    write_split(out, splits, source)
    if cfg.fit.torch_threads > 0:
        torch.set_num_threads(cfg.fit.torch_threads)
    return splits


def run_scratch(cfg: OfflineConfig, out: Path, progress: bool = True) -> list[dict]:
    """The composition task fitted from scratch with the per-task budget and no method; shared
    by every method's run (a file lock: the first fits it, the others read its records)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f".{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            # A finished reference made through another encoder file is refused.
            if (out / REFERENCE_DONE).is_file():
                check_same_encoder(out, cfg.encoder, encoder_record(cfg).get(ENCODER_RECORD))
                return json.loads((out / REFERENCE_DONE).read_text())
            source = dataset_source(cfg)
            # Its config.json also records what the dataset and the encoder held (not part of
            # the key).
            meta = dataset_meta(source, cfg.dataset_endpoint)
            saved = {**scratch_config(cfg, source), **encoder_record(cfg),
                     "resolved_dataset_meta": meta}  # fmt: skip
            splits = _prepare(cfg, out, saved, source)
            n, tasks = len(cfg.tasks), cfg.tasks
            seed_everything(cfg.seed)
            model = load_model(cfg, resolve_device(cfg.fit.device))
            model.begin_task(n - 1, cfg.fit.updates)
            buffer, windows = load_task(cfg, source, model, n - 1, splits[tasks[-1]])
            logger = OfflineLogger(out, cfg.log, saved)
            if not (out / "checkpoint.pt").exists():
                logger.keep(lambda r: False)
            try:
                records = TaskFitter(
                    model=model, buffer=buffer, scored={n - 1: windows}, fit=cfg.fit,
                    seed=cfg.seed, task_ids=tasks, task_index=n - 1, method=None,
                    logger=logger, run_dir=out, progress=progress,
                ).run()  # fmt: skip
            finally:
                logger.close()
            atomic_write_json(out / REFERENCE_DONE, records)
            (out / "checkpoint.pt").unlink(missing_ok=True)
            return records
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


class OfflineCurriculum:
    """Fits (or resumes) one offline run into `out`."""

    def __init__(self, cfg: OfflineConfig, out: str | Path, scratch_root: str | Path | None = None,
                 progress: bool = True) -> None:  # fmt: skip
        self.cfg, self.out, self.progress = cfg, Path(out), progress
        self.scratch_root = Path(scratch_root) if scratch_root else self.out.parent / "scratch"
        self.device = resolve_device(cfg.fit.device)

    def run(self) -> dict:
        """The offline curriculum to its end (resuming what `out` holds); what this call cost
        is added to `out/cost.json` (the from-scratch reference's included when it ran here,
        as online)."""
        with RunCost(self.out):
            return self._run()

    def _run(self) -> dict:
        cfg, fit, tasks = self.cfg, self.cfg.fit, self.cfg.tasks
        source = dataset_source(cfg)
        resolved = resolved_config(cfg, source)
        splits = _prepare(cfg, self.out, resolved, source)
        model, method, completed, carried = restore(cfg, self.out, self.device)
        logger = OfflineLogger(self.out, cfg.log, resolved)
        scored = {j: load_task(cfg, source, model, j, splits[tasks[j]], train=False)[1]
                  for j in range(completed)}  # fmt: skip
        try:
            for i in range(completed, len(tasks)):
                task_dir = self.out / "tasks" / f"{i}-{tasks[i]}"
                if not (task_dir / "checkpoint.pt").exists():  # a killed stage's records
                    logger.keep(lambda r, i=i: r["stage"] < i)
                model.begin_task(i, fit.updates)
                method.before_task(i, model.backbone)
                buffer, scored[i] = load_task(cfg, source, model, i, splits[tasks[i]])
                task_dir.mkdir(parents=True, exist_ok=True)
                fitter = TaskFitter(
                    model=model, buffer=buffer, scored=scored, fit=fit, seed=cfg.seed,
                    task_ids=tasks, task_index=i, method=method, logger=logger,
                    run_dir=task_dir, global_offset=i * fit.updates, progress=self.progress,
                    backbone_optim=carried,
                )  # fmt: skip
                fitter.run()
                if fit.keep_backbone_optimizer:
                    carried = backbone_optimizer_state(fitter.optim, model.backbone)
                del buffer, fitter
                self._save(i + 1, model, method, carried)
                shutil.rmtree(task_dir, ignore_errors=True)
        finally:
            logger.close()
        scratch_dir = (self.scratch_root / scratch_key(cfg)).resolve()
        scratch = run_scratch(cfg, scratch_dir, self.progress)
        result = M.compute_metrics(logger.read_evals(), scratch, len(tasks), fit.updates,
                                   key=SCORE_KEY)  # fmt: skip
        result.update(track=TRACK, suite=cfg.suite, model=cfg.model.type,
                      method=cfg.method.type, seed=cfg.seed, obs=cfg.obs, preset=cfg.preset,
                      measurement_space=cfg.measurement_space,
                      scratch_dir=str(scratch_dir))  # fmt: skip
        atomic_write_json(self.out / METRICS_JSON, result)
        return result

    def _save(self, completed: int, model: WorldModel, method: ContinualMethod,
              backbone_optim: dict | None) -> None:  # fmt: skip
        atomic_torch_save({"kind": STATE_KIND, "version": STATE_VERSION, "completed": completed,
                           "model": model.state_dict(), "method": method.state_dict(),
                           "backbone_optim": backbone_optim,
                           "rng": rng_state()}, self.out / STATE)  # fmt: skip


def restore(cfg: OfflineConfig, run_dir: Path, device: torch.device
            ) -> tuple[WorldModel, ContinualMethod, int, dict | None]:  # fmt: skip
    """Model, method, finished task count and the optimiser state the next task starts from
    (None: fresh) of `run_dir` (fresh when it has no state yet); global RNGs seeded, or
    restored from the saved state."""
    seed_everything(cfg.seed)
    model = load_model(cfg, device)
    method = make_method(cfg.method, len(cfg.tasks), cfg.seed)
    path = Path(run_dir) / STATE
    if not path.exists():
        return model, method, 0, None
    state = load_checkpoint(path, STATE_KIND, STATE_VERSION)
    model.load_state_dict(state["model"])
    method.load_state_dict(state["method"])
    set_rng_state(state["rng"])
    return model, method, int(state["completed"]), state.get("backbone_optim")


__all__ = [
    "CONFIG",
    "METRICS_JSON",
    "STATE",
    "OfflineCurriculum",
    "default_out",
    "restore",
    "run_scratch",
    "scratch_key",
]
