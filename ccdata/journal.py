"""The on-disk journal that makes `ccdata generate` interruptible, and the merges out of it.

How the work is laid out on disk (target root `R`, e.g. `$HF_LEROBOT_HOME/ccdata/Reach`):

- `R/` is always a finalized, readable LeRobot dataset (or absent). It is only ever replaced by
  an atomic rename of a freshly merged copy, so no interruption can leave it half-written.
- `R/../.<name>.ccdata-work/` is the journal of the run in progress: `settings.json` (the
  generation settings it belongs to) and `pieces/`, one small finalized LeRobot dataset per
  completed episode. An episode is written to `pieces/.tmp-<key>` and renamed to
  `pieces/<key>` only after LeRobot's `finalize()`, so a SIGKILL loses only the episodes not
  yet written: in progress, or rolled out and waiting for a writer (a `.tmp-` directory left
  behind is deleted by the next run).
- While episodes are being rolled out, a merger process (`merge_chunks`) aggregates each
  complete chunk of `GROUP` consecutive episodes into `batches/<first key>` (finalized before it
  is renamed into place, with `batch.json` naming its episodes), so most merging overlaps the
  rollouts instead of following them.
- At the end of a run, on Ctrl-C, or at the start of the next run after a SIGKILL, the batches
  and the remaining pieces are merged (with the existing `R`, if any) by
  `lerobot.datasets.aggregate` into `.<name>.ccdata-new`, which then replaces `R` (`R` ->
  `.ccdata-old`, new -> `R`, old deleted; a run killed between the renames is repaired on the
  next start).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ccdata.dataset_format import (
    CCDATA_META,
    ccdata_metadata,
    check_identity,
    check_lerobot_info,
    existing_keys,
    quiet_libraries,
    read_ccdata_metadata,
    write_json,
)
from ccdata.errors import InputError
from ccdata.lerobot_speedups import faster_lerobot
from ccdata.processes import die_with, process_context, start_soon
from ccdata.verify import check_intact

if TYPE_CHECKING:
    from ccdata.settings import DatasetSettings

GROUP = 16
"""Datasets merged per `aggregate_datasets` call, and episodes per batch of the merger process;
merges are grouped in a tree because each call rewrites its growing output once per source
(quadratic in the number of sources)."""


@dataclass(frozen=True)
class JournalPaths:
    root: Path

    @property
    def work(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-work"

    @property
    def pieces(self) -> Path:
        return self.work / "pieces"

    @property
    def batches(self) -> Path:
        return self.work / "batches"

    @property
    def new(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-new"

    @property
    def old(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-old"


BATCH_RECORD = "batch.json"
"""In a finished batch: the keys of its episodes, in order."""


def _recover(paths: JournalPaths) -> None:
    """Finish or undo a swap that a killed run left half-done; drop incomplete leftovers."""
    if not paths.root.exists():
        if (paths.new / CCDATA_META).is_file():
            os.replace(paths.new, paths.root)
        elif paths.old.exists():
            os.replace(paths.old, paths.root)
    shutil.rmtree(paths.new, ignore_errors=True)
    shutil.rmtree(paths.old, ignore_errors=True)
    shutil.rmtree(paths.work / "merge", ignore_errors=True)
    (paths.work / "STOP").unlink(missing_ok=True)
    for journal in (paths.pieces, paths.batches):
        if journal.exists():
            for tmp in journal.glob(".tmp-*"):
                shutil.rmtree(tmp, ignore_errors=True)


def finished_pieces(paths: JournalPaths) -> dict[str, Path]:
    if not paths.pieces.exists():
        return {}
    return {
        p.name: p
        for p in paths.pieces.iterdir()
        if p.is_dir() and not p.name.startswith(".") and (p / "piece.json").is_file()
    }


def finished_batches(paths: JournalPaths) -> dict[tuple[str, ...], Path]:
    """Finished batches: their episode keys (in order) -> directory."""
    if not paths.batches.exists():
        return {}
    return {
        tuple(json.loads((b / BATCH_RECORD).read_text())["keys"]): b
        for b in paths.batches.iterdir()
        if b.is_dir() and not b.name.startswith(".") and (b / BATCH_RECORD).is_file()
    }


def chunks_of(keys: list[str], group: int | None = None) -> list[list[str]]:
    """The batches a plan's episodes (`keys`, the whole plan in order) are merged in:
    consecutive runs of `group` (default `GROUP`); a shorter remainder is left to the final
    merge. Fixed by the plan alone, so the merge tree of a run, and with it every byte of the
    result, does not depend on timing; and a batch never spans an episode written by another
    run (one at the root, or one a stopped run left waiting in the journal after a gap), which
    the final merge could not put back in plan order. A chunk with an episode at the root is
    not batched: its other episodes are merged one by one."""
    group = group or GROUP
    return [keys[i : i + group] for i in range(0, len(keys) - group + 1, group)]


def merge_batch(config: DatasetSettings, keys: list[str]) -> Path:
    """Aggregate the journal's pieces of `keys` (all finished) into one batch, atomically."""
    from lerobot.datasets.aggregate import aggregate_datasets

    paths = JournalPaths(config.dataset_root)
    final, tmp = paths.batches / keys[0], paths.batches / f".tmp-{keys[0]}"
    shutil.rmtree(tmp, ignore_errors=True)
    paths.batches.mkdir(parents=True, exist_ok=True)
    try:
        with faster_lerobot():
            aggregate_datasets(
                [config.repo_id] * len(keys),
                config.repo_id,
                roots=[paths.pieces / k for k in keys],
                aggr_root=tmp,
            )
        write_json(tmp / BATCH_RECORD, {"keys": list(keys)})
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def merge_chunks(config: DatasetSettings, chunks: list[list[str]], finished) -> None:
    """What the merger process runs: batch each chunk, in order, as soon as all its pieces
    exist; return when all are batched or `finished` (an Event) is set, leaving the rest to the
    final merge. Needs only its arguments and the journal (an independent job)."""
    quiet_libraries()
    paths = JournalPaths(config.dataset_root)
    taken = set(existing_keys(paths.root)) if paths.root.exists() else set()
    taken |= {k for keys in finished_batches(paths) for k in keys}
    for keys in chunks:
        if taken & set(keys):  # batched already, or partly at the root (`chunks_of`)
            continue
        while not all((paths.pieces / k / "piece.json").is_file() for k in keys):
            if finished.wait(0.25):
                return
        if finished.is_set():
            return
        merge_batch(config, keys)


