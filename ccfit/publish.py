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
all of them, so comparisons across published folders stay current.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ccdata.errors import InputError
from ccfit.analysis.learnability import finished_task_runs, write_learnability
from ccfit.curriculum import METRICS_JSON
from ccfit.report import find_runs, scratch_dir_of, write_overview_of, write_report
from ccfit.sweep.grid import SCRATCH, SCRATCH_DONE, SWEEP_JSON

RUN_FILES = ("config.json", "metrics.json", "metrics.jsonl", "cost.json", "routing.jsonl")
"""What a published run keeps (those of them it has): settings, metrics, records, cost."""
SCRATCH_FILES = ("config.json", SCRATCH_DONE, "metrics.jsonl", "cost.json")
MAX_FILE_BYTES = 2_000_000
"""A published file larger than this is refused: results are for small files only."""
TASK_RUN_FILES = ("config.json", "metrics.jsonl", "cost.json")
"""What a published single-task run keeps: all that `ccfit learnability` reads."""
REPORT = "report"
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
    curricula = find_runs([runs]) if any(runs.rglob(METRICS_JSON)) else []
    task_runs = finished_task_runs(runs)
    if not curricula and not task_runs:
        raise InputError(f"no finished runs under {runs}: neither a curriculum (with "
                         f"metrics.json) nor a finished `ccfit train` run")  # fmt: skip
    written = []
    for run in curricula:
        rel = run.path.resolve().relative_to(runs.resolve())
        written += _copy(run.path, out / rel, RUN_FILES)
        scratch = scratch_dir_of(run.path, run.metrics)
        written += _copy(scratch, out / rel.parent / SCRATCH / scratch.name, SCRATCH_FILES)
    for run in task_runs:
        written += _copy(run, out / run.resolve().relative_to(runs.resolve()), TASK_RUN_FILES)
    if (runs / SWEEP_JSON).is_file():
        written += _copy(runs, out, (SWEEP_JSON,))
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
    written = write_report([out], fresh)
    shutil.rmtree(report, ignore_errors=True)
    fresh.rename(report)
    return [report / p.relative_to(fresh) for p in written]


def _copy(src: Path, dst: Path, names: tuple[str, ...]) -> list[Path]:
    dst.mkdir(parents=True, exist_ok=True)
    copied = []
    for name in names:
        f = src / name
        if not f.is_file():
            continue
        size = f.stat().st_size
        if size > MAX_FILE_BYTES:
            raise InputError(f"{f} is {size} bytes: too large to publish "
                             f"(limit {MAX_FILE_BYTES})")  # fmt: skip
        shutil.copyfile(f, dst / name)
        copied.append(dst / name)
    return copied
