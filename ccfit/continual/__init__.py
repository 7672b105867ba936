"""Continual-learning methods acting on a world model's task-agnostic backbone.

    from ccfit.continual import make_method
    method = make_method("packnet", num_tasks=4, retrain_steps=500)
"""

from ccfit.continual import er, ewc, experts, ft, packnet  # noqa: F401  (registers the methods)
from ccfit.continual.base import (
    METHODS,
    ContinualMethod,
    TaskData,
    make_method,
    method_names,
    register_method,
)

__all__ = [
    "METHODS",
    "ContinualMethod",
    "TaskData",
    "make_method",
    "method_names",
    "register_method",
]
