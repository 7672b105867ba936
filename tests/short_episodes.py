"""Shorter episodes for tests that train or evaluate a model.

The benchmark's episodes last 250 steps. In a smoke run, evaluation episodes are most of the
time, and nothing these tests check depends on the length, so they run with `EPISODE_STEPS`,
passed where a run takes its episode length: `train.episode_steps` in a run config (which the
run hands to its environments, their worker processes, its evaluator and TD-MPC2's discount),
`episode_steps=` to `make_env`, `Evaluator` and `EnvPool`.
"""

from __future__ import annotations

import sys

EPISODE_STEPS = 25
SHORT_FLAG = f"--train.episode_steps={EPISODE_STEPS}"
"""The command-line flag of a run with short episodes."""


def short(train: dict | None = None, steps: int = EPISODE_STEPS) -> dict:
    """A run's `train` settings (`train`, or none) with episodes of `steps` steps."""
    return {"episode_steps": steps, **(train or {})}


def ccfit_command(argv: list[str], steps: int = EPISODE_STEPS) -> list[str]:
    """The command `ccfit *argv` in a fresh interpreter, its episodes `steps` steps long
    (unless `argv` sets `--train.episode_steps` itself)."""
    given = any(a.startswith("--train.episode_steps") for a in argv)
    return [sys.executable, "-m", "ccfit.cli", *argv,
            *([] if given else [f"--train.episode_steps={steps}"])]  # fmt: skip


def smoke_train_argv(out, *extra: str, task: str = "reach-xy") -> list[str]:
    """`ccfit train` arguments: `task` at the smoke preset, no seed dataset, short episodes,
    quiet, into `out`; `extra` last."""
    return ["train", "--task", task, "--preset", "smoke", "--seed_dataset", "null",
            "--out", str(out), "--quiet", SHORT_FLAG, *extra]  # fmt: skip


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
                                     "train": short(train)})  # fmt: skip
    result = Curriculum(cfg, where / "run", where / "scratch", progress=False).run()
    return result, json.loads((where / "run" / "config.json").read_text())
