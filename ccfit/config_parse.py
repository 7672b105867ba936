"""A run config from the command line (`parse_cli`), from nested plain data (`resolve`), or
from a saved config.json (`--config_path`): the preset's defaults first, what is given on top.

    cfg = parse_cli(CurriculumConfig, ["--suite", "Reach", "--method.type=ewc"])
    cfg = resolve(CurriculumConfig, {"suite": "Reach", "method": {"type": "ewc", "lam": 10}})
"""

from __future__ import annotations

import copy
import dataclasses
import json
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import draccus
from draccus.cfgparsing import parse_string

from ccdata.errors import InputError
from ccfit.config import BaseRunConfig, TrainConfig
from ccfit.config_argv import HELP, asks_for_help, missing_value, read_argv
from ccfit.config_base import (
    DEFAULTS,
    LEGACY_VALUES,
    PRESETS,
    ChoiceConfig,
    ConfigError,
    check,
)
from ccfit.continual.base import method_config_class
from ccfit.models import DEFAULT_MODEL
from ccfit.models.registry import config_class, model_names
from ccfit.obs import OBS_MODES


def preset_defaults(cls: type[BaseRunConfig], choices: dict[str, Any]) -> dict:
    """The nested plain-data defaults of `cls` for `choices`: preset, obs, image_size,
    model (its type) and method (its type), each `DEFAULTS[...]` unless given; and the
    preset of every other section with presets (`train`, an offline run's `fit`). A
    curriculum's training settings from state (steps per task, ...) are the model's measured
    budget for its suite at this preset (`ModelConfig.SUITE_TRAIN`) when it has one, with the
    model settings that budget was measured with (`ModelConfig.SUITE_MODEL`)."""
    model = getattr(cls, "DEFAULT_MODEL", DEFAULT_MODEL)  # a config class may choose its own
    c = {**DEFAULTS, "model": model, **{k: v for k, v in choices.items() if v is not None}}
    preset, model, method = c["preset"], c["model"], c["method"]
    check(preset in PRESETS, f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    mcls = config_class(model)
    check(preset in mcls.PRESETS, f"model {model!r} has no preset {preset!r}")
    out: dict[str, Any] = {
        "preset": preset, "obs": c["obs"], "image_size": c["image_size"],
        "model": {"type": model, **mcls.preset_fields(preset), "obs_mode": c["obs"],
                  "image_size": c["image_size"]},
    }  # fmt: skip
    out.update(_preset_sections(cls, preset))
    budget = vars(mcls).get("SUITE_TRAIN", {}).get(preset, {}).get(c.get("suite"))
    if budget is not None and "train" in out and c["obs"] == "state":  # measured on state
        out["train"].update(budget)
        out["model"].update(vars(mcls).get("SUITE_MODEL", {}).get(preset, {}).get(c["suite"], {}))
    if _has_method(cls):
        out["method"] = {"type": method, **method_config_class(method).preset_fields(preset)}
    return out


def budget_note(config: dict) -> str | None:
    """One line for a curriculum (`config`: its plain data, as config.json holds it) that trains
    a suite its model has no measured budget for at a preset where models measured budgets
    (`ModelConfig.SUITE_TRAIN`), with the preset's steps per task: those steps were never shown
    to suffice. None where the budget is measured, the steps were given, or no model measured
    any at this preset."""
    train, suite, preset = config.get("train"), config.get("suite"), config["preset"]
    model = config["model"]["type"]

    def budgets(name: str) -> dict:
        return vars(config_class(name)).get("SUITE_TRAIN", {}).get(preset) or {}

    if train is None or suite is None or not any(budgets(m) for m in model_names()):
        return None
    if config["obs"] == "state" and suite in budgets(model):
        return None
    steps = TrainConfig.PRESETS[preset]["steps"]
    if train["steps"] != steps:  # given: the user chose them
        return None
    measured = ", ".join(budgets(model)) or "none"
    return (
        f"{model} has no measured {preset!r} budget for {suite} from {config['obs']} "
        f"(measured from state: {measured}); each task trains the preset's "
        f"{steps} steps, which may not learn it (docs/learnability.md; "
        "--train.steps sets them)"
    )


def state_note(config: dict) -> str | None:
    """One line for a curriculum from state on a suite some of whose tasks are one MDP from
    state (`Suite.same_from_state`: they differ only in a colour): what such a run measures
    there. None elsewhere."""
    from ccdata.suites import get_suite

    suite = config.get("suite")
    if config.get("obs") != "state" or suite is None:
        return None
    named = get_suite(suite).same_from_state_text()
    if not named:
        return None
    return (
        f"from state, {suite}'s {named} are one task (they differ only in colours, which the "
        "state does not hold): the curriculum meets that task again, and what the suite "
        "composes is seen from pixels only (--obs pixels)"
    )


def curriculum_notes(config: dict) -> list[str]:
    """The note lines `ccfit run`, `fit` and `sweep` print before training (`budget_note`,
    `state_note`)."""
    return [note for note in (budget_note(config), state_note(config)) if note is not None]


def resolve[C: BaseRunConfig](cls: type[C], overrides: dict[str, Any]) -> C:
    """`cls` from nested plain data (`{"suite": ..., "model": {"type": NAME, ...}}`): the
    preset's defaults (preset, model and method types, obs and image size taken from
    `overrides`), then `overrides` on top. The programmatic twin of `parse_cli`."""
    return _decode(cls, _under_preset_defaults(cls, overrides))


def _under_preset_defaults(cls: type[BaseRunConfig], overrides: dict[str, Any]) -> dict:
    """`overrides` on top of the preset's defaults that its own choices (preset, obs, image
    size, suite, model and method types) select; a section given as anything but an object is
    refused."""
    for name in _sections(cls):
        check(isinstance(overrides.get(name, {}), dict),
              f"{name} must be an object of settings, got {overrides.get(name)!r}")  # fmt: skip
    choices = {k: overrides.get(k) for k in ("preset", "obs", "image_size", "suite")}
    choices.update(model=overrides.get("model", {}).get("type"),
                   method=overrides.get("method", {}).get("type"))  # fmt: skip
    if "model" in overrides:  # its copy of the run's obs and image size (`DERIVED`) is dropped
        model = overrides["model"]
        overrides = {**overrides, "model": {k: v for k, v in model.items() if k not in DERIVED}}
    return _deep_merge(preset_defaults(cls, choices), overrides)


def _sections(cls: type) -> list[str]:
    """The fields of `cls` that are groups of settings (dataclasses: model, method, train)."""
    return [n for n, t in typing.get_type_hints(cls).items() if dataclasses.is_dataclass(t)]


DERIVED = ("obs_mode", "image_size")
"""The model config's fields that hold the run's `obs` and `image_size`: derived from them
(`BaseRunConfig`), recorded in config.json, never an input (a config.json that holds them,
as every one does, is read without them)."""


def saved_config[C: BaseRunConfig](cls: type[C], run_dir: str | Path,
                                    name: str = "config.json") -> C:  # fmt: skip
    """`cls` from the config.json a run wrote in `run_dir`; ConfigError when there is none."""
    path = Path(run_dir) / name
    check(path.is_file(), f"{run_dir} is not a run directory (no {name})")
    return resolve(cls, _saved_fields(cls, path))


def _saved_fields(cls: type, path: Path) -> dict:
    """A saved config.json as plain data, `cls`'s fields only: it also records what was derived
    (e.g. the resolved seed dataset), and a curriculum's config may seed a single-task run."""
    check(not path.is_dir(), f"{path} is a folder: give its config.json")
    check(path.is_file(), f"config file not found: {path}")
    try:
        saved = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path} is not a JSON config: {e}") from None
    check(isinstance(saved, dict), f"{path} is not a JSON config: not an object")
    fields = {k: v for k, v in saved.items() if k in _field_names(cls)}
    return with_legacy_values(cls, fields) if RUN_RECORD in saved else fields


