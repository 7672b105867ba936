"""`ccfit publish`: the small files of finished runs, copied into a results folder with the
report over them, so a repository can ship its numbers without checkpoints or replay.

    ccfit publish ../runs/reach-tdmpc2 --out results/online/reach-tdmpc2

Every finished run under RUNS (a folder with metrics.json) keeps its configuration, metrics,
per-evaluation records and cost; its from-scratch reference keeps the same. The copy has the
sweep's layout (runs beside `scratch/`), so `ccfit report DEST` finds everything and rebuilds
`DEST/report` byte for byte from the copied files alone. Anything large is refused rather than
silently committed.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ccdata.errors import InputError
from ccfit.report import find_runs, scratch_dir_of, write_report
from ccfit.sweep.grid import SCRATCH, SCRATCH_DONE, SWEEP_JSON

RUN_FILES = ("config.json", "metrics.json", "metrics.jsonl", "cost.json", "routing.jsonl")
"""What a published run keeps (those of them it has): settings, metrics, records, cost."""
SCRATCH_FILES = ("config.json", SCRATCH_DONE, "metrics.jsonl", "cost.json")
MAX_FILE_BYTES = 2_000_000
"""A published file larger than this is refused: results are for small files only."""
REPORT = "report"


def publish(runs: Path, out: Path) -> list[Path]:
    """Copy the small files of every finished run under `runs` (and of its from-scratch
    reference) to `out`, keeping paths relative to `runs`; write `out/report`. Returns the
    files written."""
    written = []
    for run in find_runs([runs]):
        rel = run.path.resolve().relative_to(runs.resolve())
        written += _copy(run.path, out / rel, RUN_FILES)
        scratch = scratch_dir_of(run.path, run.metrics)
        written += _copy(scratch, out / rel.parent / SCRATCH / scratch.name, SCRATCH_FILES)
    if (runs / SWEEP_JSON).is_file():
        written += _copy(runs, out, (SWEEP_JSON,))
    return sorted(set(written)) + _rewrite_report(out)


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
