"""A process's children and whether a process has ended, read from Linux's /proc (for the
tests that interrupt a launcher and check that its workers end with it)."""

from __future__ import annotations

from pathlib import Path

PROC = Path("/proc")


def workers(pid: int) -> list[int]:
    """The processes whose parent is `pid`, less multiprocessing's resource tracker (which
    ends on its own once its parent has)."""
    found = []
    for stat in PROC.glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:  # ended while read
            continue
        if ppid == pid and b"resource_tracker" not in cmdline:
            found.append(int(stat.parent.name))
    return found


def ended(pid: int) -> bool:
    """Gone, or a zombie waiting for init to reap it."""
    try:
        state = (PROC / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return True
    return state == "Z"
