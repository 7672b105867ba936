"""Files and random state: atomic writes, checkpoints, RNG capture and seeding.

Every output of ccfit goes through `atomic_write_text` / `atomic_torch_save`, so a killed
process leaves the previous file or the new one. `rng_state` / `set_rng_state` capture every
generator a run draws from (Python, NumPy, torch CPU and CUDA) so a resumed run continues
exactly where it stopped.

Checkpoints hold only tensors and plain Python data (no NumPy arrays, no classes), so
`load_checkpoint` reads them with `torch.load(weights_only=True)`: a file that is not ours, or
a pickle that would run code, is refused with one line instead of being executed.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ccdata.atomic import atomic_write, atomic_write_text
from ccdata.errors import InputError

__all__ = [
    "atomic_torch_save",
    "atomic_write",
    "atomic_write_json",
    "atomic_write_text",
    "derived_seed",
    "load_checkpoint",
    "rng_state",
    "save_figure",
    "seeded",
    "seed_everything",
    "set_rng_state",
]


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    """`torch.save` to `path` atomically."""
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def load_checkpoint(path: str | Path, kind: str, version: int) -> dict:
    """A checkpoint this project wrote: a dict with `kind` and `version` as given, read with
    `weights_only=True` onto the CPU. Anything else (another program's file, an older format,
    a corrupt or truncated file, a pickle that would run code) is an `InputError` naming the
    file: one line, exit 2 from the CLIs."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # unpickling errors have no common type
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"{path} is not a readable {kind} checkpoint ({reason[:200]})") from None
    if not isinstance(state, dict) or state.get("kind") != kind:
        raise InputError(f"{path} is not a {kind} checkpoint")
    if state.get("version") != version:
        raise InputError(f"{path}: {kind} checkpoint version {state.get('version')!r}, this "
                         f"ccfit reads version {version}; delete it to start over")  # fmt: skip
    return state


def save_figure(fig, path: str | Path, dpi: int = 120) -> None:
    """A matplotlib figure saved as PNG to `path` atomically."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi))


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Indented, key-sorted JSON with a trailing newline, written atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def read_run_json(path: Path, lines: bool = False, leave_out: str = "the report",
                  records: bool = False, remedy: str | None = None) -> Any:  # fmt: skip
    """A run's JSON file: an object, or a list of record objects (`lines`: one per line;
    `records`: one JSON array, as a reference's done.json). InputError when it is missing or
    corrupt, or of another shape: a run directory damaged or copied in part is bad input,
    not a bug. The message ends with `remedy`, by default to rerun the run or leave it out
    of `leave_out`."""
    try:
        text = Path(path).read_text()
        value = [json.loads(x) for x in text.splitlines() if x.strip()] if lines else \
            json.loads(text)  # fmt: skip
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        damage = str(err)
    else:
        if lines or records:
            listed = isinstance(value, list) and all(isinstance(r, dict) for r in value)
            damage = None if listed else "not a list of JSON objects"
        else:
            damage = None if isinstance(value, dict) else "not a JSON object"
    if damage:
        remedy = remedy or f"rerun the run or leave it out of {leave_out}"
        raise InputError(f"{path}: missing or corrupt ({damage}); {remedy}")
    return value


def out_dir(path: str | Path) -> Path:
    """An output folder given by the user: InputError when a file is in its place (writing
    into it would end in a FileExistsError traceback)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {path} is a file, not a folder")
    return path


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and every CUDA device)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)  # seeds CUDA too


def derived_seed(seed: int, tag: int, index: int, task_index: int = 0) -> int:
    """A 31-bit seed for item `index` of stream `tag` (train episodes, eval layouts, ...) of a
    curriculum's task `task_index`, independent of every other (seed, tag, task, index)."""
    return int(np.random.SeedSequence([seed, tag, task_index, index]).generate_state(1)[0] >> 1)


@contextlib.contextmanager
def seeded(seed: int, device: torch.device | str = "cpu") -> Iterator[None]:
    """A private torch RNG stream seeded with `seed` (the CPU's, and `device`'s when it is a
    GPU): the caller's RNG state is as it was afterwards, so what runs inside neither depends
    on nor changes the random numbers drawn outside."""
    device = torch.device(device)
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


def rng_state(**generators: np.random.Generator | torch.Generator) -> dict:
    """The global generators' states (Python, NumPy, torch CPU, CUDA when present) and those of
    the named `generators`."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": (name, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached),
        "torch": torch.get_rng_state(),
        "named": {k: _get(g) for k, g in generators.items()},
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, **generators: np.random.Generator | torch.Generator) -> None:
    """Restore what `rng_state` captured (the named generators by the same names)."""
    random.setstate(state["python"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
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


@contextlib.contextmanager
def folder_lock(folder: str | Path) -> Iterator[None]:
    """Held while `folder`, which several runs share, is made or read (a from-scratch
    reference, a shared first task): concurrent runs wait for the first to make it. The lock
    file `.<name>.lock` lies beside it."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f".{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
