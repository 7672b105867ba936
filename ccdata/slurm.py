"""SLURM plumbing shared by `ccdata generate --launcher slurm` (`ccdata.launch`) and
`ccfit sweep --launcher slurm` (`ccfit.sweep`): the job settings and their command-line
options, the time-limit parser, probes of the cluster (is it there, what is still queued, job
states, MaxArraySize), the code version recorded with jobs, and submitit executors built from
the settings.

A leaf: of ccdata it imports only `ccdata.errors` (and submitit only where jobs are submitted
or followed), so ccfit can use it without pulling in the dataset code.

submitit follows jobs through sacct (without accounting a cancelled job never reports done),
so a launch needs both the controller (sinfo, squeue) and accounting (sacct).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

from ccdata.archived import archived_commit
from ccdata.errors import InputError

PROBE_TIMEOUT_S = 30
"""Seconds a SLURM command may take to answer."""
MAX_REQUEUES = 3
"""Timeouts after which submitit stops requeueing a job (preemptions do not count)."""
REQUEUE_SAFE_MIN = 30
"""Below ~10 minutes submitit takes a preemption signal for a timeout (and does not requeue);
30 leaves a margin. `ccfit sweep` refuses shorter time limits."""
DEFAULT_MAX_ARRAY_SIZE = 1001
"""SLURM's MaxArraySize when the cluster's configuration does not say."""


class LaunchError(InputError):
    """SLURM is not usable here, or a launch setting is wrong: one line for the user."""


def parse_time(text: str) -> int:
    """A SLURM time limit (`M`, `M:S`, `H:M:S`, `D-H`, `D-H:M`, `D-H:M:S`) in whole minutes,
    rounded up."""
    m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text.strip())
    if not m:
        raise LaunchError(f"--time {text!r}: expected minutes or [D-]H:M:S")
    days, a, b, c = (int(g) if g is not None else None for g in m.groups())
    if days is not None:  # D-H[:M[:S]]
        seconds = ((days * 24 + a) * 60 + (b or 0)) * 60 + (c or 0)
    elif c is not None:  # H:M:S
        seconds = (a * 60 + b) * 60 + c
    else:  # M or M:S
        seconds = a * 60 + (b or 0)
    minutes = -(-seconds // 60)
    if minutes < 1:
        raise LaunchError(f"--time {text!r}: must be at least one minute")
    return minutes


# ── Settings ──────────────────────────────────────────────────────────────────────────────


@dataclass
class SlurmSettings:
    """How jobs are submitted; every job of a launch gets the same unless a field says
    otherwise. Validated on construction."""

    partition: str | None = None
    """Partition; None -> the cluster's default."""
    account: str | None = None
    """Account charged; None -> the user's default."""
    qos: str | None = None
    """Quality of service; None -> the default."""
    time_min: int = 60
    """Time limit per job in minutes (submitit's `timeout_min`). A job reaching it is requeued
    (up to `MAX_REQUEUES` times) and resumes from what it wrote. Keep it >= `REQUEUE_SAFE_MIN`
    where jobs may be preempted."""
    cpus_per_job: int = 1
    """CPUs per job (sbatch's `--cpus-per-task`); torch in the job uses as many threads (in a
    sweep unless the run config's `train.torch_threads` is positive)."""
    gpus_per_job: int = 0
    """GPUs per job (one node per job)."""
    mem: str | None = None
    """Memory per job in SLURM's notation (`8G`, `500M`); None -> the partition's default."""
    setup: list[str] = field(default_factory=list)
    """Shell lines run in each job before Python starts (`module load ...`, `source ...`,
    `export MUJOCO_EGL_DEVICE_ID=...`)."""
    max_parallel: int | None = None
    """At most this many tasks of an array at once (sbatch's `--array=...%N`); None -> the
    cluster decides."""
    shards: int = 1
    """`ccdata generate`: array tasks the episodes are split into (contiguous plan ranges)."""
    log_dir: str | Path | None = None
    """`ccdata generate`: submitit folder (logs, pickles) on a filesystem the nodes share;
    None -> beside the dataset. (A sweep's is always RUNS/slurm.)"""
    report_minutes: int = REQUEUE_SAFE_MIN
    """`ccfit sweep`: time limit of the report job (one CPU, no GPU)."""

    def __post_init__(self) -> None:
        lowest = {"--time": (self.time_min, 1), "--cpus-per-job": (self.cpus_per_job, 1),
                  "--gpus-per-job": (self.gpus_per_job, 0), "--shards": (self.shards, 1),
                  "--max-parallel": (self.max_parallel, 1)}  # fmt: skip
        for flag, (value, low) in lowest.items():
            if value is not None and value < low:
                raise LaunchError(f"{flag} must be >= {low}, got {value}")
        if self.mem is not None and not re.fullmatch(r"\d+[KMGT]?", self.mem):
            raise LaunchError(f"--mem {self.mem!r}: expected a number with K, M, G or T")

    def log_folder(self, default: Path) -> Path:
        """Where submitit writes: `log_dir` (made absolute) when given, else `default`."""
        return Path(self.log_dir).expanduser().resolve() if self.log_dir else default

    def executor_parameters(self) -> dict:
        """`submitit.SlurmExecutor.update_parameters` arguments for these settings."""
        params = dict(time=self.time_min, partition=self.partition, account=self.account,
                      qos=self.qos, cpus_per_task=self.cpus_per_job, mem=self.mem,
                      gpus_per_node=self.gpus_per_job or None, setup=list(self.setup),
                      array_parallelism=self.max_parallel)  # fmt: skip
        return {k: v for k, v in params.items() if v is not None}

    def executor(self, folder: Path, comment: str):
        """A `submitit.SlurmExecutor` with these settings: logs and pickles in
        `folder/<job id>/`, jobs requeued on preemption and timeout, `comment` (cut to 200
        characters) shown by squeue and sacct."""
        import submitit

        executor = submitit.SlurmExecutor(folder=folder / "%j", max_num_timeout=MAX_REQUEUES)
        executor.update_parameters(**self.executor_parameters(), comment=comment[:200],
                                   additional_parameters={"requeue": True})  # fmt: skip
        return executor


