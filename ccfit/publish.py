"""`ccfit publish`: the small files of finished runs, copied into a results folder with the
report over them, so a repository can ship its numbers without checkpoints or replay.

    ccfit publish ../runs/reach-tdmpc2 --out results/online/reach-tdmpc2

    ccfit publish ../runs/learn --out results/single-task

    ccfit publish ../runs/drawerpnp-tdmpc2 --out results/online/drawerpnp-tdmpc2 --root results

Every finished curriculum under RUNS (a folder with metrics.json) keeps its configuration,
metrics, per-evaluation records and cost; its from-scratch reference keeps the same. The copy
has the sweep's layout (runs beside `scratch/`), so `ccfit report DEST` finds everything and
rebuilds `DEST/report` byte for byte from the copied files alone. Every finished single-task
run (`ccfit train`) keeps the same files, and `DEST/learnability` holds `ccfit learnability`'s
tables over the published ones: the steps each task needed, from which the per-suite budgets
were set. Anything large is refused rather than silently committed. With `--root`, the folder
holding every published result, its `orderings.md`, `axes.md` and `cost.md` are rewritten over
all of them, so comparisons across published folders stay current; a publish after which the
root's runs could not be averaged (a seed published twice in one group) is refused. A refused
publish writes nothing. The copies hold no path of the machine that made them
(`ccfit.portable`): a path under RUNS is written relative to it (`out`, `scratch_dir`: the
layout the copy keeps), a dataset relative to the LeRobot home (its repo id), any other file
by its name (a frozen encoder, the code snapshot); the rest of each file is copied byte for
byte.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

from ccdata.errors import InputError
from ccfit.analysis.learnability import finished_task_runs, write_learnability
from ccfit.first_task import FIRST_RECORD
from ccfit.portable import portable, portable_json
from ccfit.report import group_metrics, group_runs, write_overview_of, write_report
from ccfit.report.cost import run_cost
from ccfit.report.runs import Run, find_runs, scratch_dir_of
from ccfit.run_files import (
    CONFIG,
    COST,
    METRICS_JSON,
    METRICS_JSONL,
    REFERENCE_DONE,
    REPORT,
    SCRATCH,
    SWEEP_JSON,
)

RUN_FILES = (CONFIG, METRICS_JSON, METRICS_JSONL, COST, "routing.jsonl", FIRST_RECORD)
"""What a published run keeps (those of them it has): settings, metrics, records, cost, and
where its first task came from (`ccfit.first_task`)."""
SCRATCH_FILES = (CONFIG, REFERENCE_DONE, METRICS_JSONL, COST)
MAX_FILE_BYTES = 2_000_000
"""A published file larger than this is refused: results are for small files only."""
TASK_RUN_FILES = (CONFIG, METRICS_JSONL, COST)
"""What a published single-task run keeps: all that `ccfit learnability` reads."""
LEARNABILITY = "learnability"


def publish(runs: Path, out: Path, root: Path | None = None) -> list[Path]:
    """Copy the small files of every finished run under `runs` (a curriculum's with its
    from-scratch reference's) to `out`, keeping paths relative to `runs`; write `out/report`
    over the curricula and `out/learnability` over the single-task runs; with `root` (a folder
    holding `out`), rewrite `root`'s overview (`write_overview`) over every run published under
    it. Returns the files written."""
    if not runs.is_dir():
        raise InputError(f"no such run folder: {runs}")
    if root is not None and not out.resolve().is_relative_to(root.resolve()):
        raise InputError(f"--root {root} does not hold --out {out}: its overview would not "
                         f"include what is published")  # fmt: skip
    curricula = _curricula_under(runs)
    task_runs = finished_task_runs(runs)
    if not curricula and not task_runs:
        raise InputError(f"no finished runs under {runs}: neither a curriculum (with "
                         f"metrics.json) nor a finished `ccfit train` run")  # fmt: skip
    placed = [(run, out / run.path.resolve().relative_to(runs.resolve())) for run in curricula]
    copies = []
    for run, dst in placed:
        copies += _files(run.path, dst, RUN_FILES)
        scratch = scratch_dir_of(run.path, run.metrics)
        copies += _files(scratch, dst.parent / SCRATCH / scratch.name, SCRATCH_FILES)
    for run in task_runs:
        copies += _files(run, out / run.resolve().relative_to(runs.resolve()), TASK_RUN_FILES)
    if (runs / SWEEP_JSON).is_file():
        copies += _files(runs, out, (SWEEP_JSON,))
    # Everything that can refuse is asked before the first file is written, so a refused
    # publish leaves `out` and the root's overview as they were.
    _check_sizes(copies)
    for src, _ in copies:  # the report reads each run's cost (the rest `find_runs` has read)
        if src.name == COST:
            run_cost(src.parent)
    machine_roots = (runs.resolve(), Path(os.path.abspath(runs)))
    if root is not None:
        _check_overview(root, placed, machine_roots)
    written = []
    for src, dst in copies:
        dst.parent.mkdir(parents=True, exist_ok=True)
        _copy(src, dst, machine_roots)
        written.append(dst)
    written = sorted(set(written))
    if curricula:
        written += _rewrite_report(out)
    if task_runs:
        written += write_learnability(finished_task_runs(out), out / LEARNABILITY)
    if root is not None:
        written += write_overview_of([root], root)
    return written


def _rewrite_report(out: Path) -> list[Path]:
    """`out/report` rebuilt whole: written beside it, then put in its place, so no file of an
    earlier report (a figure of a group that no longer exists) outlives it."""
    fresh, report = out / f".{REPORT}.new", out / REPORT
    shutil.rmtree(fresh, ignore_errors=True)
    try:
        written = write_report([out], fresh)
    except BaseException:
        shutil.rmtree(fresh, ignore_errors=True)
        raise
    shutil.rmtree(report, ignore_errors=True)
    fresh.rename(report)
    return [report / p.relative_to(fresh) for p in written]


def _curricula_under(folder: Path) -> list[Run]:
    """The finished curricula under `folder` (none where it holds no metrics.json)."""
    return find_runs([folder]) if any(folder.rglob(METRICS_JSON)) else []


def _files(src: Path, dst: Path, names: tuple[str, ...]) -> list[tuple[Path, Path]]:
    """(source, destination) of each of `names` that `src` holds."""
    return [(src / name, dst / name) for name in names if (src / name).is_file()]


def _copy(src: Path, dst: Path, roots: tuple[Path, ...]) -> None:
    """`src` copied to `dst`, a JSON (lines) file with its paths as published (`portable_json`:
    relative to `roots`, the run folder published, where they lie under it)."""
    if src.suffix in (".json", ".jsonl"):
        dst.write_text(portable_json(src.read_text(), roots))
    else:
        shutil.copyfile(src, dst)


def _check_sizes(copies: list[tuple[Path, Path]]) -> None:
    for src, _ in copies:
        size = src.stat().st_size
        if size > MAX_FILE_BYTES:
            raise InputError(f"{src} is {size} bytes: too large to publish "
                             f"(limit {MAX_FILE_BYTES})")  # fmt: skip


def _check_overview(root: Path, placed: list[tuple[Run, Path]],
                    machine_roots: tuple[Path, ...]) -> None:  # fmt: skip
    """Refuses (InputError) a publish after which the runs under `root` could not be averaged
    together (`group_metrics`: a seed twice in one group, say, from another folder under the
    root), each curriculum of `placed` taking the place of what its destination holds now,
    with its config as published (`portable`, paths relative to `machine_roots`)."""
    gone = {dst.resolve() for _, dst in placed}
    kept = [r for r in _curricula_under(root) if r.path.resolve() not in gone]
    new = [dataclasses.replace(run, config=portable(run.config, machine_roots))
           for run, _ in placed]  # fmt: skip
    for group in group_runs(kept + new).values():
        group_metrics(group)
