"""Files and random state: atomic writes, checkpoints, RNG capture and seeding.

Every output of ccfit goes through `atomic_write_text` / `atomic_torch_save`, so a killed
process leaves the previous file or the new one. `rng_state` / `set_rng_state` capture every
generator a run draws from (Python, NumPy, torch CPU and CUDA) so a resumed run continues
exactly where it stopped.
"""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ccdata.atomic import atomic_write, atomic_write_text

__all__ = [
    "atomic_torch_save",
    "atomic_write",
    "atomic_write_json",
    "atomic_write_text",
    "derived_seed",
    "rng_state",
    "seed_everything",
    "set_rng_state",
]


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    """`torch.save` to `path` atomically."""
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Indented, key-sorted JSON with a trailing newline, written atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and every CUDA device)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)  # seeds CUDA too


def derived_seed(seed: int, tag: int, index: int, task_index: int = 0) -> int:
    """A 31-bit seed for item `index` of stream `tag` (train episodes, eval layouts, ...) of a
    curriculum's task `task_index`, independent of every other (seed, tag, task, index)."""
    return int(np.random.SeedSequence([seed, tag, task_index, index]).generate_state(1)[0] >> 1)


def rng_state(**generators: np.random.Generator | torch.Generator) -> dict:
    """The global generators' states (Python, NumPy, torch CPU, CUDA when present) and those of
    the named `generators`."""
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "named": {k: _get(g) for k, g in generators.items()},
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, **generators: np.random.Generator | torch.Generator) -> None:
    """Restore what `rng_state` captured (the named generators by the same names)."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    for k, g in generators.items():
        _set(g, state["named"][k])


def _get(g):
    return g.bit_generator.state if isinstance(g, np.random.Generator) else g.get_state()


def _set(g, s) -> None:
    if isinstance(g, np.random.Generator):
        g.bit_generator.state = s
    else:
        g.set_state(s)