RUN_RECORD = "resolved_device"
"""A config.json key that only a run writes: a file holding it is a run's record, not a config
a user wrote."""


def with_legacy_values(cls: type, fields: dict) -> dict:
    """A run's recorded settings (`fields`, `cls`'s) with each `LEGACY_VALUES` setting the
    record leaves out at its legacy value: a run records every setting it has, so one it leaves
    out is newer than the run, which ran as that value says (not as today's preset would)."""
    hints = typing.get_type_hints(cls)
    out = copy.deepcopy(fields)
    for path, value in LEGACY_VALUES.items():
        section, _, leaf = path.rpartition(".")
        if not section or not isinstance(out.get(section), dict):
            continue  # a top-level record (not a setting), or a section the file leaves out
        kind = out[section].get("type")
        owner = {"model": config_class, "method": method_config_class}.get(section)
        owner_cls = owner(kind) if owner and kind else hints.get(section)
        if dataclasses.is_dataclass(owner_cls) and leaf in _field_names(owner_cls):
            out[section].setdefault(leaf, value)
    return out


def _field_names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _preset_sections(cls: type, preset: str) -> dict[str, dict]:
    """Field name -> preset values of `cls`'s sections that are plain dataclasses with
    `PRESETS` (what a registered type chooses, model and method, is handled apart)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        section = hints.get(f.name)
        if (
            isinstance(section, type)
            and dataclasses.is_dataclass(section)
            and not issubclass(section, ChoiceConfig)
            and hasattr(section, "PRESETS")
        ):
            out[f.name] = dict(section.PRESETS[preset])
    return out


def _has_method(cls: type) -> bool:
    return any(f.name == "method" for f in dataclasses.fields(cls))


def _deep_merge(base: dict, top: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in top.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            if "type" in v and v["type"] != out[k].get("type"):
                out[k] = {}  # another registered type: the old defaults do not apply
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> {'a.b.c': value}; lists and other unhashable leaves as JSON text. An
    empty dict adds no key (no options = options absent)."""
    if isinstance(config, dict):
        out: dict[str, Any] = {}
        for k, v in config.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    try:
        hash(config)
    except TypeError:
        return {prefix: json.dumps(config, sort_keys=True, default=str)}
    return {prefix: config}


