"""`ccdata generate`'s engine: roll out a suite's policies and write one LeRobot v3 dataset.

Each episode is recorded (`ccdata.writer`) into its own small finalized LeRobot dataset (a
piece) in a journal beside the target, and the pieces are merged into the target in plan order
(`ccdata.journal` describes the layout and why no interruption can leave a half-written
dataset). Episodes are identified by (task id, policy, episode seed); a run skips every episode
already in the target or the journal, so re-running the same command completes the requested
counts without duplicates. With `workers > 1`, that many spawned rollout processes (one
environment each) claim the episodes one at a time and queue them for as many writer
processes; the merge puts pieces in plan order, so the result does not depend on the number
of workers.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from ccdata.dataset_format import (
    existing_keys,
    measure_dataset,
    read_ccdata_metadata,
)
from ccdata.episode_plan import EpisodeSpec, plan
from ccdata.errors import InputError
from ccdata.journal import (
    JournalPaths,
    Merger,
    chunks_of,
    finished_batches,
    finished_pieces,
    merge_pieces,
    prepare,
)
from ccdata.processes import die_with, end_processes
from ccdata.settings import DatasetSettings
from ccdata.writer import GenerationError, Writers, roll_out, write_shard


@dataclass
class GenerateConfig(DatasetSettings):
    """A dataset's settings (`ccdata.settings.DatasetSettings`) plus how to run its generation.
    Validated on construction."""

    workers: int = 1
    """Processes rolling out episodes in parallel (one environment each). No effect on content."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.workers < 1:
            raise InputError(f"workers must be >= 1, got {self.workers}")


# ── generate ──────────────────────────────────────────────────────────────────────────────


def generate(
    config: GenerateConfig,
    on_episode: Callable[[dict], None] | None = None,
    progress: bool = True,
) -> tuple[Path, dict]:
    """Generate (or complete) the dataset of `config`. Returns (dataset root, summary).

    It starts processes (`ccdata.processes`: a multiprocessing fork server, whose children
    import the main module as spawned ones do): a script calling it needs the usual
    `if __name__ == "__main__":` guard.

    `on_episode(record)` is called in this process after each completed episode. A
    KeyboardInterrupt (Ctrl-C, or raised by `on_episode`) stops the workers after their current
    episode, merges every completed episode into a valid dataset, and is re-raised."""
    from tqdm.auto import tqdm

    paths = prepare(config)
    full_plan = plan(config)
    order = [s.key for s in full_plan]
    merge_pieces(config, order)  # pieces a killed run left behind
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    # Episodes a stopped run finished after a gap wait in the journal: not rolled out again.
    present |= set(finished_pieces(paths)) | {k for keys in finished_batches(paths) for k in keys}
    todo = [s for s in full_plan if s.key not in present]
    new_records: list[dict] = []
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc=f"{config.suite}", unit="ep", disable=not progress)

    def done_one(record: dict) -> None:
        new_records.append(record)
        bar.update(1)
        bar.set_postfix_str(f"{record['task_id']} {record['policy']}")
        if on_episode is not None:
            on_episode(record)

    interrupted = False
    merger = Merger(config, chunks_of(order), order) if todo else None
    try:
        if config.workers == 1 or len(todo) <= 1:
            write_shard(config, todo, paths.pieces, on_piece=done_one)
        else:
            _run_workers(config, todo, paths, done_one)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
        if merger is not None:
            merger.finish()
        merge_pieces(config, order)  # nothing left to do unless the merger failed
        wall = time.perf_counter() - start  # end to end: the merge is part of the work
        (paths.work / "STOP").unlink(missing_ok=True)
    if interrupted:
        raise KeyboardInterrupt
    shutil.rmtree(paths.work, ignore_errors=True)
    return paths.root, summarize(paths.root, new_records, wall)


