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
  `ccdata.slurm.MAX_REQUEUES` timeouts) and resume from the journal.
- What was submitted (job ids, code version, shards) is recorded in the journal
  (`slurm-submission.json`); a new submission is refused while those jobs are still queued or
  running, since it would repair (delete) the journal's in-progress pieces under them.

Submitting returns at once. Logs go to `<dataset parent>/.<name>.ccdata-logs/<job id>/` (beside
the dataset, not inside it: the dataset directory is replaced by the merge) or `--log-dir`.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import submitit

from ccdata.dataset_format import existing_keys, write_json
from ccdata.episode_plan import plan
from ccdata.journal import JournalPaths, finished_pieces, merge_pieces, prepare
from ccdata.record import GenerateConfig, summarize
from ccdata.slurm import (
    LaunchError,
    SlurmSettings,
    active_jobs,
    check_array_size,
    check_slurm,
    code_label,
    code_version,
    submitting,
)
from ccdata.writer import write_shard

SUBMISSION_RECORD = "slurm-submission.json"
"""In the journal: the last submission's job ids, code version and shards."""


class MissingEpisodes(RuntimeError):
    """The merge job found planned episodes that no shard wrote."""


def log_folder(slurm: SlurmSettings, config: GenerateConfig) -> Path:
    """submitit's folder: `--log-dir`, else `.<name>.ccdata-logs` beside the dataset (not
    inside it: the merge replaces the dataset directory)."""
    root = config.dataset_root
    return slurm.log_folder(root.parent / f".{root.name}.ccdata-logs")


# ── The jobs ──────────────────────────────────────────────────────────────────────────────


def _job_start(submitted: str) -> None:
    import torch

    torch.set_num_threads(max(1, int(os.environ.get("SLURM_CPUS_PER_TASK", "1"))))
    running = code_label(code_version())
    print(f"ccdata job: submitted with {submitted}; running {running}", flush=True)
    if running != submitted:
        print(
            f"ccdata job: warning: the code changed since submission ({submitted} -> {running})",
            file=sys.stderr,
            flush=True,
        )


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
        print(
            f"ccdata merge: {len(missing)} episode(s) missing:",
            *missing,
            sep="\n  ",
            file=sys.stderr,
            flush=True,
        )
        shown = ", ".join(missing[:10]) + (", ..." if len(missing) > 10 else "")
        raise MissingEpisodes(
            f"{len(missing)} of {len(plan(config))} episodes have no piece ({shown}); nothing "
            f"merged. Run the same `ccdata generate` command again to fill the gaps."
        )
    records = [json.loads((p / "piece.json").read_text()) for p in finished_pieces(paths).values()]
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
            raise LaunchError(
                f"jobs of the last submission for {paths.root} are still queued "
                f"or running ({', '.join(running)}): wait for them or scancel them"
            )
    paths = prepare(config)
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    todo = [s.key for s in plan(config) if s.key not in present]
    folder = log_folder(slurm, config)
    sub = Submission(
        root=str(paths.root),
        log_dir=str(folder),
        code=code_label(code_version()),
        planned=len(todo),
        shards={},
        array_job=None,
        merge_job=None,
    )
    if not todo:
        shutil.rmtree(paths.work, ignore_errors=True)  # nothing left in it to merge
        return sub
    done = set(finished_pieces(paths))
    # Shard i is always the same range of the episodes to add; a re-run resubmits only the
    # shards that still miss some, each with only what it misses.
    for i, keys in enumerate(_slices(todo, slurm.shards)):
        if left := [k for k in keys if k not in done]:
            sub.shards[i] = left

    check_array_size(len(sub.shards), f"--shards {slurm.shards}")
    folder.mkdir(parents=True, exist_ok=True)
    executor = slurm.executor(folder, comment=sub.code)
    settings = {**asdict(config), "root": str(paths.root), "workers": 1}
    with submitting():
        if sub.shards:
            executor.update_parameters(job_name=f"ccdata-{config.suite}-shard")
            jobs = executor.map_array(
                ShardJob(),
                [settings] * len(sub.shards),
                list(sub.shards.values()),
                [sub.code] * len(sub.shards),
            )
            sub.array_job = jobs[0].job_id.split("_")[0]
            write_json(record, asdict(sub))
        executor.update_parameters(
            job_name=f"ccdata-{config.suite}-merge",
            dependency=f"afterany:{sub.array_job}" if sub.array_job else None,
        )
        sub.merge_job = executor.submit(MergeJob(), settings, sub.code).job_id
    write_json(record, asdict(sub))
    return sub
