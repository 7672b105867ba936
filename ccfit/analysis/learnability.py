"""How many steps a model needs to learn each task: the budgets of the `cpu` preset.

`ccfit learnability RUNS --out DIR` reads single-task runs (`ccfit train`, one per task, model
and seed, long budgets, and the from-scratch references of curricula and sweeps; runs that
learn another way, `RECIPE` settings or any model setting off what their preset gives
(demonstrations oversampled or cloned, another replay capacity or precision, another model
size), pixels or a frozen encoder, are rows of their own, their model named with the settings)
and writes
`learnability.md` / `.csv`: per suite, task, model and seed, the first evaluated step
whose normalised return reached 50 and 80, the first of `STEADY` evaluations in a row at 80 or
more (`steady_80`: where `--train.stop_score=80` would end the run), the best and last score,
the mean of the last
`PLATEAU` evaluations (one evaluation of a few episodes swings with the policy's acting noise:
TD-MPC2's grasping by tens of points), the budget and what the run cost (`cost.json`), plus
`budgets.json`: per suite and model, the steps per task every task of the suite needs to reach
50 (the largest first step to 50 over its tasks and seeds, rounded up to the evaluation
interval), or None when a task never reached it within the run's budget. A run ended early by
`--train.stop_score` is finished; its budget column is still the steps it was given, its
`trained` column the step it ended at.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from pathlib import Path

from ccdata.errors import InputError
from ccfit.config import TaskRunConfig, TrainConfig, stop_reached
from ccfit.config_base import LEGACY_VALUES
from ccfit.config_parse import resolve
from ccfit.curriculum import REFERENCE_DONE
from ccfit.io import atomic_write_json, atomic_write_text, read_run_json
from ccfit.train import CONFIG, METRICS
from ccfit.train.cost import read_cost

THRESHOLDS = (50, 80)
RECIPE = ("demo_fraction", "buffer_capacity", "autocast", "episode_steps")
"""`--train.*` settings that change how a task is learnt: a run with one of them off its
preset's value is a row (and budget) of its own. Every `--model.*` setting counts likewise
(`_model_recipe`)."""
MODEL_RECIPE = ("demo_bc_coef",)
"""The `--model.*` settings compared where the preset's model cannot be rebuilt (a frozen
encoder's sizes come from its file); off is their value in every preset (`LEGACY_VALUES`)."""
PLATEAU = 5
"""Evaluations at the end of a run averaged into `last_5` (what the run ends at)."""
STEADY = TrainConfig.stop_evals
"""Evaluations in a row at 80 or more that make `steady_80` (as many as end a run early)."""


def first_step_at(records: list[dict], level: float) -> int | None:
    """Task step of the first evaluation whose normalised return is at least `level`."""
    for r in sorted(records, key=lambda r: r["task_step"]):
        if r["normalized_return"] is not None and r["normalized_return"] >= level:
            return int(r["task_step"])
    return None


def first_steady_at(records: list[dict], level: float, evals: int = STEADY) -> int | None:
    """Task step of the first of `evals` evaluations in a row whose normalised returns are all
    at least `level` (the `--train.stop_score` rule)."""
    ordered = sorted(records, key=lambda r: r["task_step"])
    scores = [r["normalized_return"] for r in ordered]
    for end in range(evals, len(ordered) + 1):
        if stop_reached(scores[:end], level, evals):
            return int(ordered[end - evals]["task_step"])
    return None


def _preset_value(cfg: dict, setting: str):
    """`--train.<setting>` of the run's preset (as configs older than the setting ran)."""
    legacy = LEGACY_VALUES.get(f"train.{setting}")
    if legacy is not None:
        return legacy
    default = next(f.default for f in dataclasses.fields(TrainConfig) if f.name == setting)
    return TrainConfig.PRESETS.get(cfg["preset"], {}).get(setting, default)


def _model_recipe(cfg: dict, task: str) -> list[str]:
    """`name=value` of each model setting the run ran with off what its preset gives that model
    now for its task and observations (sizes, planner, cloning). A `LEGACY_VALUES` setting the
    config leaves out ran at its legacy value (config.json drops a setting at that value), which
    a preset may since have changed: DreamerV3's runs from before the `cpu` preset weighted the
    state's reconstruction are rows of their own."""
    model = cfg["model"]
    if cfg.get("encoder"):
        off = {k: model.get(k, LEGACY_VALUES[f"model.{k}"]) for k in MODEL_RECIPE}
        return [f"{k}={v}" for k, v in off.items() if v != LEGACY_VALUES[f"model.{k}"]]
    if set(model) == {"type"}:
        return []
    choices = {k: cfg[k] for k in ("preset", "obs", "image_size") if k in cfg}
    # The model's settings that follow the run's episode length (TD-MPC2's) are the train
    # setting's (`RECIPE`), not the model's own.
    steps = cfg.get("train", {}).get("episode_steps", _preset_value(cfg, "episode_steps"))
    preset = resolve(TaskRunConfig, {**choices, "task": task, "model": {"type": model["type"]},
                                     "train": {"episode_steps": steps}})  # fmt: skip
    given = preset.to_dict()["model"]
    ran = {k: model[k] if k in model else LEGACY_VALUES[f"model.{k}"]
           for k in given if k in model or f"model.{k}" in LEGACY_VALUES}  # fmt: skip
    return [f"{k}={v}" for k, v in ran.items() if given[k] != v]