def _decode[C: BaseRunConfig](cls: type[C], data: dict) -> C:
    try:
        return draccus.decode(cls, data)
    except draccus.utils.ParsingError as e:
        raise _as_config_error(e) from None


def _as_config_error(e: Exception) -> Exception:
    """draccus wraps what __post_init__ raised: surface a ConfigError's (any InputError's) own
    message; other parsing problems (wrong type, unknown field) are bad input too; anything
    else is a bug."""
    cause = e
    while cause is not None:
        if isinstance(cause, InputError):
            return ConfigError(str(cause))
        cause = cause.__cause__
    root = e
    while root.__cause__ is not None:
        root = root.__cause__
    if isinstance(root, draccus.utils.ParsingError | TypeError | ValueError):
        return ConfigError(str(e) if root is e else f"{e} ({root})")
    return root


MISPLACED = {
    "seed_dataset": "the offline track reads --dataset (a Hub repo id or a folder; default: "
                    "auto, the suite's own); --seed_dataset fills an online run's replay "
                    "(ccfit train, ccfit run)",
}  # fmt: skip
"""Options of one config command that scripts give another, and what that one reads instead."""


def parse_cli[C: BaseRunConfig](cls: type[C], argv: Sequence[str], prog: str | None = None) -> C:
    """`cls` from command-line arguments in draccus syntax (`--model.type=NAME --train.steps=10`;
    words in a name joined with `_` or `-`, `--image-size 32`). Defaults come from `--preset`
    (or from `--config_path FILE`, a saved config.json), flags override them. `--help` prints
    the config tree (draccus) and exits."""
    if asks_for_help(argv):
        print_help(cls, argv, prog)
    return parse_options(cls, read_argv(argv), prog)


