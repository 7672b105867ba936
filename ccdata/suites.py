"""The six task suites: primitives in curriculum order, the composition task last."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ccdata.errors import InputError
from ccdata.tasks import TaskSpec, get_task

AXES = ("action", "perception", "full")


@dataclass(frozen=True)
class Suite:
    name: str
    axis: str
    """Composition axis: 'action', 'perception' or 'full' (both)."""
    task_ids: tuple[str, ...]
    description: str

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ValueError(f"suite {self.name}: axis must be one of {AXES}, got {self.axis!r}")

    @property
    def tasks(self) -> list[TaskSpec]:
        return [get_task(t) for t in self.task_ids]

    @property
    def composition(self) -> TaskSpec:
        return self.tasks[-1]

    def composition_matrix(self) -> np.ndarray:
        """(N, N) bool; entry (i, j): task i reuses a component of task j on the suite's axis."""
        parts = [t.components_on(self.axis) for t in self.tasks]
        return np.array([[bool(pi & pj) for pj in parts] for pi in parts], dtype=bool)


SUITES: dict[str, Suite] = {
    s.name: s
    for s in (
        Suite(
            "Reach",
            "action",
            ("reach-xy", "reach-xz", "reach-yz", "reach-xyz"),
            "Reaching along new pairs of displacement axes; the composition reaches in all three.",
        ),
        Suite(
            "Grasp",
            "action",
            ("pick-cube", "place-cube", "pnp-cube"),
            "Picking and placing learnt apart, then chained into pick-and-place in one scene.",
        ),
        Suite(
            "BinPnP",
            "perception",
            ("bin-red-blue", "bin-yellow-blue", "bin-red-purple", "bin-yellow-purple"),
            "One bin-to-bin transfer under changing bin colours; the composition pairs the "
            "source colour of one primitive with the target colour of another.",
        ),
        Suite(
            "PnPBlock",
            "perception",
            ("pnp-red-block", "pnp-blue-block", "stack-blocks"),
            "Pick-and-place of a red and of a blue block, then both in one scene: stack them.",
        ),
        Suite(
            "DrawerPnP",
            "full",
            ("pnp-cube", "drawer-open", "drawer-pnp"),
            "A cube task and a drawer task, then both in sequence: open the drawer, put the "
            "cube inside.",
        ),
        Suite(
            "PnPBoxClose",
            "full",
            ("pnp-cube", "box-close", "box-pnp-close"),
            "A cube task and a box-lid task, then both in sequence: cube into the box, close it.",
        ),
    )
}


def get_suite(name: str) -> Suite:
    try:
        return SUITES[name]
    except KeyError:
        raise InputError(f"unknown suite {name!r}; valid suites: {', '.join(SUITES)}") from None
