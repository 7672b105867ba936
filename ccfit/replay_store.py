"""A replay buffer's rows on disk, written incrementally beside a checkpoint.

A checkpoint used to hold the whole buffer: at the paper's scale (a million 64 px rows, tens
of GB) every checkpoint would rewrite all of it. Here each checkpoint writes only the rows
added since the previous one, as one file `replay/rows-<first>-<end>.pt` (write numbers),
and records the list of files it needs (its manifest) with the buffer's small state. A file
whose rows have all been overwritten leaves the manifest, unless it holds rows of a
demonstration (the buffer keeps those, `ReplayBuffer.demo_spans`; rows of one that the ring
overwrote before any checkpoint saved them get a file of their own, written from the buffer's
copy of the demonstration); a file leaving the manifest is deleted only after the
checkpoint that no longer needs it is written, so the previous checkpoint stays readable
until then. Files a killed process wrote after its last checkpoint are not in any manifest
and are deleted when the run resumes.
"""

from __future__ import annotations

from pathlib import Path

from ccfit.io import atomic_torch_save, load_checkpoint
from ccfit.replay import ReplayBuffer

ROWS_DIR = "replay"
ROWS_KIND = "ccfit-replay-rows"
ROWS_VERSION = 1


def save_rows(buffer: ReplayBuffer, run_dir: Path, manifest: list[dict]
              ) -> tuple[list[dict], list[Path]]:  # fmt: skip
    """Write the rows added since `manifest` (the previous checkpoint's); returns the new
    manifest and the files it no longer needs (delete them once it is saved)."""
    directory = Path(run_dir) / ROWS_DIR

    def needed(f: dict) -> bool:
        return f["end"] > buffer.oldest or any(
            f["start"] < end and first < f["end"] for first, end in buffer.demo_spans
        )

    def write(start: int, end: int, rows: dict) -> None:
        name = f"rows-{start:012d}-{end:012d}.pt"
        atomic_torch_save({"kind": ROWS_KIND, "version": ROWS_VERSION, "rows": rows},
                          directory / name)  # fmt: skip
        keep.append({"file": name, "start": start, "end": end})

    keep = [f for f in manifest if needed(f)]
    stale = [directory / f["file"] for f in manifest if not needed(f)]
    start = max([f["end"] for f in keep] + [buffer.oldest])
    if buffer.written > start:
        write(start, buffer.written, buffer.rows(start, buffer.written))
    for first, end in buffer.demo_spans:
        for a, b in _uncovered(first, end, keep):
            write(a, b, buffer.demo_rows(a, b))
    return sorted(keep, key=lambda f: f["start"]), stale


def _uncovered(first: int, end: int, files: list[dict]) -> list[tuple[int, int]]:
    """The ranges of rows first .. end - 1 that none of `files` holds."""
    gaps, row = [], first
    for f in sorted(files, key=lambda f: f["start"]):
        if f["start"] > row:
            gaps.append((row, min(f["start"], end)))
        row = max(row, f["end"])
        if row >= end:
            break
    if row < end:
        gaps.append((row, end))
    return [(a, b) for a, b in gaps if a < b]


def load_rows(buffer: ReplayBuffer, run_dir: Path, meta: dict, manifest: list[dict]) -> None:
    """Restore `buffer` from its saved state and the files of `manifest`; other row files in
    the directory (written after the checkpoint by a process that then died) are deleted."""
    directory = Path(run_dir) / ROWS_DIR
    wanted = {f["file"] for f in manifest}
    chunks = [
        (int(f["start"]), load_checkpoint(directory / f["file"], ROWS_KIND, ROWS_VERSION)["rows"])
        for f in manifest
    ]
    buffer.load_state(meta, chunks)
    for path in directory.glob("rows-*.pt") if directory.is_dir() else ():
        if path.name not in wanted:
            path.unlink()