OPTIONS = ("partition", "account", "qos", "time", "cpus_per_job", "gpus_per_job", "mem", "setup")
"""The argparse destinations `add_options` adds."""


def add_options(group, default_time: str) -> None:
    """Add the SLURM options of every launching command to `group` (an argparse parser or
    argument group); each defaults to None (not given), so a command can tell which were given.
    `default_time`: the command's time limit, for the help."""
    group.add_argument("--partition", help="partition (default: the cluster's default)")
    group.add_argument("--account", help="account charged (default: the user's default)")
    group.add_argument("--qos", help="quality of service (default: the default)")
    group.add_argument("--time", help=f"time limit per job, minutes or [D-]H:M:S "
                                      f"({default_time}); a job reaching it is requeued and "
                                      f"resumes; keep >= {REQUEUE_SAFE_MIN} where jobs may be "
                                      "preempted")  # fmt: skip
    group.add_argument("--cpus-per-job", "--cpus-per-task", type=int, help="CPUs per job (1)")
    group.add_argument("--gpus-per-job", type=int, help="GPUs per job (0)")
    group.add_argument("--mem", help="memory per job, e.g. 8G (default: the partition's)")
    group.add_argument(
        "--setup", action="append", help="shell line run in each job before Python (repeatable)"
    )


def settings_from_options(args: argparse.Namespace, default_time: str,
                          **fields) -> SlurmSettings:  # fmt: skip
    """`SlurmSettings` from the options of `add_options` and the command's own `fields`
    (`shards=...`); what is None keeps its default."""
    given = {name: getattr(args, name) for name in OPTIONS if name != "time"}
    given["time_min"] = parse_time(default_time if args.time is None else args.time)
    return SlurmSettings(**{k: v for k, v in {**given, **fields}.items() if v is not None})


# ── Asking the cluster ────────────────────────────────────────────────────────────────────


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
    """Raise `LaunchError` unless a SLURM controller answers and so does its accounting."""
    if shutil.which("sbatch") is None:
        raise LaunchError("no SLURM reachable: sbatch is not on PATH")
    why = _probe(["sinfo", "-h", "-o", "%P"])
    if why:
        raise LaunchError(f"no SLURM reachable: {why}")
    why = _probe(["sacct", "-n", "-X", "-S", "now", "-o", "JobID"])
    if why:
        raise LaunchError(f"sacct not available ({why}); submitit needs SLURM accounting")


def max_array_size() -> int:
    """The cluster's MaxArraySize: an array holds at most this many tasks."""
    try:
        done = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True,
                              timeout=PROBE_TIMEOUT_S)  # fmt: skip
    except (FileNotFoundError, subprocess.TimeoutExpired):
        return DEFAULT_MAX_ARRAY_SIZE
    found = re.search(r"^MaxArraySize\s*=\s*(\d+)", done.stdout, re.MULTILINE)
    return int(found.group(1)) if found else DEFAULT_MAX_ARRAY_SIZE


def check_array_size(tasks: int, what: str) -> None:
    """Raise `LaunchError` when an array of `tasks` tasks exceeds the cluster's MaxArraySize;
    `what` names the option or count that made it so large."""
    if tasks > (limit := max_array_size()):
        raise LaunchError(
            f"{what}: this cluster takes arrays of at most {limit} tasks (MaxArraySize)"
        )