def parse_options[C: BaseRunConfig](cls: type[C], options: dict[str, str | None],
                                    prog: str | None = None) -> C:  # fmt: skip
    """`cls` from the options `read_argv` read (name -> text): the preset's defaults (or those
    of `options["config_path"]`) as plain data, the options on top, typed by draccus."""
    options = dict(options)
    check(options.get("obs") in (None, *OBS_MODES), f"--obs must be one of {OBS_MODES}, got "
                                                    f"{options.get('obs')!r}")  # fmt: skip
    path = options.pop("config_path", None)
    if path:
        # what the file leaves out comes from the preset it names, as on the command line
        defaults = _under_preset_defaults(cls, _saved_fields(cls, Path(path)))
    else:
        size = options.get("image_size")  # a bad value is reported when typed below
        defaults = preset_defaults(cls, {
            "preset": options.get("preset"), "obs": options.get("obs"),
            "image_size": int(size) if size is not None and size.isdigit() else None,
            "model": options.get("model.type"), "method": options.get("method.type"),
            "suite": options.get("suite"),
        })  # fmt: skip
    for nested, top in (("model.obs_mode", "obs"), ("model.image_size", "image_size")):
        check(nested not in options, f"--{nested} follows the run's --{top}; set that instead")
    for name, kind in typing.get_type_hints(cls).items():
        value = (options.get(name) or "").strip()
        if isinstance(kind, type) and issubclass(kind, ChoiceConfig) and value:
            # a mapping (`--model '{type: pwm}'`) is draccus's; a bare name is a slip
            check(value.startswith("{"), f"--{name} is a group of options; its kind is chosen "
                                         f"with --{name}.type={value}")  # fmt: skip
    # each value is read as draccus reads a command line's (YAML: `10` a number, `{type: pwm}`
    # a mapping), then typed with the defaults by the same decoder as `resolve`
    given = draccus.utils.deflatten(
        {k: None if v is None else parse_string(v) for k, v in options.items()}
    )
    for name in _sections(cls):
        check(isinstance(given.get(name, {}), dict),
              f"--{name} is a group of options; set its fields (--{name}.FIELD=VALUE)")  # fmt: skip
    # through JSON as the defaults were read before (a tuple a list), so configs stay equal
    data = _overlaid(json.loads(json.dumps(defaults)), given)
    unknown = _unknown_option(cls, given, data)
    if unknown is not None:
        where = f" of {prog}" if prog else ""
        raise ConfigError(f"--{unknown} is not an option{where}: "
                          f"{MISPLACED.get(unknown, 'see --help')}")  # fmt: skip
    for name, value in options.items():  # after: an option that does not exist needs nothing
        if value is None:
            raise missing_value(name)
    return _decode(cls, data)


def _unknown_option(cls: type, given: dict, data: dict, prefix: str = "") -> str | None:
    """The first option in `given` (nested, as `data` holds it with the defaults) that is no
    field of `cls`'s tree, the model and method as `data` chooses them; None if all are."""
    names = {f.name for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key, value in given.items():
        if key not in names:
            return prefix + key
        kind, sub = hints[key], data.get(key)
        if not (isinstance(value, dict) and isinstance(sub, dict) and isinstance(kind, type)
                and dataclasses.is_dataclass(kind)):  # fmt: skip
            continue
        if issubclass(kind, draccus.ChoiceRegistry):
            if sub.get("type") not in kind.get_known_choices():
                continue  # an unknown kind: named as such when the config is built
            kind = kind.get_choice_class(sub["type"])
            value = {k: v for k, v in value.items() if k != "type"}
        found = _unknown_option(kind, value, sub, f"{prefix}{key}.")
        if found is not None:
            return found
    return None


def _overlaid(base: dict, top: dict) -> dict:
    """`top` over `base`, nested mappings merged key by key, anything else replaced (draccus's
    merge of a command line over a config file)."""
    out = dict(base)
    for k, v in top.items():
        both = isinstance(v, dict) and isinstance(out.get(k), dict)
        out[k] = _overlaid(out[k], v) if both else v
    return out


def print_help(cls: type, argv: Sequence[str], prog: str | None = None,
               switches: dict[str, str | None] | None = None) -> NoReturn:  # fmt: skip
    """Print `cls`'s config tree (draccus's help) for the model and method `argv` chooses, and
    exit 0. Only those choices are passed: draccus converts every value even when asked for
    help, and fails on optional fields (`--out DIR --help`)."""
    try:
        given = read_argv([a for a in argv if a not in HELP], switches)
    except InputError:  # a slip beside --help: the help is still what was asked for
        given = {}
    args = [f"--{k}={given[k]}" for k in ("model.type", "method.type") if k in given]
    draccus.parse(cls, args=[*args, "--help"], prog=prog)
    raise AssertionError("draccus --help did not exit")


def given_config_file(path: str | None) -> tuple[dict, Path] | None:
    """The saved config.json given as `--config_path` (`path`), whole, with what it recorded
    as resolved, and its path; None without one. Read after `parse_options`, which has refused
    a missing or malformed file."""
    return (json.loads(Path(path).read_text()), Path(path)) if path else None
