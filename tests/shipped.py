"""The world models and continual methods ccfit ships, for the tests parametrised over them.

pytest imports every test module while it collects, before any test runs, and test_seam.py
registers its toys when imported. A test parametrised over the registries themselves would
hold the toys' cases or not by the order the files are collected in (`pytest
tests/test_seam.py tests/test_loop.py` collects the toy first), and the toy model is a
call-counting fake, not held to the device contract. A model or method added under ccfit/
joins these lists by registering, as before.
"""

from __future__ import annotations

from ccfit.continual.base import METHODS
from ccfit.models.registry import MODELS


def _shipped(registry: dict[str, type]) -> list[str]:
    return sorted(name for name, cls in registry.items() if cls.__module__.startswith("ccfit."))


def shipped_models() -> list[str]:
    """The registered world models defined in the ccfit package."""
    return _shipped(MODELS)


def shipped_methods() -> list[str]:
    """The registered continual methods defined in the ccfit package."""
    return _shipped(METHODS)
