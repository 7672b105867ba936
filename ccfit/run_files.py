"""What a run directory holds, by file name, and how runs are named.

The one place the trainers, both curriculum tracks, the sweep, `ccfit publish` and the reports
read these names from. It imports nothing, so the light modules (the sweep's grid, the report)
can use it without importing torch.
"""

from __future__ import annotations

from pathlib import Path

CONFIG = "config.json"
"""The resolved config of a run, plus what it resolved to where it ran."""
METRICS_JSONL = "metrics.jsonl"
"""Every evaluation (online) or scoring (offline) record, one line each."""
METRICS_JSON = "metrics.json"
"""A finished curriculum's BWT, FWT and standard metrics."""
COST = "cost.json"
"""What a run cost, summed over the calls that ran it."""
CHECKPOINT = "checkpoint.pt"
"""A single task's trainer (online) or fitter (offline) state while it learns."""
REFERENCE_DONE = "done.json"
"""A from-scratch reference's records, written when it is finished (online and offline)."""
ONLINE_STATE = "curriculum.pt"
"""An online curriculum's state after its last finished task."""
OFFLINE_STATE = "fit.pt"
"""An offline curriculum's state after its last finished task."""
TASKS = "tasks"
"""Where a curriculum's task being learnt keeps its checkpoint (`task_dir`)."""
PROBED_ENCODER = "encoder.json"
"""Beside an encoder's probe (`ccfit probe-encoder --out`): the probed encoder's sidecar."""
SCRATCH = "scratch"
"""Beside a sweep's (or a lone curriculum's) runs: the from-scratch references, by key."""
FIRST = "first"
"""Beside a sweep's runs: the first tasks its seeds' runs share, by key (`ccfit.first_task`)."""
FIRST_DONE = "first.json"
"""A shared first task's record, written when it is trained to its close."""
FIRST_RECORD = "first_task.json"
"""A run that started from its sweep's shared first task: that task's record."""
SWEEP_JSON = "sweep.json"
"""A sweep's record: its grid, its runs and their submissions."""
REPORT = "report"
"""Beside a sweep's runs (and in a folder `ccfit publish` wrote): the report over them."""

ONLINE, OFFLINE = "online", "offline"
"""The curriculum tracks: learnt in the environment, or fitted on the dataset."""


def task_dir(run_dir: Path, index: int, task_id: str) -> Path:
    """Where task `index` of a curriculum keeps its checkpoint while it learns."""
    return Path(run_dir) / TASKS / f"{index}-{task_id}"


def run_name(cfg, track: str = ONLINE) -> str:
    """A curriculum run's directory name (`ccfit run`, `ccfit fit`, a sweep's runs) from its
    config: the grid values plus the shared obs and preset, and the track when not online."""
    name = f"{cfg.suite}-{cfg.model.type}-{cfg.method.type}-{cfg.obs}-{cfg.preset}-s{cfg.seed}"
    return name if track == ONLINE else f"{name}-{track}"


def task_run_name(cfg) -> str:
    """A single-task run's directory name (`ccfit train`) from its config."""
    return f"{cfg.task}-{cfg.model.type}-{cfg.obs}-{cfg.preset}-s{cfg.seed}"


def reference_name(suite: str, model: str, obs: str, preset: str, seed: int, digest: str,
                   track: str = ONLINE) -> str:  # fmt: skip
    """A from-scratch reference's directory name: what its key shows, then the first eight
    hex digits of the digest of its config (all a reference's records depend on)."""
    name = f"{suite}-{model}-{obs}-{preset}-s{seed}-{digest[:8]}"
    return name if track == ONLINE else f"{track}-{name}"
