"""A curriculum branched from another run after its first K tasks.

"What if ER stopped replaying at the composition task?" asks for two runs that are the same
run up to task K and differ after it. A run started with `ccfit run --keep-stages` keeps its
state after every finished task (`stages/after-<K>.pt`: model, stored heads, method state,
RNG, as `curriculum.pt` holds it then). `ccfit run ... --branch-from SOURCE --branch-after K`
starts a new run directory from that state:

    curriculum.pt    the source's state after K tasks
    metrics.jsonl    the source's evaluation records of stages 0 .. K-1
    branch.json      the source, K and the sha256 of the state it started from

and from there it is an ordinary run at task K (it resumes, reports and publishes as any;
config.json records the branch as `resolved_branch`). Its config may differ from the source's
only in the options of the same continual method: up to task K it *is* the source run, so
anything else that differs (the model, the budget, the seed) would make its first K tasks a
record of another config. With the source's own config a branch reproduces the source's
later tasks record for record (tested).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from ccfit.config_base import ConfigError, identity
from ccfit.config_parse import flatten
from ccfit.io import atomic_write_json, file_sha256, read_run_json
from ccfit.train.records import METRICS, record_stage, write_records
from ccfit.train.run import CONFIG

STAGES = "stages"
BRANCH = "branch.json"
RECORD = "resolved_branch"
"""config.json's record of the branch a run started as."""


def stage_path(run_dir: Path, completed: int) -> Path:
    """Where a run started with `--keep-stages` keeps its state after `completed` tasks."""
    return Path(run_dir) / STAGES / f"after-{completed}.pt"


def keep_stage(run_dir: Path, state: Path, completed: int) -> None:
    """Copy the state just saved (`state`, after `completed` tasks) to its stage file."""
    target = stage_path(run_dir, completed)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(target.name + ".tmp")
    shutil.copyfile(state, tmp)
    os.replace(tmp, target)


@dataclass(frozen=True)
class Branch:
    """Where a branch starts: the source run's directory and the tasks it takes from it."""

    source: Path
    after: int

    def record(self) -> dict:
        """`resolved_branch` in config.json and branch.json's `source` and `after`."""
        return {"source": str(self.source.resolve()), "after": self.after}


def read_branch(run_dir: Path) -> dict | None:
    """branch.json of `run_dir` (None: not a branch)."""
    path = Path(run_dir) / BRANCH
    return read_run_json(path, leave_out="the run") if path.exists() else None


def start_branch(branch: Branch, resolved: dict, out: Path, num_tasks: int, state: str) -> None:
    """Make `out` the branch's run directory at task `branch.after` (see the module's
    docstring); `resolved`: the branch's config.json; `state`: the name of a run's saved
    state (`curriculum.STATE`). Refuses (ConfigError) what would not be
    the source run up to there. `out` already started as this branch: nothing to do."""
    out = Path(out)
    known = read_branch(out)
    if known is not None:
        if {k: known[k] for k in ("source", "after")} != branch.record():
            raise ConfigError(f"{out} is a branch of {known['source']} after {known['after']} "
                              "tasks, not of the one asked for; use another --out")  # fmt: skip
        return
    # A run writes config.json before it trains; without it `out` holds at most a branch
    # start that was killed before its branch.json, which starts again.
    if (out / CONFIG).exists():
        raise ConfigError(f"{out} already holds a run; a branch starts in a new --out")
    if not 1 <= branch.after < num_tasks:
        raise ConfigError(f"--branch-after must be in 1..{num_tasks - 1} (the tasks taken "
                          "from the source, at least one left to train), got "
                          f"{branch.after}")  # fmt: skip
    saved = branch.source / CONFIG
    if not saved.exists():
        raise ConfigError(f"--branch-from {branch.source}: no run there ({CONFIG} missing)")
    _check_same_run(read_run_json(saved, leave_out="--branch-from"), resolved, branch.source)
    stage = stage_path(branch.source, branch.after)
    if not stage.exists():
        raise ConfigError(f"--branch-from {branch.source}: it kept no state after {branch.after}"
                          " tasks (only a run started with --keep-stages keeps them, once "
                          "they are finished)")  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    source_metrics = branch.source / METRICS
    records = read_run_json(source_metrics, lines=True) if source_metrics.exists() else []
    write_records(out / METRICS, [r for r in records if record_stage(r) < branch.after])
    tmp = out / (state + ".tmp")
    shutil.copyfile(stage, tmp)
    digest = file_sha256(tmp)
    os.replace(tmp, out / state)
    # Written last: what a branch killed before this line wrote is written again.
    atomic_write_json(out / BRANCH, {**branch.record(), "state_sha256": digest})


def _check_same_run(source: dict, branch: dict, where: Path) -> None:
    """The branch's config equals the source's but for the options of the same method."""
    a, b = source.get("method", {}).get("type"), branch.get("method", {}).get("type")
    if a != b:
        raise ConfigError(f"--branch-from {where}: a branch keeps the source's method ({a}), "
                          f"got {b}; only its options may change")  # fmt: skip
    rest = [flatten({k: v for k, v in identity(c).items() if k not in ("method", RECORD)})
            for c in (source, branch)]  # fmt: skip
    differ = sorted(k for k in rest[0].keys() | rest[1].keys()
                    if rest[0].get(k) != rest[1].get(k))  # fmt: skip
    if differ:
        raise ConfigError(f"--branch-from {where}: the branch's config differs from the "
                          f"source's in {', '.join(differ)}; only --method.* options "
                          "may")  # fmt: skip
