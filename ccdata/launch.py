"""`ccdata generate --launcher slurm`: a dataset's episodes as a SLURM job array of shards
(through submitit), then one merge job.

- Each shard (an array task) writes its episodes' pieces into the generation journal
  (`ccdata.journal`), exactly as a local worker does; a piece already there is skipped, so a
  requeued or resubmitted shard only does what is left.
- The merge job depends on the array with `afterany` (with `afterok` a failed shard would leave
  it pending forever): it starts once every shard has ended, however it ended, and checks that
  every planned episode has a piece. If so it merges them in plan order (the merge tree is fixed
  by the plan, so the dataset is byte for byte the one `--workers 1` writes) and swaps it in. If
  not, it lists the missing episodes and fails, leaving the journal as it is; running the same
  command again submits only the shards that still miss episodes, and a new merge.
- Jobs are submitit `Checkpointable`s: on preemption or timeout they are requeued (up to
  `MAX_REQUEUES` timeouts) and resume from the journal.
- What was submitted (job ids, code version, shards) is recorded in the journal
  (`slurm-submission.json`); a new submission is refused while those jobs are still queued or
  running, since it would repair (delete) the journal's in-progress pieces under them.

Submitting returns at once. Logs go to `<dataset parent>/.<name>.ccdata-logs/<job id>/` (beside
the dataset, not inside it: the dataset directory is replaced by the merge) or `--log-dir`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import submitit
from submitit.core.utils import FailedJobError, FailedSubmissionError

from ccdata.dataset_format import existing_keys, write_json
from ccdata.journal import JournalPaths, finished_pieces, merge_pieces, prepare
from ccdata.record import GenerateConfig, plan, summarize, write_shard

SUBMISSION_RECORD = "slurm-submission.json"
"""In the journal: the last submission's job ids, code version and shards."""

MAX_REQUEUES = 3
"""Timeouts after which submitit stops requeueing a job (preemptions do not count)."""

PROBE_TIMEOUT_S = 30


class LaunchError(ValueError):
    """SLURM is not usable here, or a launch setting is wrong: one line for the user."""


class MissingEpisodes(RuntimeError):
    """The merge job found planned episodes that no shard wrote."""


# ── Settings ──────────────────────────────────────────────────────────────────────────────


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


@dataclass
class SlurmSettings:
    """How the shards and the merge are submitted. Validated on construction."""

    shards: int = 1
    """Array tasks the episodes are split into (contiguous ranges of the plan)."""
    partition: str | None = None
    """SLURM partition; None -> the cluster's default."""
    time_min: int = 60
    """Time limit of every job in minutes (submitit's `timeout_min`). Keep it >= 30 where jobs
    may be preempted: below 10 submitit takes a preemption signal for a timeout."""
    cpus_per_task: int = 1
    """CPUs per job; torch in the job uses as many threads."""
    mem: str | None = None
    """Memory per job in SLURM's notation (`8G`, `500M`); None -> the partition's default."""
    setup: list[str] = field(default_factory=list)
    """Shell lines run in each job before Python starts (`module load ...`, `source ...`)."""
    log_dir: str | Path | None = None
    """submitit folder (logs, pickles); must be on a filesystem the nodes share. None -> beside
    the dataset."""

    def __post_init__(self) -> None:
        if self.shards < 1:
            raise LaunchError(f"--shards must be >= 1, got {self.shards}")
        if self.time_min < 1:
            raise LaunchError(f"--time must be at least one minute, got {self.time_min}")
        if self.cpus_per_task < 1:
            raise LaunchError(f"--cpus-per-task must be >= 1, got {self.cpus_per_task}")
        if self.mem is not None and not re.fullmatch(r"\d+[KMGT]?", self.mem):
            raise LaunchError(f"--mem {self.mem!r}: expected a number with K, M, G or T")

    def folder(self, config: GenerateConfig) -> Path:
        if self.log_dir is not None:
            return Path(self.log_dir).expanduser().resolve()
        root = config.dataset_root
        return root.parent / f".{root.name}.ccdata-logs"


# ── Probes ────────────────────────────────────────────────────────────────────────────────


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
    """Raise `LaunchError` unless a SLURM controller answers and so does its accounting (sacct):
    submitit follows jobs through sacct, and without it a cancelled job never reports done."""
    if shutil.which("sbatch") is None:
        raise LaunchError("no SLURM reachable: sbatch is not on PATH")
    why = _probe(["sinfo", "-h", "-o", "%P"])
    if why:
        raise LaunchError(f"no SLURM reachable: {why}")
    why = _probe(["sacct", "-n", "-X", "-S", "now", "-o", "JobID"])
    if why:
        raise LaunchError(f"sacct not available ({why}); submitit needs SLURM accounting")


