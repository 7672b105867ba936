"""Fine-tuning: the backbone simply keeps training on each new task (the lower baseline)."""

from __future__ import annotations

from dataclasses import dataclass

from ccfit.continual.base import ContinualMethod, MethodConfig, register_method


@dataclass
class FineTuneConfig(MethodConfig):
    """Fine-tuning has no options."""


@register_method("ft", FineTuneConfig)
class FineTune(ContinualMethod):
    """No hook does anything; forgetting is whatever plain training causes."""

    shares_first_task = True
