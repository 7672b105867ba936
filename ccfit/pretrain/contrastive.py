"""An episode-contrastive term: what stays the same through an episode is what the task is.

Within an episode the arm moves and the layout stays: the goal, the objects before they are
grasped, the colours of the bins and blocks. Across episodes the layout changes. So asking
the latent of one frame to pick out another frame of the same episode among frames of other
episodes (InfoNCE, as in SimCLR, with frames of one episode as the positive pair) makes it hold
the layout, from the frames alone, where a reconstruction loss is content to draw the arm
(the proprio tells it where) and leave out the one-pixel goal.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def other_frames(lengths: np.ndarray, pairs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(episode, frame) pairs: for each of `pairs`, a frame of the same episode drawn uniformly
    (the same frame where the episode has one); `lengths`: frames per episode."""
    episodes = pairs[:, 0]
    frames = rng.integers(0, lengths[episodes])
    return np.stack([episodes, frames], axis=1)


class ProjectionHead(nn.Module):
    """The latent -> the space the contrastive term compares in (SimCLR's head: the latent
    keeps more than the term needs, the head drops what the term does not)."""

    def __init__(self, latent_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.ReLU(),
                                 nn.Linear(latent_dim, latent_dim))  # fmt: skip

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.net(z), dim=-1)


def episode_contrast(a: torch.Tensor, b: torch.Tensor, episodes: torch.Tensor,
                     temperature: float) -> torch.Tensor:  # fmt: skip
    """InfoNCE of row i of `a` against the rows of `b` (both unit vectors, (N, D)), row i of
    `b` the positive: a frame of the same episode (`episodes`: (N,) episode of each row). Other
    rows of the same episode are left out rather than counted as negatives."""
    logits = a @ b.T / temperature
    same = episodes[:, None] == episodes[None, :]
    own = torch.eye(len(a), dtype=torch.bool, device=a.device)
    logits = logits.masked_fill(same & ~own, float("-inf"))
    return F.cross_entropy(logits, torch.arange(len(a), device=a.device))