def code_version() -> str:
    """The package version, and the git commit of the source tree when it is a checkout
    (`-dirty` when it has uncommitted changes)."""
    try:
        version = f"ccbench {metadata.version('ccbench')}"
    except metadata.PackageNotFoundError:
        version = "ccbench (not installed)"
    source = Path(__file__).resolve().parent.parent
    if (source / ".git").exists():
        try:
            done = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"],
                                  cwd=source, capture_output=True, text=True, timeout=30)
            if done.returncode == 0:
                version += f" git {done.stdout.strip()}"
        except (FileNotFoundError, subprocess.TimeoutExpired):
            pass
    return version


def max_array_size() -> int:
    """The cluster's MaxArraySize (SLURM's default, 1001, when it does not say)."""
    done = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True,
                          timeout=PROBE_TIMEOUT_S)
    found = re.search(r"^MaxArraySize\s*=\s*(\d+)", done.stdout, re.MULTILINE)
    return int(found.group(1)) if found else 1001


def active_jobs(job_ids: list[str]) -> list[str]:
    """Those of `job_ids` (or their array tasks) still pending or running."""
    active = []
    for job in job_ids:
        done = subprocess.run(["squeue", "-h", "-o", "%i", "-j", job], capture_output=True,
                              text=True, timeout=PROBE_TIMEOUT_S)
        if done.returncode == 0:  # an unknown (long finished) id is an error: not active
            active += done.stdout.split()
    return active


# ── The jobs ──────────────────────────────────────────────────────────────────────────────


def _job_start(submitted: str) -> None:
    import torch

    torch.set_num_threads(max(1, int(os.environ.get("SLURM_CPUS_PER_TASK", "1"))))
    running = code_version()
    print(f"ccdata job: submitted with {submitted}; running {running}", flush=True)
    if running != submitted:
        print(f"ccdata job: warning: the code changed since submission ({submitted} -> "
              f"{running})", file=sys.stderr, flush=True)


class ShardJob(submitit.helpers.Checkpointable):
    """An array task: write the pieces of the episodes `keys` of `config` (a GenerateConfig as a
    dict) into the journal. Requeued on preemption or timeout; finished pieces are skipped."""

    def __call__(self, config: dict, keys: list[str], code: str) -> dict:
        _job_start(code)
        cfg = GenerateConfig(**config)
        wanted = set(keys)
        specs = [s for s in plan(cfg) if s.key in wanted]
        if len(specs) != len(wanted):
            unknown = sorted(wanted - {s.key for s in specs})
            raise ValueError(f"episodes not in the plan of these settings: {unknown}")
        written = write_shard(cfg, specs, JournalPaths(cfg.dataset_root).pieces)
        print(f"ccdata shard: wrote {len(written)} of {len(specs)} episodes", flush=True)
        return {"episodes": len(specs), "written": len(written)}


class MergeJob(submitit.helpers.Checkpointable):
    """The job after the shards: merge the journal into the dataset, or list what is missing."""

    def __call__(self, config: dict, code: str) -> dict:
        _job_start(code)
        return merge_journal(GenerateConfig(**config))


def missing_episodes(config: GenerateConfig) -> list[str]:
    """Planned episodes neither in the dataset nor in the journal, in plan order."""
    paths = JournalPaths(config.dataset_root)
    have = set(finished_pieces(paths))
    if paths.root.exists():
        have |= set(existing_keys(paths.root))
    return [s.key for s in plan(config) if s.key not in have]


def merge_journal(config: GenerateConfig) -> dict:
    """Merge every planned episode's piece into the dataset (plan order) and return the
    summary; raise `MissingEpisodes` (merging nothing) when some episode has no piece."""
    paths = prepare(config)  # also repairs a swap that a killed merge left half-done
    missing = missing_episodes(config)
    if missing:
        print(f"ccdata merge: {len(missing)} episode(s) missing:", *missing, sep="\n  ",
              file=sys.stderr, flush=True)
        shown = ", ".join(missing[:10]) + (", ..." if len(missing) > 10 else "")
        raise MissingEpisodes(
            f"{len(missing)} of {len(plan(config))} episodes have no piece ({shown}); nothing "
            f"merged. Run the same `ccdata generate` command again to fill the gaps.")
    records = [json.loads((p / "piece.json").read_text())
               for p in finished_pieces(paths).values()]
    merge_pieces(config, [s.key for s in plan(config)])
    shutil.rmtree(paths.work, ignore_errors=True)
    summary = summarize(paths.root, records)
    print(json.dumps(summary, indent=2), flush=True)
    return summary


