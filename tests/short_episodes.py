"""Shorter episodes for tests that train or evaluate a model.

The benchmark's episodes last 250 steps. In a smoke run, evaluation episodes are most of the
time, and nothing these tests check depends on the length, so they run with `EPISODE_STEPS`.
"""

from __future__ import annotations

import contextlib
import sys

import pytest

import ccdata.env

EPISODE_STEPS = 25


@contextlib.contextmanager
def shorter_episodes(steps: int = EPISODE_STEPS):
    """Within the block, every environment episode ends after `steps` steps."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ccdata.env, "EPISODE_STEPS", steps)
        yield steps


def ccfit_command(argv: list[str], steps: int = EPISODE_STEPS) -> list[str]:
    """The command `ccfit *argv` in a fresh interpreter whose episodes last `steps` steps."""
    code = (
        f"import sys, ccdata.env; ccdata.env.EPISODE_STEPS = {steps}; "
        "from ccfit.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    return [sys.executable, "-c", code, *argv]


def smoke_train_argv(out, *extra: str, task: str = "reach-xy") -> list[str]:
    """`ccfit train` arguments: `task` at the smoke preset, no seed dataset, quiet, into `out`;
    `extra` last."""
    return ["train", "--task", task, "--preset", "smoke", "--seed_dataset", "null",
            "--out", str(out), "--quiet", *extra]  # fmt: skip


def smoke_curriculum(where, model: str, method: str, train: dict) -> tuple[dict, dict]:
    """A Reach curriculum of `model` under `method` at the smoke preset, no seed dataset,
    `train` its `--train.*` settings, on shorter episodes, in `where`/run (its reference in
    `where`/scratch): its result and its config.json."""
    import json

    from ccfit.config import CurriculumConfig
    from ccfit.config_parse import resolve
    from ccfit.curriculum import Curriculum

    cfg = resolve(CurriculumConfig, {"suite": "Reach", "preset": "smoke", "seed_dataset": None,
                                     "model": {"type": model}, "method": {"type": method},
                                     "train": train})  # fmt: skip
    with shorter_episodes():
        result = Curriculum(cfg, where / "run", where / "scratch", progress=False).run()
    return result, json.loads((where / "run" / "config.json").read_text())