def active_jobs(job_ids: list[str]) -> list[str]:
    """Those of `job_ids` (jobs, arrays or array tasks `A_i`) the controller still has queued
    or running, in the given order (squeue; a finished job is no longer listed)."""
    active = []
    for job in dict.fromkeys(job_ids):
        done = subprocess.run(["squeue", "-h", "-r", "-o", "%i", "-j", job], capture_output=True,
                              text=True, timeout=PROBE_TIMEOUT_S)  # fmt: skip
        if done.returncode == 0 and done.stdout.split():  # unknown ids are errors: not active
            active.append(job)
    return active


def controller_states(job_ids: list[str]) -> dict[str, str]:
    """The controller's live state (squeue) of those of `job_ids` (jobs or array tasks `A_i`)
    it still lists; a finished job is absent. One squeue call for all, one per job when the
    controller refuses the list (some versions reject it whole for one id they forgot)."""

    def query(ids: list[str]) -> dict[str, str] | None:
        try:
            cmd = ["squeue", "-h", "-r", "-o", "%i|%T", "-j", ",".join(ids)]
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
        except (FileNotFoundError, subprocess.TimeoutExpired):
            return None
        if done.returncode != 0:
            return None
        return dict(line.split("|", 1) for line in done.stdout.split() if "|" in line)

    ids = list(dict.fromkeys(job_ids))
    found = query(ids) if ids else {}
    if found is None:
        found = {}
        for job in ids:
            found.update(query([job]) or {})
    return {job: found[job] for job in ids if job in found}


def job_states(folder: Path, job_ids: list[str]) -> dict[str, str]:
    """The state of each job whose submitit folder is `folder/<job id>`: the controller's
    (squeue) while it lists the job, else sacct's (through submitit's watcher, one call for
    all). Accounting lags behind the controller, so a job that already runs can still be
    missing from sacct: asking sacct alone read such a job as UNKNOWN. UNKNOWN remains only
    for a job neither lists yet."""
    import submitit

    ids = list(dict.fromkeys(job_ids))
    live = controller_states(ids)
    jobs = {j: submitit.SlurmJob(folder=folder / "%j", job_id=j) for j in ids if j not in live}
    finished = {j: job.state.split()[0] if job.state else "UNKNOWN" for j, job in jobs.items()}
    return {j: live.get(j) or finished[j] for j in ids}


# ── Submitting ────────────────────────────────────────────────────────────────────────────


@contextlib.contextmanager
def submitting():
    """Around submitit's sbatch calls: without the SLURM_* variables of a job we may be
    running in, and with sbatch's refusal as one `LaunchError` line (so submitit need not
    print it too)."""
    import submitit
    from submitit.core.utils import FailedJobError, FailedSubmissionError

    with submitit.helpers.clean_env(), contextlib.redirect_stderr(io.StringIO()):
        try:
            yield
        except (FailedJobError, FailedSubmissionError) as err:
            raise LaunchError(f"sbatch refused the job: {last_line(str(err))}") from err


def last_line(text: str) -> str:
    """The last non-blank line of an error message (sbatch's or a job's)."""
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else "no message"


def code_version() -> dict:
    """What code submits or runs a job: the package version (None when not installed) and
    `git describe` (`-dirty` with uncommitted changes) and the commit, from git where the
    source tree is a checkout, else as `git archive` wrote them into an exported tree
    (`ccdata.archived`; None in neither)."""
    try:
        version = metadata.version("ccbench")
    except metadata.PackageNotFoundError:
        version = None
    source = Path(__file__).resolve().parents[1]
    git = {"describe": None, "commit": None}
    if (source / ".git").exists():  # a checkout (a worktree's .git is a file), not site-packages
        for key, cmd in (("describe", ["describe", "--always", "--dirty", "--tags"]),
                         ("commit", ["rev-parse", "HEAD"])):  # fmt: skip
            try:
                done = subprocess.run(["git", *cmd], cwd=source, capture_output=True, text=True,
                                      timeout=30)  # fmt: skip
            except (FileNotFoundError, subprocess.TimeoutExpired):
                break
            if done.returncode == 0:
                git[key] = done.stdout.strip()
    else:
        git = archived_commit() or git
    return {"package": version, "git": git["describe"], "commit": git["commit"],
            "source": str(source)}  # fmt: skip


def code_label(code: dict) -> str:
    """`code_version()` on one line: `ccbench 0.1.0 git v0.1-3-gabc1234-dirty`."""
    label = f"ccbench {code['package'] or '(not installed)'}"
    return label + (f" git {code['git']}" if code.get("git") else "")
