"""SLURM settings of a sweep, and asking the cluster: is it there, what is queued, job states.

submitit follows jobs through sacct (without accounting a cancelled job never reports done), so
a sweep needs both the controller (sinfo, squeue) and accounting (sacct).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ccdata.errors import InputError

PROBE_TIMEOUT_S = 30
MIN_TIME_MIN = 30
"""Below ~10 minutes submitit takes a preemption signal for a timeout (and does not requeue);
30 leaves a margin."""


def parse_time(text: str) -> int:
    """A SLURM time limit (`M`, `M:S`, `H:M:S`, `D-H`, `D-H:M`, `D-H:M:S`) in whole minutes,
    rounded up."""
    m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text.strip())
    if not m:
        raise InputError(f"--time {text!r}: expected minutes or [D-]H:M:S")
    days, a, b, c = (int(g) if g is not None else None for g in m.groups())
    if days is not None:  # D-H[:M[:S]]
        seconds = ((days * 24 + a) * 60 + (b or 0)) * 60 + (c or 0)
    elif c is not None:  # H:M:S
        seconds = (a * 60 + b) * 60 + c
    else:  # M or M:S
        seconds = a * 60 + (b or 0)
    return -(-seconds // 60)


@dataclass
class SlurmSettings:
    """How every job of a sweep is submitted. Validated on construction."""

    partition: str | None = None
    """Partition (None: the cluster's default)."""
    account: str | None = None
    """Account charged (None: the user's default)."""
    qos: str | None = None
    """Quality of service (None: the default)."""
    time_min: int = 24 * 60
    """Time limit of every run and reference job, in minutes; a job that reaches it is
    requeued and resumes from its last checkpoint (up to 3 times)."""
    gpus_per_job: int = 0
    """GPUs per run and reference job."""
    cpus_per_job: int = 1
    """CPUs per run and reference job. torch uses as many threads when the config's
    `train.torch_threads` is 0; a positive value there wins."""
    mem: str | None = None
    """Memory per job in SLURM's notation (`16G`, `500M`; None: the partition's default)."""
    setup: list[str] = field(default_factory=list)
    """Shell lines each job runs before Python (`module load ...`, `source venv/bin/activate`,
    `export MUJOCO_EGL_DEVICE_ID=...`)."""
    max_parallel: int | None = None
    """At most this many array tasks of a sweep at once (None: the cluster decides)."""
    report_minutes: int = MIN_TIME_MIN
    """Time limit of the report job."""

    def __post_init__(self) -> None:
        if self.time_min < MIN_TIME_MIN:
            raise InputError(f"--time must be at least {MIN_TIME_MIN} minutes (shorter limits "
                             f"break requeueing on preemption), got {self.time_min}")
        for name in ("cpus_per_job", "gpus_per_job"):
            low = 1 if name == "cpus_per_job" else 0
            if getattr(self, name) < low:
                raise InputError(f"--{name.replace('_', '-')} must be >= {low}")
        if self.max_parallel is not None and self.max_parallel < 1:
            raise InputError(f"--max-parallel must be >= 1, got {self.max_parallel}")
        if self.mem is not None and not re.fullmatch(r"\d+[KMGT]?", self.mem):
            raise InputError(f"--mem {self.mem!r}: expected a number with K, M, G or T")

    def executor_parameters(self) -> dict:
        """`submitit.SlurmExecutor.update_parameters` arguments of the run and reference jobs."""
        params = dict(time=self.time_min, partition=self.partition, account=self.account,
                      qos=self.qos, cpus_per_task=self.cpus_per_job, mem=self.mem,
                      gpus_per_node=self.gpus_per_job or None, setup=list(self.setup))
        if self.max_parallel is not None:
            params["array_parallelism"] = self.max_parallel
        return {k: v for k, v in params.items() if v is not None}


def _probe(command: list[str]) -> str | None:
    """None when `command` succeeds, else why not (its last line of error output)."""
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
    except FileNotFoundError:
        return f"{command[0]} is not on PATH"
    except subprocess.TimeoutExpired:
        return f"{command[0]} did not answer in {PROBE_TIMEOUT_S} s"
    if done.returncode == 0:
        return None
    lines = (done.stderr or done.stdout).strip().splitlines()
    return lines[-1] if lines else f"{command[0]} exited with {done.returncode}"


def check_slurm() -> None:
    """Raise `InputError` unless a SLURM controller answers and so does its accounting."""
    if shutil.which("sbatch") is None:
        raise InputError("no SLURM reachable: sbatch is not on PATH (use --launcher local)")
    why = _probe(["sinfo", "-h", "-o", "%P"])
    if why:
        raise InputError(f"no SLURM reachable: {why}")
    why = _probe(["sacct", "-n", "-X", "-S", "now", "-o", "JobID"])
    if why:
        raise InputError(f"sacct not available ({why}): submitit follows jobs through SLURM "
                         f"accounting")  # fmt: skip


def active_jobs(job_ids: list[str]) -> set[str]:
    """Those of `job_ids` (jobs or array tasks `A_i`) the controller still has queued or
    running (squeue; a finished job is no longer listed)."""
    active = set()
    for job in dict.fromkeys(job_ids):
        done = subprocess.run(["squeue", "-h", "-r", "-o", "%i", "-j", job], capture_output=True,
                              text=True, timeout=PROBE_TIMEOUT_S)  # fmt: skip
        if done.returncode == 0 and done.stdout.split():  # unknown ids are errors: not active
            active.add(job)
    return active


def job_states(folder: Path, job_ids: list[str]) -> dict[str, str]:
    """sacct's state of each job (through submitit's watcher: one sacct call for all)."""
    import submitit

    jobs = {j: submitit.SlurmJob(folder=folder / "%j", job_id=j) for j in dict.fromkeys(job_ids)}
    return {j: job.state.split()[0] if job.state else "UNKNOWN" for j, job in jobs.items()}
