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
    same_from_state: tuple[tuple[str, ...], ...] = ()
    """Groups of tasks that differ only in what the images show (a colour): from the state
    observation each group is one MDP, the same observations and rewards along the same
    actions (a contract test checks every pair of every suite). A curriculum from state
    relearns such a group's task with fresh heads; the difference the suite composes is
    seen from pixels only."""

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ValueError(f"suite {self.name}: axis must be one of {AXES}, got {self.axis!r}")
        for group in self.same_from_state:
            if len(group) < 2 or not set(group) <= set(self.task_ids):
                raise ValueError(f"suite {self.name}: same_from_state group {group} must name "
                                 "two or more of its tasks")  # fmt: skip

    def same_from_state_text(self, quote: str = "") -> str:
        """`same_from_state` in words, each id between `quote`s: 'a and b; c, d and e'."""

        def one(group: tuple[str, ...]) -> str:
            ids = [f"{quote}{t}{quote}" for t in group]
            return f"{', '.join(ids[:-1])} and {ids[-1]}"

        return "; ".join(one(group) for group in self.same_from_state)

    def same_task_from_state(self, a: str, b: str) -> bool:
        """Whether tasks `a` and `b` are one MDP from the state observation."""
        return a == b or any({a, b} <= set(group) for group in self.same_from_state)

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
            # The layout is fixed; only the bins' colours change, which the state does not hold.
            same_from_state=(
                ("bin-red-blue", "bin-yellow-blue", "bin-red-purple", "bin-yellow-purple"),
            ),
        ),
        Suite(
            "PnPBlock",
            "perception",
            ("pnp-red-block", "pnp-blue-block", "stack-blocks"),
            "Pick-and-place of a red and of a blue block, then both in one scene: stack them.",
            # Each primitive's scene holds its one block, in the same state slot.
            same_from_state=(("pnp-red-block", "pnp-blue-block"),),
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
