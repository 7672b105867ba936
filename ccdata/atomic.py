"""The one atomic file write of the project: a temp file beside the target, then rename.

A reader (or a resumed run) sees the old file or the new one, never half of one, also after
the machine itself went down: the temp file's data is flushed to disk before the rename, and
the rename before returning (without, a crash may leave the new name on an empty file). ccfit
imports this too (ccdata never imports ccfit).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def atomic_write(path: str | Path, write: Callable[[str], object], mode: int = 0o644) -> None:
    """Call `write(tmp_path)` to fill a temp file in `path`'s directory, then rename it over
    `path`. The temp file is removed if `write` fails."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, mode)  # mkstemp files are private; outputs are meant to be shared
        _fsync(tmp, os.O_RDONLY)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync(path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))


def _fsync(path: str | Path, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_partial_writes(directory: str | Path, name: str) -> None:
    """Delete the temp files `atomic_write` was filling in `directory` for targets named
    `name` (a glob) when its process was killed; only for a directory no live process writes
    in (a run resuming its own)."""
    for tmp in Path(directory).glob(f".{name}.*.tmp"):
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write `text` to `path` atomically."""
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))
