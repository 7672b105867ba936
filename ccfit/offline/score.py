"""The offline score: open-loop prediction of held-out windows, normalised by persistence.

For each scored window the model filters `context` observed rows and predicts the next H rows
from the actions alone (`Prediction.open_loop`); the persistence baseline predicts that nothing
changes (every one of those rows equals the last observed one). With squared errors summed
over windows, steps and dimensions, M for the model's and P for persistence's, per measured
quantity k (the state; or the images and the proprio; or a frozen encoder's latent):

    score_k = 100 * (P_k - M_k) / max(P_k, M_k)

that is 100 * (1 - M/P) wherever the model beats persistence (0 is persistence, 100 perfect
prediction, 75 half persistence's error), and -100 * (1 - P/M) where it does worse (-50 twice
persistence's error, -100 an infinitely worse one). Bounded in [-100, 100], as returns are
online: a fresh model's arbitrary error, thousands of times persistence's, would otherwise
dominate every integral FWT takes over its curve. The score is the mean of score_k over the
quantities (one in state mode), which weighs images and proprio equally rather than by their
dimension counts; the same per horizon step gives `score_by_step`. A task whose held-out
windows never change (zero persistence error) has no score (None).

The space never moves with training (`ccfit.offline.config.check_prediction` says why), so a
score's changes over a curriculum are the model's, and BWT and FWT read them exactly as they
read normalised returns: forgetting below the end-of-task score, floor 0 = persistence.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from ccfit.io import seeded
from ccfit.models.base import Batch, OpenLoop, WorldModel


def normalised_score(model_sse: float, persistence_sse: float) -> float | None:
    """100 * (P - M) / max(P, M): 100 (1 - M/P) when the model beats persistence, else
    -100 (1 - P/M); None when persistence makes no error."""
    m, p = float(model_sse), float(persistence_sse)
    if not p > 0:
        return None
    return 100.0 * (p - m) / max(p, m)


class Errors:
    """Squared errors of the model and of persistence, summed per quantity and horizon step."""

    def __init__(self) -> None:
        self.model: dict[str, np.ndarray] = {}
        self.persistence: dict[str, np.ndarray] = {}
        self.values: dict[str, int] = {}
        """Per quantity, how many values were compared (windows x steps x dimensions)."""

    def add(self, out: OpenLoop) -> None:
        for k, target in out.target.items():
            model = (out.predicted[k].double() - target.double()).pow(2).sum((1, 2))
            still = (out.last[k].double().unsqueeze(0) - target.double()).pow(2).sum((1, 2))
            model, still = model.cpu().numpy(), still.cpu().numpy()
            self.model[k] = self.model.get(k, 0.0) + model
            self.persistence[k] = self.persistence.get(k, 0.0) + still
            self.values[k] = self.values.get(k, 0) + target.numel()

    def record(self) -> dict:
        """score, per-quantity scores, score by horizon step, and both mean squared errors."""
        keys = sorted(self.model)
        per_key = {k: normalised_score(self.model[k].sum(), self.persistence[k].sum())
                   for k in keys}  # fmt: skip
        horizon = len(self.model[keys[0]])
        by_step = []
        for h in range(horizon):
            steps = [normalised_score(self.model[k][h], self.persistence[k][h]) for k in keys]
            by_step.append(_mean(steps))
        return {
            "score": _mean(list(per_key.values())),
            "scores": per_key,
            "score_by_step": by_step,
            "mse": {k: float(self.model[k].sum()) / self.values[k] for k in keys},
            "mse_persistence": {
                k: float(self.persistence[k].sum()) / self.values[k] for k in keys
            },  # fmt: skip
        }


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def score_windows(model: WorldModel, windows: Batch, context: int, horizon: int,
                  chunk: int, view: contextlib.AbstractContextManager | None = None
                  ) -> dict:  # fmt: skip
    """The score record of `windows` (context + horizon rows each) under `view` (a continual
    method's `evaluating` context). The model is scored in eval mode, in a private RNG stream
    (scoring draws nothing from, and changes nothing in, the training's random numbers)."""
    errors = Errors()
    was_training = model.training
    model.train(False)
    try:
        with seeded(0, model.device), torch.no_grad(), view or contextlib.nullcontext():
            for start in range(0, windows.size, chunk):
                part = windows.select(torch.arange(start, min(start + chunk, windows.size)))
                errors.add(model.open_loop(part, context, horizon))
    finally:
        model.train(was_training)
    return {**errors.record(), "windows": windows.size}
