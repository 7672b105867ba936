"""`ccdata generate`'s engine: roll out a suite's policies and write one LeRobot v3 dataset.

Each episode is recorded (`ccdata.writer`) into its own small finalized LeRobot dataset (a
piece) in a journal beside the target, and the pieces are merged into the target in plan order
(`ccdata.journal` describes the layout and why no interruption can leave a half-written
dataset). Episodes are identified by (task id, policy, episode seed); a run skips every episode
already in the target or the journal, so re-running the same command completes the requested
counts without duplicates. Workers (`workers > 1`) are spawned processes, each
running `write_shard` on its share of the plan (every `workers`-th episode) with its own
environment; the merge puts pieces in plan order, so the result does not depend on the number
of workers.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from ccdata.dataset_format import (
    existing_keys,
    measure_dataset,
    read_ccdata_metadata,
)
from ccdata.episode_plan import EpisodeSpec, plan
from ccdata.journal import (
    JournalPaths,
    Merger,
    chunks_of,
    finished_pieces,
    merge_pieces,
    prepare,
)
from ccdata.processes import die_with
from ccdata.settings import DatasetSettings
from ccdata.writer import write_shard


@dataclass
class GenerateConfig(DatasetSettings):
    """A dataset's settings (`ccdata.settings.DatasetSettings`) plus how to run its generation.
    Validated on construction."""

    workers: int = 1
    """Processes rolling out episodes in parallel (one environment each). No effect on content."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")




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
    merger = Merger(config, chunks_of([s.key for s in todo]), order) if todo else None
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


def _run_workers(config: GenerateConfig, todo: list[EpisodeSpec], paths: JournalPaths,
                 done_one: Callable[[dict], None]) -> None:
    # Every workers-th episode: each worker gets the same mix of tasks and policies, so about
    # the same steps (contiguous slices put the long random episodes of different tasks
    # unevenly), and chunks of consecutive episodes complete early for the merger.
    slices = [todo[i::config.workers] for i in range(min(config.workers, len(todo)))]
    seen: set[str] = set(finished_pieces(paths))
    wanted = {s.key for s in todo}
    records = {}

    def poll() -> None:
        for key, piece in finished_pieces(paths).items():
            if key in wanted and key not in seen:
                seen.add(key)
                records[key] = json.loads((piece / "piece.json").read_text())
                done_one(records[key])

    # Spawned, not forked from the fork server: the server forks nothing before its imports are
    # done, and the rollouts need none of them (each worker's writer comes from a server of the
    # worker's own, which imports while the worker rolls out).
    pool = ProcessPoolExecutor(len(slices), mp_context=get_context("spawn"),
                               initializer=die_with, initargs=(os.getpid(),))
    try:
        futures = [pool.submit(write_shard, config, s, paths.pieces) for s in slices]
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            poll()
            for f in finished:
                f.result()  # re-raise a worker's error here
    except BaseException:
        (paths.work / "STOP").touch()  # workers stop after their current episode
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    poll()


def summarize(root: Path, new_records: Iterable[dict] = (), wall_time: float | None = None
              ) -> dict:
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
        row.update(new_episodes=n_new, wall_time_s=s_new,
                   frames_per_s=f_new / s_new if s_new > 0 else None)
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
