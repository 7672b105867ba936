"""Analyses a curriculum records after each task, chosen by what the model offers: one
decorator adds one, and every model declaring its capability gets it.

    @register_analysis("routing")
    def routing_callback(stage: Stage) -> None: ...

`stage_callbacks(cfg)` lists the analyses of a run's model (`WorldModel.capabilities`), in
registration order; the curriculum calls each after a task's heads are stored
(`ccfit.curriculum.StageCallback`).
"""

from __future__ import annotations

from collections.abc import Callable

ANALYSES: dict[str, list[Callable]] = {}
"""Capability -> the stage callbacks of the analyses that need it."""


def register_analysis(capability: str) -> Callable[[Callable], Callable]:
    """Decorator: run the function after each task of a curriculum whose model offers
    `capability`."""

    def decorate(callback: Callable) -> Callable:
        ANALYSES.setdefault(capability, []).append(callback)
        return callback

    return decorate


def stage_callbacks(cfg) -> list[Callable]:
    """The analyses a curriculum of `cfg` records after each task."""
    import ccfit.analysis  # noqa: F401  (registers the built-in analyses)
    from ccfit.models.registry import model_class

    offered = model_class(cfg.model.type).capabilities
    return [cb for capability, cbs in ANALYSES.items() if capability in offered for cb in cbs]
