"""The typed config tree of a run, on draccus (LeRobot's config library).

    ccfit run --suite Reach --preset cpu --model.type=pwm --model.router=state \
        --method.type=ewc --method.lam=5000 --train.steps=6000

A run config has top-level fields (suite or task, obs, seed, preset, out, ...) and three
sub-configs chosen by registered type: `model` (`ccfit.models.registry.ModelConfig`),
`method` (`ccfit.continual.base.MethodConfig`) and `train` (`TrainConfig`). A preset fills the
defaults of all three, flags override them, `__post_init__` validates, and the resolved config
is saved as `config.json` beside every output; `--config_path config.json` reads one back.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import draccus

from ccfit.config_base import (
    DEFAULTS,
    DEVICES,
    PRESETS,
    ConfigError,
    check,
    check_types,
)
from ccfit.continual.base import MethodConfig, method_config_class
from ccfit.models.registry import ModelConfig, config_class, model_class
from ccfit.obs import OBS_MODES


@dataclass
class TrainConfig:
    """The online loop on one task (Algorithm 1's inner loop). Batch size, sequence length,
    update ratio and optimisers are the model's recipe (`--model.*`)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "smoke": dict(steps=600, seed_steps=300, eval_interval=300, eval_episodes=1,
                      checkpoint_interval=300, buffer_capacity=5_000),
        "cpu": dict(steps=6_000, seed_steps=1_000, eval_interval=1_000, eval_episodes=5,
                    checkpoint_interval=1_000, buffer_capacity=50_000),
        "paper": dict(steps=1_000_000, seed_steps=5_000, eval_interval=10_000, eval_episodes=10,
                      checkpoint_interval=50_000, buffer_capacity=1_000_000, torch_threads=0),
    }  # fmt: skip

    steps: int = 100_000
    """Environment (agent) steps on each task."""
    seed_steps: int = 5_000
    """Initial steps with uniformly random actions (the model observes them). Updates start
    after them, once replay holds a full window."""
    eval_interval: int = 10_000
    """Evaluate every this many task steps (and at step 0 and at the end)."""
    eval_episodes: int = 10
    """Episodes per evaluation, on a fixed set of layouts (the same at every evaluation)."""
    checkpoint_interval: int = 50_000
    """Write a resumable checkpoint every this many task steps (and at the end)."""
    checkpoint_minutes: float = 10.0
    """Also checkpoint at the first episode end after this many minutes of wall clock since
    the last checkpoint, so a killed job loses minutes at most (0 disables). Episode ends are
    natural cut points, so these checkpoints never change what the run computes."""
    buffer_capacity: int = 1_000_000
    """Replay capacity in rows (one per observation: T+1 per episode of T steps)."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu' or 'cuda'."""
    torch_threads: int = 1
    """CPU threads for torch (0: torch's default). One is fastest for small models on a shared
    CPU and fixes the reduction order, which keeps runs reproducible."""

    def __post_init__(self) -> None:
        check_types(self)
        for name in ("steps", "eval_interval", "eval_episodes", "checkpoint_interval"):
            value = getattr(self, name)
            check(value >= 1, f"train.{name} must be >= 1, got {value}")
        check(self.seed_steps >= 0, f"train.seed_steps must be >= 0, got {self.seed_steps}")
        check(self.torch_threads >= 0, f"train.torch_threads must be >= 0, got "
                                       f"{self.torch_threads}")  # fmt: skip
        check(self.checkpoint_minutes >= 0, "train.checkpoint_minutes must be >= 0")
        check(self.device in DEVICES, f"train.device must be one of {DEVICES}, got "
                                      f"{self.device!r}")  # fmt: skip
        from ccdata.env import EPISODE_STEPS

        # One full episode (T+1 rows) must fit, or the buffer could never store it.
        check(self.buffer_capacity >= EPISODE_STEPS + 1,
              f"train.buffer_capacity must be >= {EPISODE_STEPS + 1} (one episode), "
              f"got {self.buffer_capacity}")  # fmt: skip

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> TrainConfig:
        check(name in cls.PRESETS, f"unknown preset {name!r}; valid: {', '.join(PRESETS)}")
        return cls(**{**cls.PRESETS[name], **overrides})


