"""Running a sweep's unfinished work: a local process pool, or SLURM arrays through submitit.

Jobs are named `scratch:<key>`, `first:<key>`, `run:<name>` and `report`. Both launchers take
the same plan (`plan_work`): the references not yet trained, with `--share-first-task` the
shared first tasks that runs not yet begun will start from (`ccfit.first_task`), the runs
without metrics.json, and a report.

Local: at most `max_parallel` jobs at once in spawned processes (one each, so every job starts
clean); a run starts only once its reference (and its shared first task) is done; the report
runs last. States are kept in sweep.json as they change, so `--status` can read them from
another shell.

SLURM: the references and the shared first tasks as arrays, the runs as an array that waits
for them (`afterany`: with `afterok` a failed reference would leave the runs pending forever;
each run checks that its reference exists, and trains a missing first task itself), and a
report job after all. Submitting returns at once. Jobs already queued or running from an
earlier submission are not submitted again; new jobs wait for them where they need them.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, field
from datetime import UTC, datetime

from ccdata.errors import InputError
from ccdata.processes import one_line, worker_pool
from ccdata.slurm import SlurmSettings, active_jobs, check_array_size, submitting
from ccfit.run_files import ONLINE, SCRATCH
from ccfit.sweep.grid import RunSpec, Sweep, write_record
from ccfit.sweep.jobs import (
    FirstTaskJob,
    ReportJob,
    RunJob,
    ScratchJob,
    report_current,
    saved_states,
)


@dataclass
class Work:
    """What a launch submits."""

    scratch: list[str] = field(default_factory=list)
    """Scratch keys to train."""
    first: dict[str, dict] = field(default_factory=dict)
    """Shared first tasks to train: scratch key -> the config of a run that starts from it."""
    runs: list[RunSpec] = field(default_factory=list)
    """Runs to train or resume."""
    report: bool = False
    """Whether a report job runs after them."""
    finished: int = 0
    """Runs skipped because their metrics.json exists."""
    active: dict[str, str] = field(default_factory=dict)
    """Jobs of earlier submissions still queued or running (name -> job id): not resubmitted."""

    @property
    def empty(self) -> bool:
        return not (self.scratch or self.first or self.runs or self.report)


def starts_from_shared_first_task(sweep: Sweep, run: RunSpec) -> bool:
    """Whether `run`, sharing first tasks, will start from its seed's: an online run of a
    method that shares it, not begun (the run decides the same:
    `OnlineTrack._starts_from_shared_first_task`)."""
    from ccfit.continual.base import METHODS

    config = run.config
    return (sweep.grid.track == ONLINE and METHODS[config["method"]["type"]].shares_first_task
            and config["train"].get("stop_score") is None
            and not saved_states(sweep.run_dir(run)))  # fmt: skip


def plan_work(sweep: Sweep, active: dict[str, str], share_first_task: bool = False) -> Work:
    """The unfinished work of `sweep`, leaving out what the jobs in `active` are doing;
    `share_first_task`: runs start from their seed's shared first task (`ccfit.first_task`)."""
    work = Work(active=dict(active))
    for run in sweep.runs:
        if sweep.run_done(run):
            work.finished += 1
        elif f"run:{run.name}" not in active:
            work.runs.append(run)
    keys = dict.fromkeys(r.scratch_key for r in work.runs)
    work.scratch = [k for k in keys if not sweep.scratch_done(k) and f"scratch:{k}" not in active]
    if share_first_task:
        for run in work.runs:
            key = run.scratch_key
            if (key not in work.first and not sweep.first_done(key)
                    and f"first:{key}" not in active
                    and starts_from_shared_first_task(sweep, run)):  # fmt: skip
                work.first[key] = run.config
    work.report = bool(work.scratch or work.runs) or (
        "report" not in active and not active and not report_current(sweep)
    )
    return work


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


# ================================================================================== local