def _merger_main(config: DatasetSettings, chunks: list[list[str]], order: list[str], finished,
                 parent: int, group: int) -> None:  # fmt: skip
    import signal

    die_with(parent)
    # Ctrl-C reaches the whole process group: the generating process decides what stops, and
    # then sets `finished`.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    merge_chunks(config, chunks, finished)
    finished.wait()  # merge_chunks returns early when it runs out of chunks
    merge_pieces(config, order, group)


def _aggregate(sources: list[Path], dst: Path, repo_id: str, scratch: Path, group: int) -> None:
    """Merge finalized datasets, in order, into a new dataset at `dst` (in a tree of `group`s)."""
    from lerobot.datasets.aggregate import aggregate_datasets

    level = 0
    while len(sources) > group:
        groups = [sources[i : i + group] for i in range(0, len(sources), group)]
        merged = []
        for g, members in enumerate(groups):
            out = scratch / f"level{level}-{g:05d}"
            shutil.rmtree(out, ignore_errors=True)
            aggregate_datasets([repo_id] * len(members), repo_id, roots=members, aggr_root=out)
            merged.append(out)
        if level > 0:
            for s in sources:
                shutil.rmtree(s, ignore_errors=True)
        sources, level = merged, level + 1
    aggregate_datasets([repo_id] * len(sources), repo_id, roots=sources, aggr_root=dst)


