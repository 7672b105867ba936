"""DreamerV3 (Hafner et al. 2023), the authors' 2023 recipe with 2025 changes as options.

config.py (DreamerV3Config, presets), math.py (symlog, two-hot, categorical KL, lambda-returns,
return normaliser), networks.py (encoder, decoder, heads), rssm.py (GRU core, prior,
posterior), heads.py (the per-task heads), behavior.py (imagination, actor, critic),
model.py (the registered `DreamerV3` world model).
"""

from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.model import DreamerV3

__all__ = ["DreamerV3", "DreamerV3Config"]
