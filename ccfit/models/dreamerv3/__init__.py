"""DreamerV3 (Hafner et al. 2023), the authors' 2023 recipe with 2025 changes as options.

config.py (DreamerV3Config, presets), math.py (symlog, two-hot, categorical KL, lambda-returns,
return normaliser), networks.py (encoder, decoder, heads), rssm.py (GRU core, prior,
posterior), heads.py (the per-task heads), behavior.py (imagination, actor, critic),
model.py (the registered `DreamerV3` world model).

Choices where the recipe leaves room (see DREAMERV3.md):
- Row 0 of every replay window starts from the learned initial state (what came before the
  window is unknown); `is_first` rows reset deter, stoch and previous action the same way.
- With a frozen pretrained encoder its latent is the embedding and the decoder reconstructs
  that latent (not the pixels): the world model's view of the observation is the latent, and
  replay can then cache latents instead of frames (`replay_obs`).
- Prior/posterior logits pass through 1% unimix before sampling and KL; actions beyond
  [-1, 1] are clipped in value (scaled, gradient kept) before the dynamics, and the acting
  action is the clipped sample.
- 2025 replay-value loss (`critic_replay_scale`): the critic predicts raw returns (as in 2023
  and 2025, whose value normalisation is off); bootstrap targets come from a no-grad
  imagination inside `loss`, before the world-model step, as in 2025's single joint update.
- A window's first row starts imagination as a live state even when it is an episode's
  terminal observation (the transition into it is not in the window), where the authors' 2023
  code knows it is terminal: only starts at row 0 (1 in `seq_len`) that fall on the one
  terminal row of a successful episode.
"""

from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.model import DreamerV3

__all__ = ["DreamerV3", "DreamerV3Config"]
