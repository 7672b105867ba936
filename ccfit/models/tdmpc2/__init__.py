"""TD-MPC2 (Hansen et al., 2024) split into a continual backbone and per-task heads, with its
config (`TDMPC2Config`, registered as model 'tdmpc2').

Backbone (task-agnostic): observation encoder + latent dynamics `next(z, a)` (SimNorm output).
Heads (per task): two-hot reward, termination logit, Q ensemble (+ Polyak target copy),
tanh-Gaussian policy, and the running Q scale used to normalise the policy loss.

Training follows the paper on windows of `seq_len` replay rows: the latent rollout from row 0
over the window's seq_len - 1 transitions is matched to the detached encodings of the next
observations (consistency), rewards and TD targets (from two random target Q members, no
bootstrap after a termination) are learnt by two-hot cross-entropy, termination by binary
cross-entropy; per-step weights rho**t, and every per-step term is masked by
`Batch.rollout_mask()` (a window may run into the next episode). The policy maximises
scale-normalised Q plus an entropy bonus on detached latents with its own optimiser. Acting
is MPPI in latent space (`ccfit.models.mppi`), seeded with policy rollouts and warm-started
from the previous plan's mean, which is the acting state.
"""

from ccfit.models.tdmpc2.config import Q_RETURN_TYPES, TDMPC2_SIZES, TDMPC2Config
from ccfit.models.tdmpc2.model import TDMPC2
from ccfit.models.tdmpc2.networks import TDMPC2Backbone, TDMPC2Heads, modules_in_eval

__all__ = [
    "Q_RETURN_TYPES", "TDMPC2", "TDMPC2Backbone", "TDMPC2Config", "TDMPC2Heads", "TDMPC2_SIZES",
    "modules_in_eval",
]  # fmt: skip