def _run_workers(
    config: GenerateConfig,
    todo: list[EpisodeSpec],
    paths: JournalPaths,
    done_one: Callable[[dict], None],
) -> None:
    writers = Writers(config, paths.pieces, done_one, count=config.workers)
    # Spawned, not forked from the fork server: the server forks nothing before its imports are
    # done, and rolling out needs none of them. The writers are the server's, so its imports
    # (torch, LeRobot) are paid once whatever the number of workers.
    ctx = get_context("spawn")
    claimed = ctx.Value("q", 0)
    stop_file = paths.work / "STOP"
    rollouts = [
        ctx.Process(target=_rollout_main, name=f"ccdata-rollout-{i}", daemon=True,
                    args=(config, todo, claimed, writers.episodes, writers.results, stop_file,
                          os.getpid()))
        for i in range(min(config.workers, len(todo)))
    ]  # fmt: skip
    try:
        for r in rollouts:
            r.start()
        while any(r.is_alive() for r in rollouts):
            writers.wait()
            _raise_if_died(rollouts)
        writers.poll()  # a failed rollout reports before it exits
        _raise_if_died(rollouts)
        writers.finish()
    except BaseException as err:
        stop_file.touch()  # rollouts stop after their current episode
        # A process killed while sending an episode may leave the queue locked or half-written:
        # then no one waits for a writer to finish its piece.
        broken = isinstance(err, GenerationError)
        writers.abort(grace_s=0 if broken else 120)
        # The other rollouts may be blocked on that queue's lock for good: after a death they
        # are ended at once (what they had not sent is redone by a rerun), not waited for.
        end_processes(rollouts, grace_s=0 if broken else 60)
        raise


def _raise_if_died(rollouts: list) -> None:
    for r in rollouts:
        if r.exitcode not in (None, 0):
            raise GenerationError(f"{r.name} died (exit code {r.exitcode})")


def _rollout_main(
    config: GenerateConfig,
    todo: list[EpisodeSpec],
    claimed,
    episodes,
    results,
    stop_file: Path,
    parent: int,
) -> None:
    """A rollout process: roll out the next unclaimed episode of `todo` until none is left.

    Claimed one at a time in plan order, so that the workers finish together whatever the
    lengths of their episodes, and consecutive episodes (the merger's chunks) complete early."""
    die_with(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the generating process decides what stops

    def next_spec() -> Iterator[EpisodeSpec]:
        while True:
            with claimed.get_lock():
                i = claimed.value
                claimed.value = i + 1
            if i >= len(todo):
                return
            yield todo[i]

    try:
        roll_out(config, next_spec(), episodes, stop_file)
        if episodes.stop.is_set() or stop_file.exists():
            # Stopped: the writers may read no more, and what was not sent is dropped. Waiting
            # to send it would keep this process from exiting.
            episodes.jobs.cancel_join_thread()
    except BaseException:
        results.put(("error", f"a rollout process failed:\n{traceback.format_exc()}"))
        results.close()
        results.join_thread()  # the report is on its way before this process exits
        raise SystemExit(1) from None


def summarize(root: Path, new_records: Iterable[dict] = (), wall_time: float | None = None) -> dict:
    """`measure_dataset` of the dataset at `root` (per task and policy: episodes, frames, steps,
    success rate, mean discounted and normalised return), plus this run's new episodes: count,
    seconds of work and frames per second per row, and the run's wall time."""
    meta = read_ccdata_metadata(root)
    measured = measure_dataset(root, [t["id"] for t in meta["tasks"]])
    new = {}
    for r in new_records:
        agg = new.setdefault((r["task_id"], r["policy"]), [0, 0, 0.0])
        agg[0] += 1
        agg[1] += r["frames"]
        agg[2] += r["seconds"]
    for row in measured["per_task_policy"]:
        n_new, f_new, s_new = new.get((row["task"], row["policy"]), [0, 0, 0.0])
        row.update(
            new_episodes=n_new, wall_time_s=s_new, frames_per_s=f_new / s_new if s_new > 0 else None
        )
    new_frames = sum(r["frames"] for r in new_records)
    new_steps = sum(r.get("steps", r["frames"]) for r in new_records)
    return {
        "root": str(root),
        **{k: measured[k] for k in ("episodes", "frames", "steps", "bytes_per_1000_frames")},
        "new_episodes": sum(r["new_episodes"] for r in measured["per_task_policy"]),
        "new_steps": new_steps,
        "wall_time_s": wall_time,
        "frames_per_s": new_frames / wall_time if wall_time else None,
        "steps_per_s": new_steps / wall_time if wall_time else None,
        "per_task_policy": measured["per_task_policy"],
    }
