"""The task registry: every benchmark task is one `TaskSpec`, registered once by id."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ccdata.policies.base import Oracle
    from ccdata.tasks.base import SceneEnv

AXES = ("action", "perception")


@dataclass(frozen=True)
class TaskSpec:
    """One task: its scene, its scripted oracle, and what it is made of."""

    id: str
    """Stable kebab-case id, e.g. 'pnp-cube'; one id wherever the task appears."""
    title: str
    """Short name as in the paper's Table II, e.g. 'reach in xy'."""
    instruction: str
    """Natural-language instruction stored with every dataset frame."""
    success: str
    """The success criterion, in words (for cards and docs)."""
    scene: Callable[[], SceneEnv]
    """Builds a fresh scene (a Meta-World SawyerXYZEnv subclass) for this task."""
    oracle: Callable[[], Oracle]
    """Builds the scripted privileged-state oracle."""
    components: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    """Reusable components per axis: {'action': (...), 'perception': (...)}."""

    def __post_init__(self) -> None:
        unknown = set(self.components) - set(AXES)
        if unknown:
            raise ValueError(f"task {self.id}: unknown axes {sorted(unknown)}; use {AXES}")
        if not any(self.components.get(a) for a in AXES):
            raise ValueError(f"task {self.id}: declare at least one component")

    def components_on(self, axis: str) -> frozenset[str]:
        """Components on 'action', 'perception', or 'full' (both, tagged by axis)."""
        axes = AXES if axis == "full" else (axis,)
        return frozenset(f"{a}:{c}" for a in axes for c in self.components.get(a, ()))


TASKS: dict[str, TaskSpec] = {}


def register_task(spec: TaskSpec) -> TaskSpec:
    if spec.id in TASKS:
        raise ValueError(f"task id {spec.id!r} registered twice")
    TASKS[spec.id] = spec
    return spec


def get_task(task_id: str) -> TaskSpec:
    try:
        return TASKS[task_id]
    except KeyError:
        raise ValueError(
            f"unknown task {task_id!r}; known tasks: {', '.join(TASKS)}"
        ) from None
