"""World models: one interface (base.py), a registry (registry.py), and the registered models.

Importing this package registers every model (TD-MPC2, PWM, DreamerV3); each model module
keeps its config beside it. `make_model(cfg, device)` builds the model a config belongs to.
"""

from ccfit.models import dreamerv3, pwm, tdmpc2  # noqa: F401  (registers the models)
from ccfit.models.base import Batch, WorldModel
from ccfit.models.registry import ModelConfig, make_model, model_names, register_model

DEFAULT_MODEL = "tdmpc2"
"""The world model a run uses when none is named (`--model.type`)."""
DEFAULT_OFFLINE_MODEL = "dreamerv3"
"""The world model an offline run (`ccfit fit`) uses when none is named: one that decodes, so
it predicts in observation space without a frozen encoder."""

__all__ = [
    "DEFAULT_MODEL", "DEFAULT_OFFLINE_MODEL", "Batch", "ModelConfig", "WorldModel", "make_model",
    "model_names", "register_model",
]  # fmt: skip
