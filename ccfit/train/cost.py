"""What a run cost: `cost.json` in its run directory, wall and CPU seconds, summed over every
process that ran it (the training process and its worker processes) and over resumptions,
which code ran each segment (a run resumed under newer code says so) and on what kind of CPU
(the same seed takes other rounding paths on a CPU whose vector kernels differ, so a run
resumed on another machine kind, or compared with one made there, says so).

A resumed run adds to what is recorded. While a segment runs, its cost so far is written every
`FLUSH_S` seconds, so a process killed without warning (a session's end, a SLURM timeout's
SIGKILL) leaves its segment counted up to its last flush; only the minute before it died is
lost."""

from __future__ import annotations

import json
import platform
import resource
import sys
import threading
import time
from pathlib import Path

import torch

from ccdata.processes import available_cores
from ccdata.slurm import code_version
from ccfit.io import atomic_write_json
from ccfit.run_files import COST
from ccfit.settings import cpu_info

FLUSH_S = 60.0
"""Seconds between writes of a running segment's cost so far."""


def _cpu() -> float:
    """CPU seconds of this process and of its children that have ended."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    return total


class RunCost:
    """Context manager: adds the wall and CPU time spent in the block (the block's own worker
    processes included, once they ended) to `cost.json`, every `flush_s` seconds while it
    runs (from a background thread) and once more on exit, also by an exception."""

    def __init__(self, run_dir: str | Path, flush_s: float = FLUSH_S) -> None:
        self.path = Path(run_dir) / COST
        self.flush_s = flush_s

    def __enter__(self) -> RunCost:
        # what earlier segments recorded, a killed one's up to its last flush
        self._before = read_cost(self.path.parent)
        self._code, self._machine = running_code(), running_machine()
        note = moved_note(self._before["machines"], self._machine)
        if note:
            print(f"ccfit: note: {self.path.parent}: {note}", file=sys.stderr)
        self._wall, self._cpu = time.monotonic(), _cpu()
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_until_stopped, daemon=True,
                                         name="ccfit-cost")  # fmt: skip
        self._flusher.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._flusher.join()
        self._write()

    def _flush_until_stopped(self) -> None:
        while not self._stop.wait(self.flush_s):
            self._write()

    def _write(self) -> None:
        if not self.path.parent.is_dir():
            return  # the run never started (bad input): nothing was spent on it
        before = self._before
        atomic_write_json(self.path, {
            "wall_s": before["wall_s"] + time.monotonic() - self._wall,
            "cpu_s": before["cpu_s"] + _cpu() - self._cpu,
            "segments": before["segments"] + 1,
            "code": [*before["code"], self._code],
            "machines": [*before["machines"], self._machine_now()],
        })  # fmt: skip

    def _machine_now(self) -> dict:
        """The segment's machine, its GPU's name once the run has put CUDA to use (asked
        earlier, it would initialise CUDA in a process that forks workers afterwards)."""
        if self._machine["gpu"] is None and torch.cuda.is_initialized():
            self._machine["gpu"] = torch.cuda.get_device_name()
        return self._machine


def running_code() -> dict:
    """The code of this process: ccbench's version, git describe and commit of its source
    tree (None outside a checkout), torch's version."""
    code = code_version()
    return {"package": code["package"], "git": code["git"], "commit": code["commit"],
            "torch": torch.__version__}  # fmt: skip


def running_machine() -> dict:
    """What of this machine decides a run's floating-point results: the CPU model, the vector
    instruction set torch's CPU kernels dispatch to (`ATEN_CPU_CAPABILITY` can lower it), the
    cores this process may use, and the GPU (None here: `RunCost` names it once the run
    uses CUDA)."""
    return {"cpu": _cpu_model(), "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "cores": available_cores(), "gpu": None}  # fmt: skip


def moved_note(earlier: list[dict], machine: dict) -> str | None:
    """A line for a run resumed on another kind of CPU than its last segment's (model or
    vector instruction set): from here on it rounds differently, so it reproduces neither an
    uninterrupted run there nor one here. None when the kind is the same or not recorded."""
    if not earlier:
        return None
    last = earlier[-1]
    if (last["cpu"], last["cpu_capability"]) == (machine["cpu"], machine["cpu_capability"]):
        return None
    return (f"resumed on {machine['cpu']} ({machine['cpu_capability']}); its last segment ran "
            f"on {last['cpu']} ({last['cpu_capability']}), so from here on it rounds otherwise "
            "and reproduces an uninterrupted run on neither")  # fmt: skip


def _cpu_model() -> str | None:
    """The CPU's model name (/proc/cpuinfo on Linux), else what `platform` knows, or None."""
    return cpu_info().get("model name") or platform.processor() or None


def read_cost(run_dir: str | Path) -> dict:
    """{'wall_s', 'cpu_s', 'segments', 'code', 'machines'} of a run directory (zeros when
    none is recorded); 'code' lists the code of each segment (`running_code`) in order and
    'machines' the machine of each (`running_machine`), each recorded since cost.json holds it
    (older files list none: the lists name the last segments)."""
    path = Path(run_dir) / COST
    if not path.is_file():
        return {"wall_s": 0.0, "cpu_s": 0.0, "segments": 0, "code": [], "machines": []}
    return {"code": [], "machines": [], **json.loads(path.read_text())}