def read_run(run: Path) -> dict | None:
    """The learnability row of one `ccfit train` directory, or of a curriculum's from-scratch
    reference (the same single-task run of the suite's last task; None: neither, or not
    finished)."""
    config, metrics = run / CONFIG, run / METRICS
    if not (config.is_file() and metrics.is_file()):
        return None
    from ccdata import SUITES

    cfg = read_run_json(config, leave_out="the table")
    records = read_run_json(metrics, lines=True, leave_out="the table")
    if "train" not in cfg:  # the offline track's (`ccfit fit`): it scores predictions, not returns
        return None
    task = cfg.get("task")
    if task is None and (run / REFERENCE_DONE).is_file() and records:
        task = records[0].get("task")
    if task is None:
        return None
    steps = int(cfg["train"]["steps"])
    if not records:
        return None
    # Finished: at its budget, or ended early by `--train.stop_score` (decided on the
    # evaluations before the last one, the task's final evaluation at the step it ended).
    train = cfg["train"]
    stopped = train.get("stop_score") is not None and stop_reached(
        [r["normalized_return"] for r in records[:-1]], train["stop_score"], train["stop_evals"]
    )
    trained = max(int(r["task_step"]) for r in records)
    if trained < steps and not stopped:
        return None
    scores = [r["normalized_return"] for r in records if r["normalized_return"] is not None]
    cost = read_cost(run)
    model = cfg["model"]["type"]
    recipe = [
        f"{k}={cfg['train'][k]}"
        for k in RECIPE
        if cfg["train"].get(k, _preset_value(cfg, k)) != _preset_value(cfg, k)
    ]
    recipe += _model_recipe(cfg, task)
    if cfg.get("encoder"):  # through a frozen pretrained encoder: another problem to learn
        recipe.insert(0, "frozen encoder")
    if cfg.get("obs", "state") != "state":
        recipe.insert(0, cfg["obs"])
    if recipe:  # another way of learning: its rows and budgets are kept apart
        model += f" [{', '.join(recipe)}]"
    return {
        "suites": [s.name for s in SUITES.values() if task in s.task_ids],
        "task": task, "model": model, "seed": cfg["seed"],
        "preset": cfg["preset"], "obs": cfg["obs"], "budget": steps,
        "trained": trained,
        "eval_interval": int(cfg["train"]["eval_interval"]),
        **{f"steps_to_{t}": first_step_at(records, t) for t in THRESHOLDS},
        "steady_80": first_steady_at(records, 80),
        "best": max(scores) if scores else None, "last": scores[-1] if scores else None,
        f"last_{PLATEAU}": sum(scores[-PLATEAU:]) / len(scores[-PLATEAU:]) if scores else None,
        # A from-scratch reference trained in a worker records no cost.
        "cpu_hours": cost["cpu_s"] / 3600 if cost["segments"] else None, "run": str(run),
    }  # fmt: skip


def finished_task_runs(root: Path) -> list[Path]:
    """The finished single-task `ccfit train` runs under `root` (not a curriculum's from-scratch
    references, which are published with their curricula)."""
    found = sorted(p.parent for p in Path(root).rglob(CONFIG))
    return [p for p in found if "task" in read_run_json(p / CONFIG) and read_run(p) is not None]


def budgets(rows: list[dict]) -> dict:
    """{suite: {model: steps per task}} from the rows (see the module doc)."""
    from ccdata import SUITES

    out: dict = {}
    for suite in SUITES.values():
        for model in sorted({r["model"] for r in rows}):
            mine = [r for r in rows if r["model"] == model and suite.name in r["suites"]]
            if {r["task"] for r in mine} != set(suite.task_ids):
                continue  # not every task of the suite was measured
            firsts = [r["steps_to_50"] for r in mine]
            if any(f is None for f in firsts):
                need = None
            else:
                step = max(r["eval_interval"] for r in mine)
                need = int(math.ceil(max(max(firsts), 1) / step) * step)
            out.setdefault(suite.name, {})[model] = need
    return out


def write_learnability(runs: list[Path], out: Path) -> list[Path]:
    """The tables and budgets of every finished single-task run under `runs`."""
    found = sorted({p.parent for r in runs for p in Path(r).rglob("config.json")})
    rows = [row for row in (read_run(p) for p in found) if row is not None]
    if not rows:
        raise InputError(f"no finished `ccfit train` run under {', '.join(map(str, runs))}")
    rows.sort(key=lambda r: (r["suites"][0], r["task"], r["model"], r["seed"]))
    out.mkdir(parents=True, exist_ok=True)
    cols = ["suites", "task", "model", "seed", "budget", "trained", "steps_to_50", "steps_to_80",
            "steady_80", "best", "last", f"last_{PLATEAU}", "cpu_hours"]  # fmt: skip

    def cell(col: str, v) -> str:
        if v is None:
            return "not reached" if col.startswith(("steps_to", "steady")) else "n/a"
        if isinstance(v, list):
            return ", ".join(v)
        return f"{v:.2f}" if col == "cpu_hours" else f"{v:.1f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(cell(c, r[c]) for c in cols) + " |" for r in rows]
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(cols)
    writer.writerows([[";".join(r[c]) if c == "suites" else r[c] for c in cols] for r in rows])
    paths = [out / "learnability.md", out / "learnability.csv", out / "budgets.json"]
    atomic_write_text(paths[0], "\n".join(lines) + "\n")
    atomic_write_text(paths[1], text.getvalue())
    atomic_write_json(paths[2], budgets(rows))
    return paths
