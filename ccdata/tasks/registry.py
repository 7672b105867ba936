"""The task registry: every benchmark task is one `TaskSpec`, registered once by id."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ccdata.errors import InputError

if TYPE_CHECKING:
    from ccdata.policies.base import Oracle
    from ccdata.tasks.base import SceneEnv

AXES = ("action", "perception")


@dataclass(frozen=True)
class ExplorationNoise:
    """How the `noisy-oracle` policy perturbs a task's oracle.

    Calibrated per task (`ccdata.calibration`) so that noisy-oracle episodes succeed about half
    the time: exploration data then holds both successes and near misses on every task."""

    noise_std: float
    """Std of the Gaussian noise added to each of the oracle's four action components."""
    random_prob: float
    """Probability that a step takes a uniform random action instead."""

    def __post_init__(self) -> None:
        if not self.noise_std >= 0 or not 0.0 <= self.random_prob <= 1.0:
            raise ValueError(
                f"noise_std must be >= 0 and random_prob in [0, 1], got {self.noise_std}, "
                f"{self.random_prob}"
            )

    def to_dict(self) -> dict[str, float]:
        return {"noise_std": self.noise_std, "random_prob": self.random_prob}


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
    exploration: ExplorationNoise | None = None
    """The noisy oracle's calibrated noise for this task (required; `ccdata calibrate` finds
    it)."""

    def __post_init__(self) -> None:
        if not isinstance(self.exploration, ExplorationNoise):
            raise ValueError(
                f"task {self.id}: declare its calibrated exploration=ExplorationNoise(...) "
                "(find it with `ccdata calibrate --task ...`)"
            )
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
        raise InputError(f"unknown task {task_id!r}; known tasks: {', '.join(TASKS)}") from None
