"""Continual-learning methods acting on a world model's task-agnostic backbone.

from ccfit.continual import make_method, method_config
method = make_method(method_config("packnet", retrain_steps=500), num_tasks=4, seed=0)
"""

from ccfit.continual import er, ewc, experts, ft, packnet  # noqa: F401  (registers the methods)
from ccfit.continual.base import (
    METHODS,
    ContinualMethod,
    MethodConfig,
    TaskData,
    make_method,
    method_config,
    method_names,
    register_method,
)

__all__ = [
    "METHODS",
    "ContinualMethod",
    "MethodConfig",
    "TaskData",
    "make_method",
    "method_config",
    "method_names",
    "register_method",
]
