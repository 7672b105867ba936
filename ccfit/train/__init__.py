"""The shared online loop (`Trainer`), evaluation, run records and single-task training."""

from ccfit.train.evaluate import (
    EnvPool,
    Episode,
    EvalResult,
    Evaluator,
    eval_seeds,
    normalized_or_none,
    play_episodes,
)
from ccfit.train.loop import CHECKPOINT, Trainer
from ccfit.train.records import METRICS, RunLogger
from ccfit.train.run import (
    CONFIG,
    LoadedTaskRun,
    build_model,
    load_task_run,
    make_evaluator,
    make_replay,
    resolved_config,
    train_single,
    train_task,
)

__all__ = [
    "CHECKPOINT", "CONFIG", "METRICS", "EnvPool", "Episode", "EvalResult", "Evaluator",
    "LoadedTaskRun", "RunLogger", "Trainer", "build_model", "eval_seeds", "load_task_run",
    "make_evaluator", "make_replay",
    "normalized_or_none", "play_episodes", "resolved_config", "train_single", "train_task",
]  # fmt: skip
