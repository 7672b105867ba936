"""A sweep's grid expanded into run configs, and its record `sweep.json`.

Every grid point (suite x model x method x seed) is a `ccfit run` config, or with
`--track offline` a `ccfit fit` config: the grid's values and the common options go through the
same `parse_cli` as the command, so a sweep accepts every option of it and validates it the
same way. An option of one model's or one method's config (`--method.retrain_steps=6000`, a
PackNet field) goes to the grid points whose model or method has that field. Runs go to
`RUNS/<name>` (named by their config); runs that differ only in the method share one
from-scratch reference in `RUNS/scratch/<scratch_key>`.

`sweep.json` holds the grid, each run's resolved config, its directory and scratch key, the
code version, and one entry per submission (launcher, job ids, job states when local). It
identifies the sweep: a folder that holds another one is refused.
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path

from ccdata.errors import InputError
from ccdata.slurm import code_version
from ccfit.config_base import LEGACY_VALUES, identity
from ccfit.io import atomic_write_json
from ccfit.run_files import (
    FIRST,
    FIRST_DONE,
    METRICS_JSON,
    OFFLINE,
    ONLINE,
    REFERENCE_DONE,
    SCRATCH,
    SWEEP_JSON,
    run_name,
)

SWEEP_VERSION = 1
STATUS_JSON = "status.json"

GRID_FLAGS = ("suite", "seed", "model.type", "method.type", "preset")
"""Run options the grid sets itself: giving them as common options is an error."""
REFUSED_FLAGS = ("out", "config_path")
TRACKS = (ONLINE, OFFLINE)
"""`ccfit run` curricula, or `ccfit fit` offline ones (`ccfit.offline`)."""


@dataclass(frozen=True)
class Grid:
    """What a sweep varies and what it shares."""

    suites: tuple[str, ...]
    """Suites, each learnt as one curriculum per (model, method, seed)."""
    models: tuple[str, ...]
    """Registered world models (`--model.type` values)."""
    methods: tuple[str, ...]
    """Registered continual methods (`--method.type` values)."""
    seeds: tuple[int, ...]
    """Run seeds (each run takes its seed from its config, never from a job index)."""
    preset: str = "cpu"
    """Size preset of every run."""
    args: tuple[str, ...] = ()
    """Common run options in `ccfit run` syntax (`--obs pixels --train.steps=2000`)."""
    plugins: tuple[str, ...] = ()
    """Modules imported before configs are built, here and in every job: they register world
    models or methods defined outside ccfit."""
    track: str = ONLINE
    """'online' (`ccfit run` curricula) or 'offline' (`ccfit fit`)."""

    def __post_init__(self) -> None:
        if self.track not in TRACKS:
            raise InputError(f"--track must be one of {', '.join(TRACKS)}, got {self.track!r}")
        for name in ("suites", "models", "methods", "seeds"):
            values = getattr(self, name)
            if not values:
                raise InputError(f"--{name} is empty")
            repeated = sorted({str(v) for v in values if values.count(v) > 1})
            if repeated:
                raise InputError(f"--{name} lists {', '.join(repeated)} more than once")
        for arg in self.args:
            flag = _flag_name(arg)
            if flag in GRID_FLAGS:
                plural = {"model.type": "models", "method.type": "methods"}.get(flag, flag + "s")
                hint = "--preset" if flag == "preset" else f"--{plural}"
                raise InputError(f"--{flag} is set by the sweep grid; use {hint}")
            if flag in REFUSED_FLAGS:
                raise InputError(
                    f"--{flag} is not a sweep option (runs go to RUNS/<name>; "
                    f"pass run options as flags)"
                )

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict) -> Grid:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def _flag_name(arg: str) -> str | None:
    if not arg.startswith("--"):
        return None
    return arg[2:].partition("=")[0].replace("-", "_")


@dataclass
class RunSpec:
    """One run of the sweep."""

    name: str
    """Directory name under RUNS, made from the config."""
    config: dict
    """The resolved config (`CurriculumConfig.to_dict()`), `out` = the run directory."""
    scratch_key: str
    """Its from-scratch reference: RUNS/scratch/<scratch_key>."""


@dataclass
class Sweep:
    """An expanded grid under `root`."""

    root: Path
    grid: Grid
    runs: list[RunSpec]
    code: dict = field(default_factory=dict)

    def run_dir(self, run: RunSpec) -> Path:
        return self.root / run.name

    def scratch_dir(self, key: str) -> Path:
        return self.root / SCRATCH / key

    def run_done(self, run: RunSpec) -> bool:
        return (self.run_dir(run) / METRICS_JSON).is_file()

    def scratch_done(self, key: str) -> bool:
        return (self.scratch_dir(key) / REFERENCE_DONE).is_file()

    def first_dir(self, key: str) -> Path:
        """The first task shared by the runs of scratch key `key` (`ccfit.first_task`)."""
        return self.root / FIRST / key

    def first_done(self, key: str) -> bool:
        return (self.first_dir(key) / FIRST_DONE).is_file()

    def scratch_configs(self) -> dict[str, dict]:
        """Scratch key -> the config of the first run that needs it (the method is ignored)."""
        out: dict[str, dict] = {}
        for run in self.runs:
            out.setdefault(run.scratch_key, run.config)
        return out

    def identity(self) -> dict:
        """What makes two sweeps the same: every run's config but where it is stored."""
        return {r.name: run_identity(r.config) for r in self.runs}

    def record(self) -> dict:
        """sweep.json without the submissions."""
        return {
            "version": SWEEP_VERSION,
            "grid": self.grid.to_dict(),
            "code": self.code,
            "runs": [
                {
                    "name": r.name,
                    "dir": r.name,
                    "scratch": f"{SCRATCH}/{r.scratch_key}",
                    "config": r.config,
                }
                for r in self.runs
            ],  # fmt: skip
        }