# ── Submission ────────────────────────────────────────────────────────────────────────────


@dataclass
class Submission:
    """What `submit_generation` submitted."""

    root: str
    """The dataset directory the merge writes."""
    log_dir: str
    """submitit folder: `<job id>/` per job (array tasks: `<array>_<task>/`)."""
    code: str
    """Code version recorded with the jobs."""
    planned: int
    """Episodes to add to the dataset (plan minus those already in it)."""
    shards: dict[int, list[str]]
    """Submitted shards (index among `--shards`) -> the episodes each still has to write."""
    array_job: str | None
    """Job id of the shards' array; None when every piece already exists."""
    merge_job: str | None
    """Job id of the merge; None when the dataset is already complete."""


def _slices(items: list, n: int) -> list[list]:
    """`items` in `n` contiguous, near-equal, non-empty slices (fewer if there are fewer)."""
    return [list(s) for s in np.array_split(np.array(items, dtype=object), min(n, len(items)))]


def submit_generation(config: GenerateConfig, slurm: SlurmSettings) -> Submission:
    """Submit what is left of `config`'s dataset as shards and a merge; return at once."""
    check_slurm()
    paths = JournalPaths(config.dataset_root)
    record = paths.work / SUBMISSION_RECORD
    if record.is_file():
        previous = json.loads(record.read_text())
        running = active_jobs([j for j in (previous["array_job"], previous["merge_job"]) if j])
        if running:
            raise LaunchError(f"jobs of the last submission for {paths.root} are still queued "
                              f"or running ({', '.join(running)}): wait for them or scancel them")
    paths = prepare(config)
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    todo = [s.key for s in plan(config) if s.key not in present]
    folder = slurm.folder(config)
    sub = Submission(root=str(paths.root), log_dir=str(folder), code=code_version(),
                     planned=len(todo), shards={}, array_job=None, merge_job=None)
    if not todo:
        shutil.rmtree(paths.work, ignore_errors=True)  # nothing left in it to merge
        return sub
    done = set(finished_pieces(paths))
    # Shard i is always the same range of the episodes to add; a re-run resubmits only the
    # shards that still miss some, each with only what it misses.
    for i, keys in enumerate(_slices(todo, slurm.shards)):
        if left := [k for k in keys if k not in done]:
            sub.shards[i] = left

    if len(sub.shards) > (limit := max_array_size()):
        raise LaunchError(f"--shards {slurm.shards}: this cluster takes arrays of at most "
                          f"{limit} tasks (MaxArraySize)")
    folder.mkdir(parents=True, exist_ok=True)
    executor = submitit.SlurmExecutor(folder=folder / "%j", max_num_timeout=MAX_REQUEUES)
    executor.update_parameters(
        time=slurm.time_min, cpus_per_task=slurm.cpus_per_task, partition=slurm.partition,
        mem=slurm.mem, setup=list(slurm.setup), comment=sub.code[:200],
        additional_parameters={"requeue": True},
    )
    settings = {**asdict(config), "root": str(paths.root), "workers": 1}
    # clean_env: not the SLURM_* variables of a job we may be running in; sbatch's complaints
    # come back in the error, so submitit need not print them too.
    with submitit.helpers.clean_env(), contextlib.redirect_stderr(io.StringIO()):
        try:
            if sub.shards:
                executor.update_parameters(job_name=f"ccdata-{config.suite}-shard")
                jobs = executor.map_array(ShardJob(), [settings] * len(sub.shards),
                                          list(sub.shards.values()), [sub.code] * len(sub.shards))
                sub.array_job = jobs[0].job_id.split("_")[0]
                write_json(record, asdict(sub))
            executor.update_parameters(
                job_name=f"ccdata-{config.suite}-merge",
                dependency=f"afterany:{sub.array_job}" if sub.array_job else None)
            sub.merge_job = executor.submit(MergeJob(), settings, sub.code).job_id
        except (FailedJobError, FailedSubmissionError) as err:
            raise LaunchError(f"sbatch refused the job: {_last_line(str(err))}") from err
    write_json(record, asdict(sub))
    return sub


def _last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else "no message"
