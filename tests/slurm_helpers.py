"""What the tests marked `slurm` ask the cluster directly (sacct, sinfo), independently of the
code under test: job rows once jobs have ended, and the partitions there are; and a PATH
that holds only some of the SLURM commands."""

from __future__ import annotations

import shutil
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest

FINAL_STATES = {
    "COMPLETED",
    "FAILED",
    "CANCELLED",
    "TIMEOUT",
    "OUT_OF_MEMORY",
    "NODE_FAIL",
    "BOOT_FAIL",
    "DEADLINE",
    "PREEMPTED",
}
JOB_WAIT_S = 420
"""How long `wait_for` waits for jobs to end (a loaded 2-core machine runs them slowly)."""


def sacct(ids: list[str]) -> dict[str, dict]:
    """sacct's row of each job of `ids` it knows (by job id, array tasks as `A_i`): its state,
    start and end (ISO stamps, or `Unknown`/`None` before it started or ended) and exit code."""
    out = subprocess.run(["sacct", "-n", "-X", "-P", "-j", ",".join(ids),
                          "-o", "JobID,State,Start,End,ExitCode"],
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    rows = {}
    for line in out.splitlines():
        job, state, start, end, code = line.split("|")
        rows[job] = {"state": state.split()[0], "start": start, "end": end, "exit": code}
    return rows


def wait_for(ids: list[str], timeout_s: float = JOB_WAIT_S) -> dict[str, dict]:
    """sacct rows of `ids` once all of them have ended (sacct may lag a poll behind)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        rows = sacct(ids)
        if all(rows.get(j, {}).get("state") in FINAL_STATES for j in ids):
            return rows
        time.sleep(2)
    pytest.fail(f"jobs {ids} did not end in {timeout_s} s: {sacct(ids)}")


def when(stamp: str) -> datetime:
    """A start or end stamp of a `sacct` row as a time."""
    return datetime.fromisoformat(stamp)


def partitions() -> set[str]:
    """The cluster's partitions (the default one without its `*`); none when sinfo does not
    answer."""
    try:
        done = subprocess.run(["sinfo", "-h", "-o", "%P"], capture_output=True, text=True,
                              timeout=30)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return set()
    return {p.rstrip("*") for p in done.stdout.split()} if done.returncode == 0 else set()


def bin_with(folder: Path, *tools: str) -> Path:
    """`folder` made to hold links to these SLURM commands only: a PATH without the others."""
    folder.mkdir()
    for tool in tools:
        (folder / tool).symlink_to(shutil.which(tool))
    return folder
