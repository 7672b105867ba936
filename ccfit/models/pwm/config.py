"""PWM's config: TD-MPC2's fields plus the mixture's."""

from __future__ import annotations

from dataclasses import dataclass

from ccfit.config_base import check
from ccfit.models.tdmpc2 import TDMPC2Config

PWM_ROUTERS: tuple[str, ...] = ("task", "state")
"""Gate inputs of PWM's router: the task identity, or the latent and action."""
PWM_SCOPES: tuple[str, ...] = ("own", "all")
"""The expert groups a task routes over: its own and earlier ones, or every active group."""

_PWM_EXTRAS: dict[str, dict] = {
    # Short runs get a short hold, so that the entropy feedback runs at all.
    "smoke": dict(tau_hold_min=100),
    "cpu": dict(tau_hold_min=1000),
    "paper": dict(),
}
"""PWM settings on top of the TD-MPC2 preset of the same name (sizes: the paper's settings)."""


@dataclass
class PWMConfig(TDMPC2Config):
    """PWM (prismatic world model): TD-MPC2 whose latent dynamics is a mixture of experts.

    Every TD-MPC2 field keeps its meaning; the fields below configure the mixture. Experts are
    allocated in groups of `experts_per_task` (one group per task under the 'experts' continual
    method, a single group otherwise); the temperature schedule follows the authors' code (see
    the package docstring).
    Presets: TD-MPC2's of the same name plus the mixture settings of `_PWM_EXTRAS`.
    """

    PRESETS = {
        name: {**fields, **_PWM_EXTRAS.get(name, {})}
        for name, fields in TDMPC2Config.PRESETS.items()
    }

    experts_per_task: int = 3
    """K: experts in each group (the paper adds K = 3 per task)."""
    max_tasks: int = 8
    """Most expert groups (tasks) the model can hold; also the width of the task one-hot seen
    by the router. Groups are allocated up front; only active ones are computed and trained."""
    orthogonalize: bool = False
    """Gram-Schmidt orthonormalise the expert features across experts (in activation order)
    before mixing them. Off: the paper does not say, FACTS.md calls it optional; the authors'
    later progressive driver turns it on."""
    router: str = "task"
    """Gate input: 'task' (one-hot task identity, as the authors) or 'state' ([z, a])."""
    routing_scope: str = "own"
    """Experts a task routes over: 'own' (the groups of tasks 0..t, the experts that existed
    while task t trained: the authors' progressive runs, which evaluate task j on experts
    [0, (j+1)K)) or 'all' (every active group: a finished task also mixes in the experts of
    later tasks; the authors' first progressive driver, and this toolkit before 51a4dde)."""
    tau_init: float = 1.8
    """Router temperature at the start of each task, held during the hold phase."""
    tau_min: float = 0.5
    """Lower clip of the temperature."""
    tau_max: float = 2.0
    """Upper clip of the temperature."""
    tau_rate: float = 0.02
    """Step of the entropy feedback: tau += tau_rate * tanh(H_target - H(w))."""
    tau_target_frac: float = 0.75
    """H_target = tau_target_frac * log(the experts the task routes over)."""
    tau_hold_min: int = 5000
    """The temperature is held for the first max(tau_hold_min, tau_hold_frac * task_steps)
    dynamics steps of a task's training (seq_len - 1 per update)."""
    tau_hold_frac: float = 0.05
    """Share of a task's steps during which the temperature is held (see tau_hold_min)."""
    task_steps: int | None = None
    """Steps of each task, for the hold length; None: tau_hold_min only.
    `PWM.begin_task(i, task_steps)` overrides it per task."""

    def __post_init__(self) -> None:
        super().__post_init__()
        name = type(self).__name__
        check(self.router in PWM_ROUTERS,
              f"{name}.router must be one of {PWM_ROUTERS}, got {self.router!r}")  # fmt: skip
        check(self.routing_scope in PWM_SCOPES,
              f"{name}.routing_scope must be one of {PWM_SCOPES}, "
              f"got {self.routing_scope!r}")  # fmt: skip
        checks = [
            (self.experts_per_task >= 1, "experts_per_task must be >= 1"),
            (self.max_tasks >= 1, "max_tasks must be >= 1"),
            (0.0 < self.tau_min <= self.tau_init <= self.tau_max,
             "need 0 < tau_min <= tau_init <= tau_max"),
            (self.tau_rate >= 0.0, "tau_rate must be >= 0"),
            (self.tau_target_frac >= 0.0, "tau_target_frac must be >= 0"),
            (self.tau_hold_min >= 0, "tau_hold_min must be >= 0"),
            (0.0 <= self.tau_hold_frac <= 1.0, "tau_hold_frac must be in [0, 1]"),
            (self.task_steps is None or self.task_steps >= 1, "task_steps must be >= 1 or None"),
        ]  # fmt: skip
        for ok, msg in checks:
            check(ok, f"{name}: {msg}")

    def check_curriculum(self, num_tasks: int) -> None:
        check(num_tasks <= self.max_tasks,
              f"{type(self).__name__}.max_tasks is {self.max_tasks} but the curriculum has "
              f"{num_tasks} tasks: set --model.max_tasks={num_tasks} or more")  # fmt: skip

    def hold_steps(self, task_steps: int | None = None) -> int:
        """Dynamics steps (seq_len - 1 per update) during which the temperature is held for a
        task of `task_steps` steps."""
        steps = task_steps if task_steps is not None else self.task_steps
        frac = int(round(self.tau_hold_frac * steps)) if steps is not None else 0
        return max(self.tau_hold_min, frac)
