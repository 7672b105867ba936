"""The runs `ccfit report` reads: a finished run's files (`Run`), how its config names the
table's axes (backbone, suite, method) and which of its settings may differ between the seeds
of one experiment (`PER_SEED`, `AS_RUN`): the one module the report's parts (`stages`,
`ccfit.publish`) share to name a run."""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ccdata.errors import InputError
from ccfit.config_base import (
    COMPILE_REASON,
    DATASET_RECORDS,
    EXECUTION_SETTINGS,
    drop_legacy_values,
)
from ccfit.config_parse import flatten
from ccfit.io import read_run_json
from ccfit.metrics import check_evaluated, task_curves
from ccfit.offline.fit import SCORE_KEY, TRACK
from ccfit.run_files import CONFIG, METRICS_JSON, ONLINE, REFERENCE_DONE
from ccfit.run_files import METRICS_JSONL as METRICS

PER_SEED = (
    "seed",
    "*.seed",
    "*_seed",
    "*.*_seed",
    "out",
    "*.out",
    "*_dir",
    "*.*_dir",
    "*_path",
    "*.*_path",
    "resolved_branch.source",
    "resolved_branch.state_sha256",
)
"""Flattened config keys (fnmatch patterns) that differ between the seeds of one experiment
and so do not split groups: the seed, seeds derived from it, where outputs went, the run (of
that seed) a branch started from (its `resolved_branch.after` does split them)."""
AS_RUN = ("resolved_compile", COMPILE_REASON, "resolved_seed_dataset", *DATASET_RECORDS,
          *EXECUTION_SETTINGS)  # fmt: skip
"""Records of how a run was computed, not of what: which of the model's functions this code
version compiled and why (eager and compiled compute the same within float tolerance), where
the seed dataset lay on the machine that ran it and what the run recorded of its datasets (runs
made before that record existed have none), how it spread over processes and where it logged. Seeds
run by two code versions, on two machines or with and without worker processes still
average."""
CURVE_KEYS = {ONLINE: "normalized_return", TRACK: SCORE_KEY}
"""Per track, what a record's curve value is."""
AXES = ("suite", "model", "method", "encoder", "track")
"""Settings that are the table's own axes (backbone, suite, method), never variant labels."""


def is_per_seed(key: str) -> bool:
    return any(key == s or key.startswith(f"{s}.") for s in AS_RUN) or any(
        fnmatch.fnmatchcase(key, p) for p in PER_SEED
    )


def _axis_name(config: dict, name: str) -> Any:
    """`config[name]`, or its 'type' / 'name' when the setting is a nested config."""
    value = config.get(name)
    if isinstance(value, dict):
        return value.get("type", value.get("name"))
    return value


def is_axis(key: str) -> bool:
    head, _, rest = key.partition(".")
    return head in AXES and rest in ("", "type", "name")


@dataclass
class Run:
    path: Path
    config: dict
    records: list[dict]
    scratch: list[dict]
    metrics: dict

    @property
    def track(self) -> str:
        """'online' (`ccfit run`) or 'offline' (`ccfit fit`)."""
        return self.metrics.get("track", ONLINE)

    @property
    def backbone(self) -> str:
        """The model (+frozen-enc), and -offline for the offline track: tracks never share a
        table or a figure."""
        return _axis_name(self.config, "model") + (
            "+frozen-enc" if _axis_name(self.config, "encoder") else "") + (
            f"-{TRACK}" if self.track == TRACK else "")  # fmt: skip

    @property
    def suite(self) -> str:
        return _axis_name(self.config, "suite")

    @property
    def method(self) -> str:
        """The continual method's type (its options are in `config['method']`)."""
        return _axis_name(self.config, "method")

    @property
    def key(self) -> tuple[str, str, str]:
        return self.backbone, self.suite, self.method

    @property
    def seed(self) -> int:
        flat = flatten(self.config)
        keys = sorted(
            (k for k in flat if k == "seed" or k.endswith(".seed")), key=lambda k: (k.count("."), k)
        )
        return int(flat[keys[0]]) if keys else 0

    @property
    def identity(self) -> dict[str, Any]:
        """The flattened config without what may differ between seeds (`PER_SEED`, `AS_RUN`)
        and without the settings at their legacy values (`LEGACY_VALUES`): a run that records
        one and a run made before it existed are the same experiment."""
        flat = flatten(drop_legacy_values(self.config))
        return {k: v for k, v in flat.items() if not is_per_seed(k)}


def find_runs(paths: list[Path]) -> list[Run]:
    dirs: list[Path] = []
    for p in paths:
        if not p.exists():
            raise InputError(f"no such run directory: {p}")
        dirs += [m.parent for m in sorted(p.rglob(METRICS_JSON))] if p.is_dir() else []
    if not dirs:
        where = ", ".join(map(str, paths))
        raise InputError(f"no finished runs (with {METRICS_JSON}) under {where}")
    runs = []
    for d in dict.fromkeys(dirs):
        metrics = read_run_json(d / METRICS_JSON)
        records = read_run_json(d / METRICS, lines=True)
        scratch = read_run_json(scratch_dir_of(d, metrics) / REFERENCE_DONE, records=True)
        runs.append(Run(d, read_run_json(d / CONFIG), records, scratch, metrics))
        _check_records(runs[-1])
    return runs


def _check_records(run: Run) -> None:
    """A run whose records lack an evaluation its metrics read (`check_evaluated`) is refused:
    the report would interpolate the score there instead."""
    n, key = len(run.metrics["task_ends"]), CURVE_KEYS[run.track]
    curves, scratch = task_curves(run.records, n, key), task_curves(run.scratch, n, key)[-1]
    try:
        check_evaluated(curves, run.metrics["task_ends"], scratch, run.metrics["budget"])
    except ValueError as e:
        raise InputError(f"{run.path}: {e}") from None


def scratch_dir_of(run_dir: Path, metrics: dict) -> Path:
    """The run's from-scratch reference: the one beside the run (`<run>/../scratch/<key>`,
    where a sweep keeps it and `ccfit publish` copies it) or else where the run wrote it. The
    copy beside comes first: a published tree is read from itself even on the machine whose
    paths its metrics.json names."""
    stored = Path(metrics["scratch_dir"])
    beside = run_dir.parent / "scratch" / stored.name
    for where in (beside, stored):
        if (where / REFERENCE_DONE).is_file():
            return where
    raise InputError(f"{run_dir}: its from-scratch reference {stored} is missing")
