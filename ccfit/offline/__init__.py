"""The offline track: world-model forgetting and reuse measured directly, on the suite datasets,
with no environment and no planner (the track a CPU can afford).

    ccfit fit --suite Reach --preset cpu --model.type=NAME --method.type=ewc

The task-agnostic backbone is fitted on each task's dataset episodes in curriculum order under a
continual method (the same hooks as online), and every task seen so far is scored on held-out
episodes by open-loop prediction against persistence (`score`: 0 = predict that nothing
changes, 100 = perfect, -100 = infinitely worse; `ccfit.offline.score`), in a space that does
not move with training: observations where the model decodes, or a frozen pretrained encoder's
latent (`config.check_prediction` says why).
BWT and FWT are the paper's, read from the score curves (`ccfit.metrics`).

Modules: `config` (OfflineConfig, FitConfig and its presets), `data` (the episode split, replay
and scored windows), `score`, `fit` (one task), `run` (the curriculum, the from-scratch
reference, metrics).
"""

from ccfit.offline.config import FitConfig, OfflineConfig
from ccfit.offline.fit import TRACK
from ccfit.offline.run import OfflineCurriculum, OfflineTrack, default_out

__all__ = [
    "TRACK",
    "FitConfig",
    "OfflineConfig",
    "OfflineCurriculum",
    "OfflineTrack",
    "default_out",
]
