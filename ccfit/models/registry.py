"""The world-model registry: one decorator makes a model and its config known everywhere.

    @register_model("tdmpc2", TDMPC2Config)
    class TDMPC2(WorldModel): ...

`--model.type=tdmpc2` on the command line picks the config class (draccus' choice registry);
`make_model(cfg, device)` builds the model it belongs to. Presets live on the config class.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import draccus
import torch

from ccfit.config_base import PRESETS, ChoiceConfig, check, check_types
from ccfit.models.base import WorldModel
from ccfit.obs import OBS_MODES


@dataclass
class ModelConfig(ChoiceConfig, draccus.ChoiceRegistry):
    """Fields every world model has; a model's config subclasses this and is registered with
    its model by `register_model`. Subclasses list presets in `PRESETS` (name -> fields): every
    name of `ccfit.config_base.PRESETS`, and more if they like (e.g. sizes)."""

    SUITE_TRAIN: ClassVar[dict[str, dict[str, dict[str, Any]]]] = {}
    """Preset -> suite -> `--train.*` settings: what this model needs at that preset for every
    task of the suite to be learnt from state (measured with `ccfit learnability`): the steps
    per task, and where a suite needs them, e.g. demonstrations oversampled or a replay that
    holds the whole task. Where a task is not learnt within 100 000 steps, what the suite's
    other tasks need (docs/learnability.md names such tasks). A state curriculum
    of the suite at the preset uses them unless the command line says otherwise; pixel runs
    keep the preset's (nothing measured there yet). A subclass does not inherit its parent's
    budgets unless it says so."""
    SUITE_MODEL: ClassVar[dict[str, dict[str, dict[str, Any]]]] = {}
    """Preset -> suite -> this model's own settings (`--model.*`) that its budget for the suite
    (`SUITE_TRAIN`) was measured with, e.g. cloning where the budget replays demonstrations:
    applied wherever that budget is, unless the command line says otherwise."""

    obs_mode: str = "state"
    """'state' (39-D privileged state) or 'pixels' (9-channel images + 7-D proprio). Set from
    the run's top-level --obs."""
    state_dim: int = 39
    """Size of the 'state' vector."""
    proprio_dim: int = 7
    """Size of the 'proprio' vector (pixel mode)."""
    image_size: int = 64
    """Side S of the square (9, S, S) pixel input. Set from the run's --image-size."""
    action_dim: int = 4
    """Action size; actions live in [-1, 1]."""
    batch_size: int = 256
    """Replay windows per update."""
    seq_len: int = 4
    """Rows per replay window (a window may cross episode boundaries, see `Batch`)."""
    train_ratio: float = 1.0
    """Updates per env step after the seed phase; fractions accumulate (0.5 = one update every
    second step)."""
    grad_clip: float = 20.0
    """Global-norm clip of the world-model update (`WorldModel.world_model_optimizer`)."""
    pretrain_updates: int = 0
    """Updates run in one burst when updates first become possible on a fresh model (the
    run's first task, right after the seed steps), before `train_ratio` takes over
    (DreamerV3's recipe: 100). Later tasks of a curriculum do not repeat it. TD-MPC2 runs
    none, where the official one runs `seed_steps` updates at once when seeding ends."""

    def __post_init__(self) -> None:
        check_types(self, finite=True)
        name = type(self).__name__
        check(self.obs_mode in OBS_MODES, f"{name}.obs_mode must be one of {OBS_MODES}")
        for f in ("state_dim", "proprio_dim", "action_dim", "batch_size", "seq_len"):
            check(getattr(self, f) >= 1, f"{name}.{f} must be >= 1, got {getattr(self, f)}")
        check(self.image_size >= 32, f"{name}.image_size must be >= 32, got {self.image_size}")
        check(self.seq_len >= 2, f"{name}.seq_len must be >= 2 (one transition), got "
                                 f"{self.seq_len}")  # fmt: skip
        check(self.train_ratio > 0, f"{name}.train_ratio must be > 0, got {self.train_ratio}")
        check(self.grad_clip > 0, f"{name}.grad_clip must be > 0, got {self.grad_clip}")
        check(self.pretrain_updates >= 0,
              f"{name}.pretrain_updates must be >= 0, got {self.pretrain_updates}")  # fmt: skip

    def check_curriculum(self, num_tasks: int) -> None:
        """ConfigError if this model cannot learn a curriculum of `num_tasks` tasks (checked
        before a run starts, not when the task that does not fit comes)."""


# ------------------------------------------------------------------------------- registry

MODELS: dict[str, type[WorldModel]] = {}
"""Registered world models by name."""


def register_model(
    name: str, config_class: type[ModelConfig]
) -> Callable[[type[WorldModel]], type[WorldModel]]:
    """Class decorator: registers the model under `name` and its config as the `name` choice
    of `--model.type`. The model's constructor is `(cfg, device, encoder=None)`."""

    def decorate(cls: type[WorldModel]) -> type[WorldModel]:
        if name in MODELS:
            raise ValueError(f"world model {name!r} is already registered")
        if not (isinstance(cls, type) and issubclass(cls, WorldModel)):
            raise TypeError(f"{cls!r} is not a WorldModel subclass")
        missing = [p for p in PRESETS if p not in config_class.PRESETS]
        if missing:
            raise TypeError(f"{config_class.__name__}.PRESETS lacks {missing}")
        ModelConfig.register_subclass(name)(config_class)
        MODELS[name] = cls
        cls.config_class = config_class
        return cls

    return decorate


def model_names() -> list[str]:
    return sorted(MODELS)


def model_class(name: str) -> type[WorldModel]:
    check(name in MODELS, f"unknown model {name!r}; valid: {', '.join(sorted(MODELS))}")
    return MODELS[name]


def config_class(name: str) -> type[ModelConfig]:
    return model_class(name).config_class


def make_model(cfg: ModelConfig, device: torch.device, encoder=None) -> WorldModel:
    """The registered model of `cfg`'s type on `device` (resolved: `ccfit.settings`; a plain
    torch name such as 'cpu' is taken as that device). `encoder`: a frozen pretrained encoder
    (`ccfit.models.encoders.load_frozen_encoder`) to use instead of a trainable one."""
    return model_class(cfg.type)(cfg, device=device, encoder=encoder)
