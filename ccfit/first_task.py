"""One first task for every method: runs that differ only in the method train it once.

Until its first task's steps are done, a run of FT, ER, EWC or PackNet computes the same
thing: nothing is stored yet, EWC has no Fisher, PackNet has pruned nothing, so their hooks
leave training as plain fine-tuning leaves it. A method first acts when the task closes
(`after_task`: ER keeps the task's replay, EWC its Fisher, PackNet prunes and retrains). A
method says so with `ContinualMethod.shares_first_task`, and the contract test holds it to
it: a run started from the shared first task equals, record for record, the run that trained
its own (tests/test_first_task.py).

So a sweep's runs of one seed (`ccfit sweep`, by default) share the part up to the
close. `RUNS/first/<key>` (the key of their shared from-scratch reference: everything but the
method) holds FT's run trained through task 0's steps and checkpointed before the task closes,
by a job of its own that the seed's runs wait for (or, where none ran, by the first run to need
it while the others wait on the folder's lock); each run copies that checkpoint, less FT's
method state, into its own task folder with the stage-0 records and the TensorBoard scalars,
and resumes from it as from any checkpoint: its own method closes the task, and the end-of-task
evaluation is its own.

    first/<key>/            config.json (FT's), metrics.jsonl, tb/, tasks/0-<task>/
    first/<key>/first.json  written last: the checkpoint's sha256, what training it cost,
                            whether a job of its own or a run trained it
    <run>/first_task.json   the shared folder it started from and that record
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import torch

from ccfit.io import atomic_torch_save, atomic_write_json, file_sha256, read_run_json
from ccfit.replay_store import ROWS_DIR
from ccfit.run_files import CHECKPOINT, COST, FIRST, FIRST_DONE, FIRST_RECORD
from ccfit.train.records import METRICS, TENSORBOARD, record_stage, write_records

__all__ = ["FIRST", "FIRST_DONE", "FIRST_RECORD", "first_task_done", "mark_done",
           "start_from_first_task"]  # fmt: skip


def first_task_done(shared: Path) -> dict | None:
    """The shared folder's record (None: not trained to its close yet)."""
    path = Path(shared) / FIRST_DONE
    if not path.exists():
        return None
    return read_run_json(path, remedy=f"delete {Path(shared)} and run the sweep again")


def mark_done(shared: Path, folder: Path, trained_by: str) -> dict:
    """Record the shared first task trained: `folder` (its task folder) holds the checkpoint
    taken before the task closes; `trained_by`: 'job' (a sweep's job of its own, whose cost
    no run counts) or 'run' (a run's process, whose cost.json counts it)."""
    checkpoint = Path(folder) / CHECKPOINT
    cost = Path(shared) / COST
    record = {
        "task_folder": str(Path(folder).relative_to(shared)),
        "state_sha256": file_sha256(checkpoint),
        "cost": json.loads(cost.read_text()) if cost.exists() else None,
        "trained_by": trained_by,
    }
    atomic_write_json(Path(shared) / FIRST_DONE, record)
    return record


def start_from_first_task(shared: Path, out: Path, folder: Path) -> None:
    """Make run directory `out` resume its first task (task folder `folder`) from the shared
    one: the checkpoint without the shared run's method state (the run's own method, fresh
    from `before_task(0)`, is what that state would be), the replay rows it lists (hard links
    where the file system allows), the stage-0 records and TensorBoard scalars."""
    shared, out, folder = Path(shared), Path(out), Path(folder)
    record = first_task_done(shared)
    if record is None:
        raise RuntimeError(f"{shared}: the shared first task is not finished")
    source = shared / record["task_folder"]
    state = torch.load(source / CHECKPOINT, map_location="cpu", weights_only=False)
    state.pop("method", None)
    shutil.rmtree(folder, ignore_errors=True)
    (folder / ROWS_DIR).mkdir(parents=True)
    for entry in state["replay_files"]:
        _link_or_copy(source / ROWS_DIR / entry["file"], folder / ROWS_DIR / entry["file"])
    records = read_run_json(shared / METRICS, lines=True) if (shared / METRICS).exists() else []
    write_records(out / METRICS, [r for r in records if record_stage(r) == 0])
    shutil.rmtree(out / TENSORBOARD, ignore_errors=True)
    if (shared / TENSORBOARD).is_dir():
        shutil.copytree(shared / TENSORBOARD, out / TENSORBOARD)
    atomic_write_json(out / FIRST_RECORD, {"shared": shared.name, **record})
    # The checkpoint last: until it is there the run starts from the shared task again.
    atomic_torch_save(state, folder / CHECKPOINT)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:  # another file system, or one without hard links
        shutil.copyfile(src, dst)
