"""A replay buffer's rows on disk, written incrementally beside a checkpoint.

A checkpoint used to hold the whole buffer: at the paper's scale (a million 64 px rows, tens
of GB) every checkpoint would rewrite all of it. Here each checkpoint writes only the rows
added since the previous one, as files `replay/rows-<first>-<end>.pt` (write numbers) of at
most `file_rows` rows, and records the list of files it needs (its manifest) with the
buffer's small state. A file whose rows have all been overwritten leaves the manifest; the
rows of demonstrations it held (the buffer keeps those, `ReplayBuffer.demo_spans`) are
written again from the buffer's copy, into a file of their own marked `demo`. The disk thus
holds at most the ring's capacity, one file partly overwritten, and the demonstrations
(`disk_rows`). A file leaving the manifest is deleted only after the checkpoint that no
longer needs it is written, so the previous checkpoint stays readable until then. Files a
killed process wrote after its last checkpoint are not in any manifest and are deleted when
the run resumes.
"""

from __future__ import annotations

from pathlib import Path

from ccfit.io import atomic_torch_save, load_checkpoint
from ccfit.replay import ReplayBuffer
from ccfit.replay_state import uncovered

ROWS_DIR = "replay"
ROWS_KIND = "ccfit-replay-rows"
ROWS_VERSION = 1
MIN_FILE_ROWS = 10_000
FILE_SHARE = 16
"""A row file holds at most max(MIN_FILE_ROWS, capacity // FILE_SHARE) rows: the file the ring
has partly overwritten stays whole until all its rows are, so its size is disk held twice."""


def file_rows(capacity: int | None) -> int | None:
    """The most rows one row file of a buffer of `capacity` rows holds (None: no limit, for a
    buffer without a ring)."""
    return None if capacity is None else max(MIN_FILE_ROWS, capacity // FILE_SHARE)


def disk_rows(capacity: int, demo_rows: int = 0) -> int:
    """The most rows the row files of a buffer of `capacity` rows keeping `demo_rows` rows of
    demonstrations hold at once: the ring, one file it partly overwrote, the demonstrations."""
    return capacity + file_rows(capacity) + demo_rows


def save_rows(buffer: ReplayBuffer, run_dir: Path, manifest: list[dict]
              ) -> tuple[list[dict], list[Path]]:  # fmt: skip
    """Write the rows added since `manifest` (the previous checkpoint's); returns the new
    manifest and the files it no longer needs (delete them once it is saved)."""
    directory = Path(run_dir) / ROWS_DIR

    def needed(f: dict) -> bool:
        if f.get("demo"):
            return any(f["start"] < end and first < f["end"] for first, end in buffer.demo_spans)
        return f["end"] > buffer.oldest

    def write(start: int, end: int, rows: dict, demo: bool = False) -> None:
        name = f"rows-{start:012d}-{end:012d}{'-demo' if demo else ''}.pt"
        atomic_torch_save({"kind": ROWS_KIND, "version": ROWS_VERSION, "rows": rows},
                          directory / name)  # fmt: skip
        keep.append({"file": name, "start": start, "end": end, **({"demo": True} if demo else {})})

    keep = [f for f in manifest if needed(f)]
    stale = [directory / f["file"] for f in manifest if not needed(f)]
    start = max([f["end"] for f in keep if not f.get("demo")] + [buffer.oldest])
    step = file_rows(buffer.capacity) or max(1, buffer.written - start)
    for a in range(start, buffer.written, step):
        b = min(a + step, buffer.written)
        write(a, b, buffer.rows(a, b))
    for first, end in buffer.demo_spans:
        for a, b in uncovered(first, end, [(f["start"], f["end"]) for f in keep]):
            write(a, b, buffer.demo_rows(a, b), demo=True)
    return sorted(keep, key=lambda f: f["start"]), stale


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