def import_plugins(plugins: tuple[str, ...] | list[str]) -> None:
    for module in plugins:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as e:
            raise InputError(f"plugin module {module!r} not found ({e})") from None


def expand(grid: Grid, root: str | Path) -> Sweep:
    """Every grid point's config, resolved and validated as `ccfit run` (or `ccfit fit`)
    does it."""
    from ccfit.config_parse import parse_cli
    from ccfit.tracks import TRACKS

    track = TRACKS[grid.track]

    import_plugins(grid.plugins)
    root = Path(root).resolve()
    scoped = _scoped_options(grid)
    runs = []
    # Seed-major: a sweep run in order (a local pool, an array) finishes every method of a
    # seed before the next seed, so a partly run sweep already compares all of them.
    for seed, suite, model, method in itertools.product(grid.seeds, grid.suites, grid.models,
                                                        grid.methods):  # fmt: skip
        argv = [f"--preset={grid.preset}", f"--suite={suite}", f"--seed={seed}",
                f"--model.type={model}", f"--method.type={method}",
                *point_args(grid.args, scoped, {"model": model, "method": method})]  # fmt: skip
        cfg = parse_cli(track.config_class, argv, prog="ccfit sweep")
        name = run_name(cfg, grid.track)
        cfg.out = str(root / name)
        run = track(cfg)  # completes the config with what the run's start reads (an encoder)
        runs.append(RunSpec(name, run.cfg.to_dict(), run.reference_key()))
    return Sweep(root, grid, runs, code_version())


def _options(args: tuple[str, ...]) -> list[list[str]]:
    """`args` cut into options: `--key=value`, `--key value` or a lone `--flag`."""
    out: list[list[str]] = []
    for a in args:
        if a.startswith("--") or not out or "=" in out[-1][0] or len(out[-1]) == 2:
            out.append([a])
        else:
            out[-1].append(a)
    return out


def _config_fields(group: str, name: str) -> set[str]:
    import ccfit.continual  # noqa: F401  (registers the methods)
    import ccfit.models  # noqa: F401  (registers the models)
    from ccfit.continual.base import method_config_class
    from ccfit.models.registry import config_class as model_config_class

    config_class = model_config_class if group == "model" else method_config_class
    return {f.name for f in dataclasses.fields(config_class(name))}