def _default_model() -> ModelConfig:
    return config_class(DEFAULTS["model"])()


def _default_method() -> MethodConfig:
    return method_config_class(DEFAULTS["method"])()


@dataclass
class RunConfig:
    """What every run has (one task with `ccfit train`, a curriculum with `ccfit run`)."""

    obs: str = DEFAULTS["obs"]
    """Observation mode: 'state' (39-D privileged state) or 'pixels' (the paper: three
    cameras channel-stacked to 9 channels plus the 7-D proprio)."""
    seed: int = 0
    """Seeds everything: model init, replay sampling, episode and evaluation layouts."""
    preset: str = DEFAULTS["preset"]
    """Size preset filling the defaults of model, method and train: smoke (seconds), cpu
    (2 CPU cores), paper (the paper's scale, for a GPU). Flags override it."""
    out: str | None = None
    """Run directory (None: a name made from the config under runs/)."""
    image_size: int = DEFAULTS["image_size"]
    """Camera image side in pixel mode (the other render settings are ccdata's defaults,
    `ccdata.RenderSettings`, recorded in config.json)."""
    encoder: str | None = None
    """'frozen:PATH': a pretrained encoder (`ccfit pretrain-encoder`), frozen for the run."""
    seed_dataset: str | None = "auto"
    """Replay of each task starts with its own episodes of this LeRobot dataset: 'auto' = the
    suite's dataset when it exists locally, None = off, or a repo id / directory."""
    dataset_endpoint: str | None = None
    """Hub endpoint a repo-id `seed_dataset` is downloaded from when it is not in LeRobot's
    local cache (as `ccdata push --endpoint`); None: HF_ENDPOINT or the hub."""
    model: ModelConfig = field(default_factory=_default_model)
    """The world model (`--model.type`: a registered model) and its hyperparameters."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """The online training loop."""

    def __post_init__(self) -> None:
        check_types(self)
        check(self.obs in OBS_MODES, f"unknown obs mode {self.obs!r}; valid: {OBS_MODES}")
        check(self.preset in PRESETS, f"unknown preset {self.preset!r}; valid: "
                                      f"{', '.join(PRESETS)}")  # fmt: skip
        check(self.image_size >= 32, f"image_size must be >= 32, got {self.image_size}")
        check(self.model.obs_mode == self.obs,
              f"model.obs_mode {self.model.obs_mode!r} != obs {self.obs!r}: set it with --obs")
        check(self.model.image_size == self.image_size,
              f"model.image_size {self.model.image_size} != image_size {self.image_size}: "
              f"set it with --image_size")  # fmt: skip
        if self.encoder is not None:
            check(self.encoder.startswith("frozen:"),
                  f"encoder must be 'frozen:PATH', got {self.encoder!r}")
            check(self.obs == "pixels", "a frozen pretrained encoder needs --obs pixels")
            check(Path(self.encoder_path).is_file(),
                  f"encoder checkpoint not found: {self.encoder_path}")
            self.model = _with_encoder(self.model, self.encoder_path, self.image_size)

    @property
    def encoder_path(self) -> str | None:
        return self.encoder.split(":", 1)[1] if self.encoder else None

    def to_dict(self) -> dict:
        """The resolved config as plain data (what config.json holds)."""
        return draccus.encode(self)

    def save(self, path: str | Path) -> None:
        from ccfit.io import atomic_write_json

        atomic_write_json(path, self.to_dict())


def _with_encoder(model: ModelConfig, path: str, image_size: int) -> ModelConfig:
    """`model` with the frozen encoder's sizes (those fields the model's config has), so the
    saved config states what the run used; its image size must be the run's."""
    from ccfit.models.encoders import load_frozen_encoder

    try:
        _, spec = load_frozen_encoder(path)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    size = spec.pop("image_size")
    check(size == image_size, f"the encoder {path} reads {size} px images but the run renders "
                              f"{image_size} px (--image_size)")  # fmt: skip
    names = {f.name for f in dataclasses.fields(model)} - {"obs_mode"}
    return dataclasses.replace(model, **{k: v for k, v in spec.items() if k in names})


