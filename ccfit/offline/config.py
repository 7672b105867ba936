"""The offline track's config: a run's common fields, the suite, the continual method, the
dataset and the offline loop (`FitConfig`, with its presets).

    ccfit fit --suite Reach --preset cpu --model.type=NAME --method.type=ewc \
        [--fit.updates=2000 --fit.horizon=15 --dataset ccdata/Reach ...]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from ccfit.config import AUTOCAST_SETTINGS, BaseRunConfig, check_pairing, models_offering
from ccfit.config_base import (
    DEFAULTS,
    Presets,
    check,
    check_types,
    suite_tasks,
)
from ccfit.continual.base import MethodConfig, method_config_class
from ccfit.models import DEFAULT_OFFLINE_MODEL
from ccfit.models.registry import ModelConfig, config_class, model_class
from ccfit.settings import check_device_name

PREDICTION = "prediction"
"""The model capability the offline track needs (`ccfit.models.base.Prediction`)."""


@dataclass
class FitConfig(Presets):
    """The offline loop on one task: the backbone alone fitted on the task's dataset episodes
    for a budget of updates, open-loop prediction scored on held-out episodes at a fixed
    interval. Batch size, window length, learning rates and gradient clip are the model's
    (`--model.*`)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "smoke": dict(updates=20, score_interval=10, checkpoint_interval=10, context=3,
                      horizon=4, windows=8, score_batch=8),
        "cpu": dict(updates=2_000, score_interval=250, checkpoint_interval=500, context=5,
                    horizon=15, windows=64),
        "paper": dict(updates=100_000, score_interval=5_000, checkpoint_interval=10_000,
                      context=5, horizon=30, windows=512, score_batch=128, torch_threads=0,
                      keep_backbone_optimizer=True),
    }  # fmt: skip

    updates: int = 10_000
    """Backbone updates on each task (its step budget: BWT and FWT integrate over updates)."""
    score_interval: int = 1_000
    """Score every seen task every this many updates of a task (and at its start and end)."""
    context: int = 5
    """Observed rows before the open-loop rollout (a recurrent model filters them)."""
    horizon: int = 15
    """H: rows predicted open-loop from the context and the actions alone."""
    holdout: float = 0.2
    """Share of each task's episodes held out for scoring (split by episode, seeded, recorded
    in the run directory's split.json); they never reach training."""
    windows: int = 128
    """Held-out windows of context + horizon rows scored per task (fixed for the run)."""
    score_batch: int = 32
    """Windows per forward pass while scoring (bounds memory, e.g. decoded images)."""
    checkpoint_interval: int = 10_000
    """Write a resumable checkpoint every this many updates (and at the end of a task)."""
    checkpoint_minutes: float = 10.0
    """Also checkpoint after this many minutes of wall clock since the last one (0: never);
    a checkpoint never changes what the run computes."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N', as
    `--train.device`."""
    torch_threads: int = 1
    """CPU threads for torch (0: torch's default)."""
    autocast: str = "off"
    """As `--train.autocast`: 'bf16' runs the backbone's updates under bfloat16 autocast,
    'auto' where the hardware multiplies in bf16, 'off' float32 (every preset). Scoring stays
    float32: it measures. Recorded as `resolved_autocast`. (No `fit.compile`: this loop steps
    `backbone_loss` and open-loop prediction, none of the models' compiled hot paths.)"""
    keep_backbone_optimizer: bool = False
    """Each task's optimiser starts from the state where the previous task left it (Adam's
    step counts and moments), as `--train.keep_backbone_optimizer` online; False: fresh at
    every task. On in the `paper` preset."""

    def __post_init__(self) -> None:
        check_types(self)
        for name in ("updates", "score_interval", "context", "horizon", "windows",
                     "score_batch", "checkpoint_interval"):  # fmt: skip
            value = getattr(self, name)
            check(value >= 1, f"fit.{name} must be >= 1, got {value}")
        check(0.0 < self.holdout < 1.0, f"fit.holdout must be in (0, 1), got {self.holdout}")
        check(self.checkpoint_minutes >= 0, "fit.checkpoint_minutes must be >= 0")
        check(self.torch_threads >= 0, f"fit.torch_threads must be >= 0, got "
                                       f"{self.torch_threads}")  # fmt: skip
        check_device_name(self.device, "fit.device")
        if self.autocast in (True, False, "True", "False"):  # draccus reads off as YAML false
            self.autocast = "on" if self.autocast in (True, "True") else "off"
        check(
            self.autocast in AUTOCAST_SETTINGS,
            f"fit.autocast must be one of {AUTOCAST_SETTINGS}, got {self.autocast!r}",
        )
        check(self.updates % self.score_interval == 0,
              f"fit.updates ({self.updates}) must be a multiple of fit.score_interval "
              f"({self.score_interval}) so every task is scored at its end")  # fmt: skip

    @property
    def rows(self) -> int:
        """Rows of a scored window: context + horizon."""
        return self.context + self.horizon