def _scoped_options(grid: Grid) -> dict[str, dict[str, set[str]]]:
    """Per `--model.FIELD` / `--method.FIELD` option that only some of the grid's models
    (methods) have: group -> FIELD -> the grid values having it. An option none of them has
    is left to `parse_cli`, which names it as unknown."""
    values = {"model": grid.models, "method": grid.methods}
    out: dict[str, dict[str, set[str]]] = {"model": {}, "method": {}}
    for option in _options(grid.args):
        group, _, name = (_flag_name(option[0]) or "").partition(".")
        if group not in values or not name or name == "type":
            continue
        name = name.partition(".")[0]
        having = {v for v in values[group] if name in _config_fields(group, v)}
        if having and having != set(values[group]):
            out[group][name] = having
    return out


def point_args(args: tuple[str, ...], scoped: dict[str, dict[str, set[str]]],
               point: dict[str, str]) -> list[str]:  # fmt: skip
    """The common options that apply to one grid point (`point`: its model and method)."""
    out: list[str] = []
    for option in _options(args):
        group, _, name = (_flag_name(option[0]) or "").partition(".")
        having = scoped.get(group, {}).get(name.partition(".")[0])
        if having is None or point[group] in having:
            out += option
    return out


# ================================================================================ sweep.json


def read_record(root: str | Path) -> dict | None:
    path = Path(root) / SWEEP_JSON
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{path} is not a sweep record: {e}") from None


def load_sweep(root: str | Path) -> tuple[Sweep, dict]:
    """The sweep recorded in `root` and its full record (with the submissions)."""
    record = read_record(root)
    if record is None:
        raise InputError(f"{root} holds no sweep (no {SWEEP_JSON})")
    runs = [RunSpec(r["name"], r["config"], r["scratch"].split("/", 1)[1])
            for r in record["runs"]]  # fmt: skip
    sweep = Sweep(Path(root).resolve(), Grid.from_dict(record["grid"]), runs, record["code"])
    return sweep, record


def run_identity(config: dict) -> dict:
    """What a run computes (`config_base.identity`), wherever it is stored."""
    return {k: v for k, v in identity(config).items() if k != "out"}


def check_same_sweep(sweep: Sweep, record: dict) -> tuple[int, ...]:
    """Refuse a folder whose sweep.json holds another sweep (other runs or other configs).

    A sweep may grow by seeds: where every recorded run is still in it, unchanged, and every
    new run is of a seed the record did not have, it is the same sweep with more seeds
    (returned, to be said), so 3 seeds become 5 in the folder that holds the first 3."""
    theirs = {r["name"]: run_identity(r["config"]) for r in record.get("runs", [])}
    ours = sweep.identity()
    if theirs == ours:
        return ()
    where = sweep.root / SWEEP_JSON
    added, removed = sorted(set(ours) - set(theirs)), sorted(set(theirs) - set(ours))
    changed = [name for name in theirs if name in ours and ours[name] != theirs[name]]
    old_seeds = {cfg.get("seed") for cfg in theirs.values()}
    new_seeds = {ours[name].get("seed") for name in added}
    if added and not removed and not changed and not new_seeds & old_seeds:
        return tuple(sorted(new_seeds))
    if changed:
        key, a, b = _first_difference(theirs[changed[0]], ours[changed[0]])
        # A setting missing from one side is at its legacy value there.
        a, b = (LEGACY_VALUES.get(key, v) if v is None else v for v in (a, b))
        what = f"run {changed[0]}: {key} is {b!r}, was {a!r}"
    else:
        what = "; ".join(
            filter(
                None,
                [
                    added and f"new runs {', '.join(added[:3])}",
                    removed and f"missing runs {', '.join(removed[:3])}",
                ],
            )
        )
    raise InputError(f"{where} holds a different sweep ({what}); use another --out")


def _first_difference(a, b, prefix: str = "") -> tuple[str, object, object]:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{prefix}{k}.")
    return prefix.rstrip("."), a, b


def write_record(sweep: Sweep, submissions: list[dict]) -> None:
    atomic_write_json(sweep.root / SWEEP_JSON, {**sweep.record(), "submissions": submissions})
