"""The shared online loop (`Trainer`), evaluation, run records and single-task training."""

from ccfit.train.evaluate import EvalResult, eval_seeds, evaluate, normalized_or_none
from ccfit.train.loop import CHECKPOINT, Trainer
from ccfit.train.records import METRICS, RunLogger
from ccfit.train.run import CONFIG, build_model, make_replay, resolve_device, train_task

__all__ = [
    "CHECKPOINT", "CONFIG", "METRICS", "EvalResult", "RunLogger", "Trainer", "build_model",
    "eval_seeds", "evaluate", "make_replay", "normalized_or_none", "resolve_device",
    "train_task",
]  # fmt: skip
