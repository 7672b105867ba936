"""The sweep's jobs: the same callables run in the local process pool and on SLURM.

Each is a module-level `submitit.helpers.Checkpointable` with plain-data arguments (a config as
`CurriculumConfig.to_dict()`, paths as strings), so it pickles anywhere. A job is idempotent:
it resumes from its directory (the trainer's checkpoints, written every
`train.checkpoint_interval` steps and every `train.checkpoint_minutes` of wall clock) and never
from pickled state, and its seed is the config's, never an array index. On preemption or a
time limit submitit calls `checkpoint()`, which resubmits the same call: the requeued job
resumes from the last checkpoint on disk.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from datetime import UTC, datetime
from pathlib import Path

import submitit

from ccdata.errors import InputError
from ccdata.slurm import code_version
from ccfit.first_task import FIRST
from ccfit.io import atomic_write_json
from ccfit.run_files import (
    CHECKPOINT,
    CONFIG,
    METRICS_JSON,
    OFFLINE_STATE,
    ONLINE_STATE,
    REFERENCE_DONE,
    REPORT,
)
from ccfit.sweep.grid import (
    STATUS_JSON,
    Sweep,
    import_plugins,
    load_sweep,
)


class ScratchMissing(RuntimeError):
    """A run started before its from-scratch reference exists (its job failed)."""


def config_from_dict(d: dict):
    """A `CurriculumConfig` (or, for an offline run, an `OfflineConfig`) from its plain data
    (config.json or sweep.json), ignoring keys that are not config fields
    (`resolved_seed_dataset`)."""
    from ccfit.config_parse import resolve
    from ccfit.tracks import track_of

    cls = track_of(d).config_class
    names = {f.name for f in dataclasses.fields(cls)}
    return resolve(cls, {k: v for k, v in d.items() if k in names})


def job_start(what: str, plugins: list[str], code: dict, threads: int | None) -> None:
    """What every job does first: register plugins, size torch's thread pool (a positive
    `train.torch_threads` in the config wins later), and say which code runs."""
    import torch

    import_plugins(plugins)
    threads = threads or int(os.environ.get("SLURM_CPUS_PER_TASK", "0") or 0)
    if threads > 0:
        torch.set_num_threads(threads)
    running = code_version()
    print(f"ccfit sweep: {what} (code {running['git'] or running['package']})", flush=True)
    if (running["git"], running["package"]) != (code.get("git"), code.get("package")):
        print(f"ccfit sweep: warning: the code changed since submission ({code.get('git')} -> "
              f"{running['git']})", file=sys.stderr, flush=True)  # fmt: skip


def check_key(key: str, submitted: str) -> None:
    """A job's from-scratch key as computed where it runs must be the one it was submitted
    with (it differs where e.g. seed_dataset 'auto' found another dataset here)."""
    if key != submitted:
        raise RuntimeError(f"the run's from-scratch key is {key} here but was {submitted} at "
                           f"submission: run the sweep again")  # fmt: skip


class _Job(submitit.helpers.Checkpointable):
    def checkpoint(self, *args, **kwargs) -> submitit.helpers.DelayedSubmission:
        """Preempted or timed out: requeue the same call; it resumes from its directory."""
        print("ccfit sweep: requeued; the job resumes from its last checkpoint", flush=True)
        return submitit.helpers.DelayedSubmission(self, *args, **kwargs)


class ScratchJob(_Job):
    """Train one from-scratch reference (the composition task with the per-task budget)."""

    def __call__(self, config: dict, scratch_dir: str, plugins: list[str], code: dict,
                 threads: int | None = None) -> dict:  # fmt: skip
        from ccfit.runner import run_reference
        from ccfit.tracks import track_of
        from ccfit.train.cost import RunCost

        job_start(f"scratch reference {scratch_dir}", plugins, code, threads)
        # Trained here, the reference has a cost of its own; one a curriculum trains counts in
        # the curriculum's cost.json.
        with RunCost(scratch_dir):
            track = track_of(config)(config_from_dict(config))
            evals = run_reference(track, Path(scratch_dir), progress=False)
        return {"scratch_dir": scratch_dir, "evaluations": len(evals)}


class FirstTaskJob(_Job):
    """Train the first task that one seed's runs share (`ccfit.first_task`) into
    RUNS/first/<key>, the key of their from-scratch reference; the runs start when it ended
    (one that finds it missing trains it itself)."""

    def __call__(self, config: dict, first_dir: str, plugins: list[str], code: dict,
                 threads: int | None = None) -> dict:  # fmt: skip
        from ccfit.curriculum import OnlineTrack, train_shared_first_task

        job_start(f"shared first task {first_dir}", plugins, code, threads)
        cfg = config_from_dict(config)
        check_key(OnlineTrack(cfg).reference_key(), Path(first_dir).name)
        record = train_shared_first_task(cfg, Path(first_dir), trained_by="job")
        return {"first_dir": first_dir, "state_sha256": record["state_sha256"]}


class RunJob(_Job):
    """Train (or resume) one continual run; its from-scratch reference must exist already (on
    SLURM the run's job waits for the reference's with `afterany`, then checks here).
    keep_stages: an online run keeps its state after each task (`ccfit run --keep-stages`);
    share_first_task: it starts from the first task its seed's runs share, in RUNS/first
    (`ccfit.first_task`; trained by a `FirstTaskJob` before the runs start, or by the first
    run that finds it missing while the others wait)."""

    def __init__(self, keep_stages: bool = False, share_first_task: bool = False) -> None:
        self.keep_stages = keep_stages
        self.share_first_task = share_first_task

    def __call__(self, config: dict, run_dir: str, scratch_root: str, scratch_key: str,
                 plugins: list[str], code: dict, threads: int | None = None) -> dict:  # fmt: skip
        from ccfit.analysis import stage_callbacks
        from ccfit.runner import CurriculumRunner
        from ccfit.tracks import track_of

        job_start(f"run {run_dir}", plugins, code, threads)
        metrics = Path(run_dir) / METRICS_JSON
        if metrics.is_file():  # finished by an earlier attempt: nothing to do
            return _summary(json.loads(metrics.read_text()))
        cfg = config_from_dict(config)
        # The analyses its model offers, as `ccfit run` records them (offline: none run).
        first = Path(scratch_root).parent / FIRST if self.share_first_task else None
        track = track_of(config).in_sweep(cfg, self.keep_stages, stage_callbacks(cfg), first)
        check_key(track.reference_key(), scratch_key)
        done = Path(scratch_root) / scratch_key / REFERENCE_DONE
        if not done.is_file():
            raise ScratchMissing(f"from-scratch reference {done.parent} did not finish (see its "
                                 f"job's log); run the sweep again")  # fmt: skip
        print(f"ccfit sweep: {resume_point(Path(run_dir))}", flush=True)
        return _summary(CurriculumRunner(track, run_dir, scratch_root, progress=False).run())


def saved_states(run_dir: Path) -> list[Path]:
    """A run's saved curriculum state (online or offline) and task checkpoints: empty before
    it began."""
    states = [run_dir / ONLINE_STATE, run_dir / OFFLINE_STATE]
    return [p for p in [*states, *sorted(run_dir.glob(f"tasks/*/{CHECKPOINT}"))] if p.is_file()]


def resume_point(run_dir: Path) -> str:
    """Where a run continues from: its saved states (`saved_states`), if any."""
    found = saved_states(run_dir)
    if not found:
        return "starting fresh"
    return "resuming from " + ", ".join(str(p.relative_to(run_dir)) for p in found)


def _summary(result: dict) -> dict:
    return {k: result.get(k) for k in ("suite", "model", "method", "seed", "bwt", "fwt")}


class ReportJob(_Job):
    """After every run ended: `ccfit report` over the finished runs into RUNS/report/, and
    RUNS/report/status.json listing the runs that are done and those missing."""

    def __call__(self, root: str, plugins: list[str], code: dict,
                 errors: dict[str, str] | None = None) -> dict:  # fmt: skip
        job_start(f"report of {root}", plugins, code, None)
        return write_status(root, errors or {})


def write_status(root: str | Path, errors: dict[str, str]) -> dict:
    """Write the report and status.json of the sweep in `root`; print what is missing.
    `errors`: run name -> why its job failed, when the launcher knows it."""
    from ccfit.report import write_report

    sweep, _ = load_sweep(root)
    done = [r.name for r in sweep.runs if sweep.run_done(r)]
    missing = [
        {
            "name": r.name,
            "started": (sweep.run_dir(r) / CONFIG).is_file(),
            "error": errors.get(r.name),
        }
        for r in sweep.runs
        if not sweep.run_done(r)
    ]
    out = sweep.root / REPORT
    files, report_error = [], None
    if done:
        try:
            files = [str(p.relative_to(out)) for p in
                     write_report([sweep.root / n for n in done], out)]  # fmt: skip
        except ValueError as e:  # e.g. a reference went missing: the status still lists runs
            report_error = str(e)
    status = {
        "time": datetime.now(UTC).isoformat(timespec="seconds"),
        "runs": len(sweep.runs),
        "done": done,
        "missing": missing,
        "report": files,
        "report_error": report_error,
    }
    atomic_write_json(out / STATUS_JSON, status)
    print(f"ccfit sweep: {len(done)} of {len(sweep.runs)} runs done; report in {out}")
    for m in missing:
        why = m["error"] or ("started, did not finish" if m["started"] else "never started")
        print(f"  missing {m['name']}: {why}")
    if report_error:
        print(f"  report failed: {report_error}", file=sys.stderr)
    return status


def read_report_status(sweep: Sweep) -> dict | None:
    """The status.json the sweep's last report job wrote (`write_status`), None before any;
    a damaged one is bad input, named."""
    path = sweep.root / REPORT / STATUS_JSON
    if not path.is_file():
        return None
    try:
        status = json.loads(path.read_text())
        if not isinstance(status.get("missing"), list) or not isinstance(status.get("done"), list):
            raise ValueError("no 'done' and 'missing' lists")
    except (json.JSONDecodeError, ValueError, AttributeError) as e:
        raise InputError(f"{path} is not a sweep's report status ({e}); delete it and run the "
                         f"sweep's command again to rewrite it") from None  # fmt: skip
    return status


def report_current(sweep: Sweep) -> bool:
    """The report lists every run as done (nothing for a report job to add)."""
    status = read_report_status(sweep)
    if status is None:
        return False
    return (not status["missing"] and status.get("report_error") is None
            and sorted(status["done"]) == sorted(r.name for r in sweep.runs))  # fmt: skip
