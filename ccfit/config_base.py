"""The base of every ccfit config: validation, preset names, the run defaults, the device.

A leaf module (it imports nothing from ccfit), so the run config tree (`ccfit.config`), the
world-model configs (`ccfit.models`) and the continual-method configs (`ccfit.continual`) all
build on it without importing each other:

    ConfigError, check, check_types   bad input -> one line, exit 2 (the CLIs print it)
    ChoiceConfig                      a config chosen by registered type (`--model.type=...`),
                                      with option defaults per size preset
    PRESETS, DEFAULTS                 preset names; what a run uses when nothing is said
    resolve_device                    'auto' | 'cpu' | 'cuda[:N]' -> the torch device used
                                      (called by `ccfit.settings.resolve_execution` alone)
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from typing import Any, ClassVar

import torch

from ccdata.errors import InputError

PRESETS: tuple[str, ...] = ("smoke", "cpu", "paper")
"""Preset names every model config defines (a model may add more, e.g. its sizes)."""

DEFAULTS: dict[str, Any] = {
    "method": "ft",
    "preset": "cpu",
    "obs": "state",
    "image_size": 64,
}
"""What a run uses when the command line (or a dict given to `resolve`) does not say: the one
source of these defaults for `parse_cli`, `resolve` and the config classes' field defaults.
The default world model is `ccfit.models.DEFAULT_MODEL` (models are named only there)."""


class ConfigError(InputError):
    """Bad user input in a config (unknown name, out-of-range value, contradiction): the CLI
    prints it on one line and exits 2. Anything else raised while building is a bug."""


def check(ok: bool, message: str) -> None:
    """Raise ConfigError(message) unless `ok`: the one-liner configs validate with."""
    if not ok:
        raise ConfigError(message)


def suite_tasks(suite: str) -> list[str]:
    """The suite's task ids in curriculum order (the composition last); ConfigError for a suite
    that does not exist."""
    from ccdata.suites import get_suite

    try:
        return list(get_suite(suite).task_ids)
    except InputError as e:
        raise ConfigError(str(e)) from None


_SIMPLE = {int: (int,), float: (int, float), bool: (bool,), str: (str,), type(None): (type(None),)}
_HINTS: dict[type, dict[str, Any]] = {}


def check_types(config: Any, finite: bool = False) -> None:
    """ConfigError naming the field when a value does not have its annotated simple type
    (int, float, bool, str, or unions of them with None); other annotations are skipped.
    `finite`: a float must also be finite (a hyperparameter of inf or nan is never meant:
    `--model.train_ratio=inf` looped forever, `--model.lr=inf` trained to NaN weights)."""
    cls = type(config)
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    hints = _HINTS[cls]
    for f in dataclasses.fields(config):
        parts = getattr(hints.get(f.name), "__args__", None) or (hints.get(f.name),)
        if not all(p in _SIMPLE for p in parts):
            continue
        allowed = tuple(t for p in parts for t in _SIMPLE[p])
        value = getattr(config, f.name)
        if isinstance(value, bool) and bool not in allowed:
            allowed = ()  # True is an int to Python, not to a config
        check(isinstance(value, allowed),
              f"{cls.__name__}.{f.name} must be {f.type}, got {value!r}")  # fmt: skip
        if finite and isinstance(value, float):
            check(math.isfinite(value), f"{cls.__name__}.{f.name} must be finite, got {value!r}")


class Presets:
    """A config dataclass with size presets (`--preset`): `PRESETS` maps a preset name to the
    fields it sets; a name of `PRESETS` (the module's) that it does not list sets nothing."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {}

    @classmethod
    def preset_fields(cls, name: str) -> dict[str, Any]:
        """The fields preset `name` sets ({} for a preset this config does not tune)."""
        return dict(cls.PRESETS.get(name, {}))

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> Any:
        """This config at preset `name`, then `overrides`."""
        check(name in cls.PRESETS or name in PRESETS,
              f"unknown preset {name!r}; valid: "
              f"{', '.join(dict.fromkeys([*PRESETS, *cls.PRESETS]))}")  # fmt: skip
        return cls(**{**cls.preset_fields(name), **overrides})


class ChoiceConfig(Presets):
    """A config picked by its registered name (`--model.type=NAME`, `--method.type=ewc`):
    the base of each kind's config, listed with `draccus.ChoiceRegistry` (draccus needs that
    one as a direct base, and it gives each kind its own registry):

        @dataclass
        class ModelConfig(ChoiceConfig, draccus.ChoiceRegistry): ...

    Subclasses are dataclasses with `PRESETS` (`Presets`)."""

    @property
    def type(self) -> str:
        """The registered name (what `--<group>.type` selects)."""
        return self.get_choice_name(type(self))  # from draccus.ChoiceRegistry


def resolve_device(name: str | torch.device) -> torch.device:
    """The device a run uses: 'auto' = CUDA when available, else the CPU; any other name is
    torch's ('cpu', 'cuda', 'cuda:1', 'meta'). The one place a device name is resolved, called
    by `ccfit.settings.resolve_execution` (what it returns is what a run records)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    check(device.type != "cuda" or torch.cuda.is_available(),
          f"device {str(device)!r} requested but CUDA is not available; use 'cpu' or "
          "'auto'")  # fmt: skip
    return device


LEGACY_VALUES: dict[str, Any] = {
    "train.demo_fraction": 0.0, "resolved_autocast": "off", "train.stop_score": None,
    "train.stop_evals": 3, "train.keep_backbone_optimizer": False,
    "train.end_eval_episodes": None, "train.episode_steps": 250,
    "fit.keep_backbone_optimizer": False, "fit.autocast": "off", "model.demo_bc_coef": 0.0,
    "model.imag_cont": "mode", "model.demo_bc_loss": "mse", "model.keypoints": 0,
    "model.image_trunk": "stacked",
    "model.state_recon_scale": 1.0,
}  # fmt: skip
"""Settings added after runs were made, each with the value that reproduces what runs did
before it existed. A setting at that value is left out wherever configs are compared or hashed
(config.json, sweep.json, checkpoints, the from-scratch key), so a run or sweep written before
it resumes under newer code, and a new one at that value is the same as the old."""


def without_setting(config: dict, path: str, only_if: Any = ...) -> dict:
    """A copy of the nested dict `config` without the setting at dotted `path` (when it is
    there and, given `only_if`, holds that value); the dicts on the way are copied, the input
    is unchanged."""
    *parents, leaf = path.split(".")
    out = node = dict(config)
    for key in parents:
        if not isinstance(node.get(key), dict):
            return out
        node[key] = node = dict(node[key])
    if leaf in node and (only_if is ... or node[leaf] == only_if):
        del node[leaf]
    return out


DATASET_RECORDS = ("resolved_seed_dataset_meta", "resolved_dataset_meta")
"""config.json keys of what a run's dataset held (online: the seed dataset; offline: the
fitted one), recorded for the reader."""
ENCODER_RECORD = "resolved_encoder_sha256"
"""config.json key of the SHA-256 of a run's frozen encoder file (`--encoder frozen:PATH`). A
resume checks it (`check_same_encoder`): another file at the same path is another run."""
EXECUTION_SETTINGS = ("log", "train.parallel", "train.env_workers")
"""config.json settings of how a run is executed, not of what it computes: where it logs and how
it spreads over processes (a parallel run's records equal the serial run's:
`tests/test_parallel.py`). Runs that differ only in these are the same experiment."""
COMPILE_REASON = "resolved_compile_reason"
"""config.json key of why `resolved_compile` holds what it does (`compile_choice`): a note for
the reader, no part of the run's identity."""
NOT_IDENTITY = (*EXECUTION_SETTINGS, "out", *DATASET_RECORDS, ENCODER_RECORD, COMPILE_REASON)
"""config.json settings a run may change when it is resumed (`EXECUTION_SETTINGS`, where its
directory now is), and what it records of its datasets and encoder for the reader (runs made
before those records existed resume; the encoder's is checked apart, where both configs hold
it)."""


def identity(resolved: dict) -> dict:
    """A run's config (config.json) as far as it decides what the run computes: without the
    `NOT_IDENTITY` settings and the settings at their legacy values (`drop_legacy_values`),
    as JSON reads it back."""
    out = drop_legacy_values(json.loads(json.dumps(resolved)))
    for path in NOT_IDENTITY:
        out = without_setting(out, path)
    return out


def drop_legacy_values(config: dict, prefix: str = "") -> dict:
    """`config` (a nested dict; `prefix`: where it sits, e.g. 'train.') without the
    `LEGACY_VALUES` settings that hold their legacy value; a copy, the input is unchanged."""
    for path, value in LEGACY_VALUES.items():
        if path.startswith(prefix):
            config = without_setting(config, path[len(prefix) :], only_if=value)
    return config