@dataclass
class TaskRunConfig(RunConfig):
    """One task learnt online from scratch (`ccfit train`)."""

    task: str = "reach-xy"
    """Task id, e.g. 'reach-xy' (`ccdata list`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        from ccdata.tasks import get_task

        try:
            get_task(self.task)
        except ValueError as e:
            raise ConfigError(str(e)) from None


@dataclass
class CurriculumConfig(RunConfig):
    """A suite's curriculum learnt continually with one method (`ccfit run`)."""

    suite: str = "Reach"
    """Suite name (`ccdata list`); its tasks are learnt in order, the composition last."""
    method: MethodConfig = field(default_factory=_default_method)
    """The continual method (`--method.type`: ft, er, ewc, packnet, experts)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        from ccdata.suites import get_suite

        try:
            get_suite(self.suite)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        # Everything that would fail once the run is under way fails here, before it starts.
        missing = self.method.REQUIRES - model_class(self.model.type).capabilities
        offering = ", ".join(models_offering(self.method.REQUIRES)) or "none"
        check(not missing, f"method {self.method.type!r} needs a model offering "
                           f"{', '.join(sorted(missing))}; models that do: {offering}")  # fmt: skip
        self.model.check_curriculum(len(self.tasks))
        self.method.check_curriculum(len(self.tasks))
        check_references(self.tasks)
        check(self.train.steps % self.train.eval_interval == 0,
              f"steps per task ({self.train.steps}) must be a multiple of eval_interval "
              f"({self.train.eval_interval}) so every task is evaluated at its end")  # fmt: skip

    @property
    def tasks(self) -> list[str]:
        from ccdata.suites import get_suite

        return list(get_suite(self.suite).task_ids)


def models_offering(capabilities: frozenset[str]) -> list[str]:
    """Registered models declaring every one of `capabilities`."""
    from ccfit.models.registry import MODELS

    return sorted(n for n, cls in MODELS.items() if capabilities <= cls.capabilities)


def check_references(tasks: list[str]) -> None:
    """ConfigError unless every task has its oracle reference (normalised returns, hence
    BWT and FWT, need it): found before a run starts, not after it."""
    from ccdata.scoring import oracle_reference

    for task in tasks:
        try:
            oracle_reference(task)
        except ValueError as e:
            raise ConfigError(str(e)) from None


# ============================================================================== resolving


def preset_defaults(cls: type[RunConfig], choices: dict[str, Any]) -> dict:
    """The nested plain-data defaults of `cls` for `choices`: preset, obs, image_size,
    model (its type) and method (its type), each `DEFAULTS[...]` unless given."""
    c = {**DEFAULTS, **{k: v for k, v in choices.items() if v is not None}}
    preset, model, method = c["preset"], c["model"], c["method"]
    check(preset in PRESETS, f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    mcls = config_class(model)
    check(preset in mcls.PRESETS, f"model {model!r} has no preset {preset!r}")
    out: dict[str, Any] = {
        "preset": preset, "obs": c["obs"], "image_size": c["image_size"],
        "model": {"type": model, **mcls.preset_fields(preset), "obs_mode": c["obs"],
                  "image_size": c["image_size"]},
        "train": dict(TrainConfig.PRESETS[preset]),
    }  # fmt: skip
    if _has_method(cls):
        out["method"] = {"type": method, **method_config_class(method).preset_fields(preset)}
    return out


def resolve[C: RunConfig](cls: type[C], overrides: dict[str, Any]) -> C:
    """`cls` from nested plain data (`{"suite": ..., "model": {"type": "pwm", ...}}`): the
    preset's defaults (preset, model and method types, obs and image size taken from
    `overrides`), then `overrides` on top. The programmatic twin of `parse_cli`."""
    choices = {k: overrides.get(k) for k in ("preset", "obs", "image_size")}
    choices.update(model=overrides.get("model", {}).get("type"),
                   method=overrides.get("method", {}).get("type"))  # fmt: skip
    return _decode(cls, _deep_merge(preset_defaults(cls, choices), overrides))


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


def _decode[C: RunConfig](cls: type[C], data: dict) -> C:
    try:
        return draccus.decode(cls, data)
    except draccus.utils.ParsingError as e:
        raise _as_config_error(e) from None


def _as_config_error(e: Exception) -> Exception:
    """draccus wraps what __post_init__ raised: surface a ConfigError's own message; other
    parsing problems (wrong type, unknown field) are bad input too; anything else is a bug."""
    cause = e
    while cause is not None:
        if isinstance(cause, ConfigError):
            return ConfigError(str(cause))
        cause = cause.__cause__
    root = e
    while root.__cause__ is not None:
        root = root.__cause__
    if isinstance(root, draccus.utils.ParsingError | TypeError | ValueError):
        return ConfigError(str(e) if root is e else f"{e} ({root})")
    return root


def parse_cli[C: RunConfig](cls: type[C], argv: Sequence[str], prog: str | None = None) -> C:
    """`cls` from command-line arguments in draccus syntax (`--model.type=pwm --train.steps=10`;
    top-level options may also be spelt with dashes, `--image-size 32`). Defaults come from
    `--preset` (or from `--config_path FILE`, a saved config.json), flags override them."""
    args = [_underscored(a) for a in argv]
    pre = _preparse(args)
    if pre.get("config_path"):
        path = Path(pre["config_path"])
        check(path.is_file(), f"config file not found: {path}")
        try:
            defaults = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ConfigError(f"{path} is not a JSON config: {e}") from None
        # A saved config.json also records what was derived (e.g. the resolved seed dataset),
        # and a curriculum's config may seed a single-task run: keep this class's fields.
        names = {f.name for f in dataclasses.fields(cls)}
        defaults = {k: v for k, v in defaults.items() if k in names}
        args = _without(args, "config_path")
    else:
        size = pre.get("image_size")  # a bad value is reported by draccus below
        defaults = preset_defaults(cls, {
            "preset": pre.get("preset"), "obs": pre.get("obs"),
            "image_size": int(size) if size is not None and size.isdigit() else None,
            "model": pre.get("model.type"), "method": pre.get("method.type"),
        })  # fmt: skip
    for nested, top in (("model.obs_mode", "obs"), ("model.image_size", "image_size")):
        check(nested not in pre, f"--{nested} follows the run's --{top}; set that instead")
    with tempfile.NamedTemporaryFile("w", suffix=".json") as f:
        json.dump(defaults, f)
        f.flush()
        try:
            return draccus.parse(cls, config_path=f.name, args=args, prog=prog,
                                 exit_on_error=False)  # fmt: skip
        except draccus.utils.ParsingError as e:
            raise _as_config_error(e) from None
        except (draccus.utils.DraccusException, argparse.ArgumentError) as e:
            raise ConfigError(f"{e}; see --help") from None


def _underscored(arg: str) -> str:
    if not arg.startswith("--"):
        return arg
    name, sep, value = arg[2:].partition("=")
    return "--" + name.replace("-", "_") + sep + value


def _preparse(args: list[str]) -> dict[str, str]:
    """Values of `--key=value` / `--key value` options, last one winning."""
    out: dict[str, str] = {}
    for i, a in enumerate(args):
        if not a.startswith("--"):
            continue
        name, sep, value = a[2:].partition("=")
        if not sep:
            nxt = args[i + 1] if i + 1 < len(args) else ""
            value = "" if nxt.startswith("--") else nxt
        out[name] = value
    return out


def _without(args: list[str], name: str) -> list[str]:
    """`args` without `--name=value` / `--name value`."""
    out, skip = [], False
    for a in args:
        if skip:
            skip = False
        elif a == f"--{name}":
            skip = True
        elif not a.startswith(f"--{name}="):
            out.append(a)
    return out