def _default_method() -> MethodConfig:
    return method_config_class(DEFAULTS["method"])()


def _default_model() -> ModelConfig:
    return config_class(DEFAULT_OFFLINE_MODEL)()


@dataclass
class OfflineConfig(BaseRunConfig):
    """A suite's curriculum fitted offline on its dataset with one method (`ccfit fit`)."""

    DEFAULT_MODEL: ClassVar[str] = DEFAULT_OFFLINE_MODEL
    """`--model.type` when none is given (`ccfit.config_parse`)."""

    model: ModelConfig = field(default_factory=_default_model)
    """The world model (`--model.type`: a registered model offering 'prediction')."""
    suite: str = "Reach"
    """Suite name (`ccdata list`); its tasks are fitted in order, the composition last."""
    method: MethodConfig = field(default_factory=_default_method)
    """The continual method (`--method.type`), acting on the backbone as online."""
    dataset: str = "auto"
    """The suite's LeRobot dataset: 'auto' = `ccdata generate`'s local one (ccdata/<suite> in
    LeRobot's cache), or a repo id or directory."""
    fit: FitConfig = field(default_factory=FitConfig)
    """The offline loop."""

    def __post_init__(self) -> None:
        super().__post_init__()
        suite_tasks(self.suite)
        check(getattr(self.model, "demo_bc_coef", 0.0) == 0,
              "model.demo_bc_coef clones the demonstrations an online run oversamples "
              "(--train.demo_fraction); the offline track fits every episode alike")  # fmt: skip
        check_prediction(self.model, self.encoder is not None)
        check_pairing(self.model, self.method, len(self.tasks))

    @property
    def tasks(self) -> list[str]:
        return suite_tasks(self.suite)

    @property
    def measurement_space(self) -> str:
        """Where the prediction error is measured (the model's `measurement_space`)."""
        return model_class(self.model.type).measurement_space(self.model, self.encoder is not None)


def check_prediction(model, frozen_encoder: bool) -> None:
    """ConfigError unless the model predicts in a space that does not move with training.

    The score compares the model's open-loop error with persistence's in one space at every
    scoring point and across tasks; a model's own latent space moves as it trains (and as it is
    regularised, pruned or replayed), so an error measured there at two times compares two
    different spaces: forgetting and transfer read from it would mean nothing. Observations
    where the model decodes, or a frozen pretrained encoder's latent, stay put."""
    cls, offering = model_class(model.type), models_offering(frozenset({PREDICTION}))
    check(PREDICTION in cls.capabilities,
          f"model {model.type!r} offers no open-loop prediction (capability {PREDICTION!r}); "
          f"models that do: {', '.join(offering) or 'none'}")  # fmt: skip
    decoding = [
        n
        for n in offering
        if model_class(n).measurement_space(config_class(n)(), False) is not None
    ]
    check(cls.measurement_space(model, frozen_encoder) is not None,
          f"model {model.type!r} predicts only in its own latent space here, which moves as it "
          "trains, so an error measured there means nothing: give it a frozen pretrained "
          "encoder (--obs pixels --encoder frozen:PATH) or use a model that decodes "
          f"({', '.join(decoding) or 'none'})")  # fmt: skip