@contextlib.contextmanager
def sweep_lock(sweep: Sweep):
    """One local launcher per sweep folder at a time."""
    sweep.root.mkdir(parents=True, exist_ok=True)
    with open(sweep.root / ".sweep.lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(f"another `ccfit sweep` is running in {sweep.root}") from None
        yield


def launch_local(sweep: Sweep, work: Work, submissions: list[dict], max_parallel: int,
                 threads: int | None = None, run_job: RunJob | None = None) -> None:  # fmt: skip
    """Run `work` here, at most `max_parallel` jobs at once, then the sweep's report.
    run_job: the job each run is (its options: `RunJob`; None: the default)."""
    run_job = run_job or RunJob()
    entry = {"launcher": "local", "time": _now(), "code": sweep.code, "pid": os.getpid(),
             "jobs": {}}  # fmt: skip
    submissions.append(entry)
    jobs: dict[str, dict] = entry["jobs"]
    plugins, code = list(sweep.grid.plugins), sweep.code

    def alone(config: dict) -> dict:
        # Jobs side by side already fill the cores: none spawns workers of its own
        # (`train.parallel` and `train.env_workers` change how a run spreads over processes,
        # not what it computes).
        if max_parallel < 2 or "train" not in config:  # an offline run spawns nothing
            return config
        return {**config, "train": {**config.get("train", {}), "parallel": "off",
                                    "env_workers": "0"}}  # fmt: skip

    def scratch_call(key: str) -> tuple:
        return (ScratchJob(), alone(sweep.scratch_configs()[key]), str(sweep.scratch_dir(key)),
                plugins, code, threads)  # fmt: skip

    def first_call(key: str) -> tuple:
        return (FirstTaskJob(), alone(work.first[key]), str(sweep.first_dir(key)), plugins,
                code, threads)  # fmt: skip

    # In the grid's (seed-major) order, each shared first task and reference just before the
    # first run that needs it: the pool starts jobs in this order as they become ready, so a
    # seed's runs go before the next seed's reference and a partly run sweep holds whole seeds.
    calls: dict[str, tuple] = {}
    waiting_on: dict[str, list[str]] = {}
    for run in work.runs:
        name, key = f"run:{run.name}", run.scratch_key
        waiting_on[name] = []
        # A run already begun needs no shared first task, only its reference.
        starts = key in work.first and starts_from_shared_first_task(sweep, run)
        for kind, needed, call in (("first", starts, first_call),
                                   ("scratch", key in work.scratch, scratch_call)):  # fmt: skip
            if needed:
                calls.setdefault(f"{kind}:{key}", call(key))
                waiting_on[name].append(f"{kind}:{key}")
        calls[name] = (run_job, alone(run.config), str(sweep.run_dir(run)),
                       str(sweep.root / SCRATCH), key, plugins, code, threads)  # fmt: skip
    for name in calls:
        jobs[name] = {"state": "PENDING"}
    errors: dict[str, str] = {}
    log_dir = sweep.root / "local"
    total, ended = len(calls), 0
    write_record(sweep, submissions)

    def ready() -> list[str]:
        done = {n for n, j in jobs.items() if j["state"] == "COMPLETED"}
        return [n for n, j in jobs.items()
                if j["state"] == "PENDING" and done.issuperset(waiting_on.get(n, []))]  # fmt: skip

    pool = worker_pool(max_parallel, max_tasks_per_child=1)
    running: dict = {}
    try:
        while True:
            for name in ready()[: max_parallel - len(running)]:
                fn, *args = calls[name]
                running[pool.submit(fn, *args)] = name
                jobs[name].update(state="RUNNING", start=_now())
            for name, j in jobs.items():  # a failed reference or first task fails its runs
                failed = [d for d in waiting_on.get(name, ()) if jobs[d]["state"] == "FAILED"]
                if j["state"] == "PENDING" and failed:
                    kind = failed[0].split(":")[0]
                    what = {"scratch": "its reference", "first": "its shared first task"}[kind]
                    j.update(state="FAILED", error=f"{what} {failed[0]} failed")
                    errors[name.split(":", 1)[1]] = j["error"]
                    ended += 1
                    print(f"[{ended}/{total}] failed {name}: {j['error']}", flush=True)
            write_record(sweep, submissions)
            if not running:
                break
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                name = running.pop(future)
                j = jobs[name]
                ended += 1
                j["end"] = _now()
                exc = future.exception()
                if exc is None:
                    j["state"] = "COMPLETED"
                    print(f"[{ended}/{total}] done {name}", flush=True)
                    continue
                j.update(state="FAILED", error=one_line(exc))
                errors[name.split(":", 1)[1]] = j["error"]
                log = log_dir / (name.replace(":", "-") + ".err")
                log.parent.mkdir(parents=True, exist_ok=True)
                log.write_text("".join(traceback.format_exception(exc)))
                print(f"[{ended}/{total}] failed {name}: {j['error']} (traceback: {log})",
                      flush=True)  # fmt: skip
    except BaseException:
        for j in jobs.values():
            if j["state"] in ("PENDING", "RUNNING"):
                j["state"] = "INTERRUPTED"
        write_record(sweep, submissions)
        pool.kill_workers()  # each interrupted job resumes from its last checkpoint
        raise
    pool.shutdown()
    jobs["report"] = {"state": "RUNNING", "start": _now()}
    write_record(sweep, submissions)
    ReportJob()(str(sweep.root), plugins, code, errors)
    jobs["report"].update(state="COMPLETED", end=_now())
    write_record(sweep, submissions)


# ================================================================================== SLURM


def launch_slurm(sweep: Sweep, work: Work, submissions: list[dict], settings: SlurmSettings,
                 run_job: RunJob | None = None) -> dict:  # fmt: skip
    """Submit `work` as SLURM jobs and return at once; returns the submission entry.
    run_job: the job each run is (its options: `RunJob`; None: the default)."""
    run_job = run_job or RunJob()
    arrays = ((work.scratch, "from-scratch references"), (work.first, "shared first tasks"),
              (work.runs, "runs"))  # fmt: skip
    for items, what in arrays:
        check_array_size(len(items), f"{len(items)} {what} to submit")
    folder = sweep.root / "slurm"
    folder.mkdir(parents=True, exist_ok=True)
    entry = {"launcher": "slurm", "time": _now(), "code": sweep.code, "folder": "slurm",
             "jobs": {}}  # fmt: skip
    submissions.append(entry)
    jobs: dict[str, str] = entry["jobs"]
    plugins, code = list(sweep.grid.plugins), sweep.code
    executor = settings.executor(folder, f"ccfit-sweep-{code.get('git') or code.get('package')}")

    def after(ids: list[str]) -> str | None:
        return "afterany:" + ":".join(sorted(set(ids))) if ids else None

    try:
        with submitting():
            scratch_ids = {
                k: work.active[f"scratch:{k}"]
                for k in {r.scratch_key for r in work.runs}
                if f"scratch:{k}" in work.active
            }
            if work.scratch:
                executor.update_parameters(job_name="ccfit-scratch", dependency=None)
                configs = sweep.scratch_configs()
                n = len(work.scratch)
                submitted = executor.map_array(
                    ScratchJob(), [configs[k] for k in work.scratch],
                    [str(sweep.scratch_dir(k)) for k in work.scratch],
                    [plugins] * n, [code] * n, [None] * n)  # fmt: skip
                for key, job in zip(work.scratch, submitted, strict=True):
                    scratch_ids[key] = jobs[f"scratch:{key}"] = job.job_id
                write_record(sweep, submissions)
            first_ids = {k: work.active[f"first:{k}"] for k in {r.scratch_key for r in work.runs}
                         if f"first:{k}" in work.active}  # fmt: skip
            if work.first:
                executor.update_parameters(job_name="ccfit-first", dependency=None)
                keys = list(work.first)
                n = len(keys)
                submitted = executor.map_array(
                    FirstTaskJob(), [work.first[k] for k in keys],
                    [str(sweep.first_dir(k)) for k in keys], [plugins] * n, [code] * n,
                    [None] * n)  # fmt: skip
                for key, job in zip(keys, submitted, strict=True):
                    first_ids[key] = jobs[f"first:{key}"] = job.job_id
                write_record(sweep, submissions)
            if work.runs:
                needed = [ids[r.scratch_key] for r in work.runs for ids in (scratch_ids, first_ids)
                          if r.scratch_key in ids]  # fmt: skip
                executor.update_parameters(job_name="ccfit-run", dependency=after(needed))
                n = len(work.runs)
                submitted = executor.map_array(
                    run_job,
                    [r.config for r in work.runs],
                    [str(sweep.run_dir(r)) for r in work.runs],
                    [str(sweep.root / SCRATCH)] * n,
                    [r.scratch_key for r in work.runs],
                    [plugins] * n,
                    [code] * n,
                    [None] * n,
                )
                for run, job in zip(work.runs, submitted, strict=True):
                    jobs[f"run:{run.name}"] = job.job_id
                write_record(sweep, submissions)
            if work.report:
                before = [j.split("_")[0] for j in jobs.values()] + list(work.active.values())
                executor.update_parameters(job_name="ccfit-report", time=settings.report_minutes,
                                           cpus_per_task=1, gpus_per_node=None,
                                           dependency=after(before))  # fmt: skip
                jobs["report"] = executor.submit(ReportJob(), str(sweep.root), plugins,
                                                 code, None).job_id  # fmt: skip
    finally:  # the jobs submitted so far, also when sbatch refused one
        write_record(sweep, submissions)
    return entry


def slurm_active(submissions: list[dict]) -> dict[str, str]:
    """Jobs of earlier SLURM submissions still queued or running: name -> job id."""
    from ccfit.sweep.status import latest_jobs

    latest = {name: job for name, (entry, job) in latest_jobs(submissions).items()
              if entry["launcher"] == "slurm"}  # fmt: skip
    alive = active_jobs(list(latest.values())) if latest else set()
    return {name: job for name, job in latest.items() if job in alive}


def wait_report(entry: dict, timeout_s: float) -> None:
    """Block until the report job of a SLURM submission left the queue (tests, `--wait`)."""
    job = entry["jobs"].get("report")
    deadline = time.monotonic() + timeout_s
    while job and active_jobs([job]):
        if time.monotonic() > deadline:
            raise TimeoutError(f"report job {job} still queued after {timeout_s} s")
        time.sleep(2)
