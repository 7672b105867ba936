"""Benchmark tasks, one module per scene family; importing this package registers them all."""

import importlib
import pkgutil

from ccdata.tasks.registry import TASKS, ExplorationNoise, TaskSpec, get_task, register_task

_NOT_FAMILIES = {"base", "registry"}

# Every other module in this package is a scene family that registers its tasks on import.
for _module in sorted(m.name for m in pkgutil.iter_modules(__path__)):
    if _module not in _NOT_FAMILIES:
        importlib.import_module(f"{__name__}.{_module}")

__all__ = ["TASKS", "ExplorationNoise", "TaskSpec", "get_task", "register_task"]