def merge_pieces(config: DatasetSettings, order: list[str] | None = None,
                 group: int | None = None) -> int:  # fmt: skip
    """Merge the journal (batches and pieces) after the episodes already at the root; swap
    atomically. `order`: the plan's keys, which fixes the episode order and the chunks;
    `group`: datasets per merge (default `GROUP`; the merger process is handed its parent's,
    so that the tree is the one the parent planned whichever process merges).

    Journal entries whose episodes are already at the root are dropped. Returns the episodes
    added."""
    paths = JournalPaths(config.dataset_root)
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    pieces, batches = finished_pieces(paths), finished_batches(paths)
    for keys in list(batches):
        if set(keys) & present:  # a run killed after its swap, before its clean-up
            shutil.rmtree(batches.pop(keys))
    for key in [k for k in pieces if k in present]:
        shutil.rmtree(pieces.pop(key))
    if not pieces and not batches:
        return 0
    quiet_libraries()
    # Complete chunks the merger did not get to are batched here: the same tree either way.
    batched = {k for keys in batches for k in keys}
    group = group or GROUP
    for keys in chunks_of(order or [], group):
        if all(k in pieces and k not in batched for k in keys):
            batches[tuple(keys)] = merge_batch(config, keys)
            batched.update(keys)
    if order is not None:
        # Only what continues the root without a gap: an episode after one not written yet
        # (a run stopped with episodes done out of order) waits in the journal for it, so a
        # dataset completed across interruptions is in plan order, as one run writes it.
        done = set(pieces) | batched
        prefix: set[str] = set()
        for k in (k for k in order if k not in present):
            if k not in done:
                break
            prefix.add(k)
        batches = {keys: p for keys, p in batches.items() if set(keys) <= prefix}
        pieces = {k: p for k, p in pieces.items() if k in prefix}
        if not pieces and not batches:
            return 0
    rank = {k: i for i, k in enumerate(order or [])}
    entries = [(keys[0], path, list(keys)) for keys, path in batches.items()]
    entries += [(k, p, [k]) for k, p in pieces.items() if k not in batched]
    entries.sort(key=lambda e: (rank.get(e[0], len(rank)), e[0]))
    sources = ([paths.root] if paths.root.exists() else []) + [e[1] for e in entries]
    shutil.rmtree(paths.new, ignore_errors=True)
    scratch = paths.work / "merge"
    scratch.mkdir(parents=True, exist_ok=True)
    with faster_lerobot():
        _aggregate(sources, paths.new, config.repo_id, scratch, group)
    shutil.rmtree(scratch, ignore_errors=True)
    _sort_stats(paths.new)
    from ccdata.cards import render_card

    meta = ccdata_metadata(config)
    # The card states this dataset's settings and what was measured on it.
    (paths.new / "README.md").write_text(render_card(config, dataset=paths.new, metadata=meta))
    write_json(paths.new / CCDATA_META, meta)  # written last: "complete"
    if paths.root.exists():
        os.replace(paths.root, paths.old)
    os.replace(paths.new, paths.root)
    shutil.rmtree(paths.old, ignore_errors=True)
    for p in [*batches.values(), *pieces.values()]:  # merged; what waits for a gap stays
        shutil.rmtree(p, ignore_errors=True)
    if paths.batches.is_dir() and not any(paths.batches.iterdir()):
        paths.batches.rmdir()
    return sum(len(e[2]) for e in entries)


def _sort_stats(root: Path) -> None:
    """meta/stats.json with its features in sorted order: LeRobot's merge collects them in a
    set, so their order would follow Python's string hashing, which differs per process."""
    path = root / "meta/stats.json"
    stats = json.loads(path.read_text())
    path.write_text(json.dumps({k: stats[k] for k in sorted(stats)}, indent=4, ensure_ascii=False))


def prepare(config: DatasetSettings) -> JournalPaths:
    """Check the target and the journal belong to these settings; repair leftovers."""
    paths = JournalPaths(config.dataset_root)
    if paths.root.exists() and not paths.root.is_dir():
        raise InputError(f"the dataset root {paths.root} is a file, not a folder")
    _recover(paths)
    if paths.root.exists():
        if not any(paths.root.iterdir()):
            paths.root.rmdir()
        else:
            check_identity(read_ccdata_metadata(paths.root).get("identity", {}), config, paths.root)
            check_lerobot_info(paths.root)
            # else the final merge would fail on it after every new episode was rolled out
            check_intact(paths.root, "nothing can be added to it")
    settings = paths.work / "settings.json"
    if settings.is_file():
        try:
            identity = json.loads(settings.read_text())
            damage = None if isinstance(identity, dict) else "not a JSON object"
        except json.JSONDecodeError as err:
            damage = str(err)
        if damage:
            raise InputError(f"{settings} is corrupt ({damage}): delete {paths.work} to start "
                             f"the journal over (its finished episodes are lost)")  # fmt: skip
        check_identity(identity, config, paths.work)
    paths.pieces.mkdir(parents=True, exist_ok=True)
    write_json(settings, config.identity())
    return paths


class Merger:
    """`merge_chunks` in a process of its own (`ccdata.processes`) beside the rollouts, and at
    the end the final merge (`merge_pieces`), so that the rolling-out process never imports
    LeRobot (torch and LeRobot take seconds to import)."""

    def __init__(self, config: DatasetSettings, chunks: list[list[str]], order: list[str]) -> None:
        ctx = process_context()
        self.finished = ctx.Event()
        self.process = ctx.Process(
            target=_merger_main,
            name="ccdata-merger",
            daemon=True,
            args=(config, chunks, order, self.finished, os.getpid(), GROUP),
        )
        self.starting = start_soon(self.process)

    def finish(self) -> None:
        """Let the merger complete the batch it is writing, then merge the journal into the
        dataset; wait for it to exit. The caller then runs `merge_pieces` itself, which finds
        nothing to do unless the merger failed."""
        self.finished.set()
        self.starting.join()
        while True:
            try:
                self.process.join()
                return
            except KeyboardInterrupt:  # a second Ctrl-C: still wait, merges are atomic
                continue
