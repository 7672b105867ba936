"""What of a frame is the task: pixels that differ from their camera's static background.

A 2 cm goal marker is one or two pixels of a 64 px camera; a whole-frame reconstruction error
barely notices it, so an autoencoder trained on it keeps the arm (large, and in the proprio)
and drops the goal and the objects (docs/training.md, the probe). Weighting the error toward
the pixels that differ from the scene's static background, the table and walls each suite's
layouts share, makes the small things that vary between layouts count.

The background of a suite is the per-pixel median of a sample of its training frames: layouts
put the goal and objects somewhere else in each, so the median is the empty scene. The
gripper's camera moves with the hand and has no static background; most of its pixels come out
as foreground, which only makes its weighting plain MSE.
"""

from __future__ import annotations

import numpy as np
import torch

from ccdata.render import CAMERAS

BACKGROUND_FRAMES = 512
"""Training frames per suite whose median is its background (a sample: the median of a few
hundred random layouts is already the empty scene)."""
_BACKGROUND_TAG = 3  # seed stream of the background sample (the split is 1, batches 2)


def backgrounds(pixels: list[np.ndarray], episodes: list[dict], train: list[int],
                seed: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(background per suite, uint8 (n_suites, 9, S, S); suite index per episode, int64) from
    the training episodes `train` of `pixels` (per episode (T, 9, S, S)) and `episodes` (their
    records, with 'suite'). Seeded: the same frames give the same backgrounds."""
    suites = sorted({episodes[e]["suite"] for e in range(len(episodes))})
    suite_of = np.array([suites.index(ep["suite"]) for ep in episodes], dtype=np.int64)
    rng = np.random.default_rng([seed, _BACKGROUND_TAG])
    out = []
    for s in range(len(suites)):
        frames = [(e, t) for e in train if suite_of[e] == s for t in range(len(pixels[e]))]
        if not frames:  # a suite whose every episode was held out: its own frames
            frames = [(e, t) for e in range(len(pixels)) if suite_of[e] == s
                      for t in range(len(pixels[e]))]  # fmt: skip
        pick = rng.permutation(len(frames))[:BACKGROUND_FRAMES]
        sample = np.stack([pixels[frames[i][0]][frames[i][1]] for i in sorted(pick)])
        out.append(np.median(sample, axis=0).round().astype(np.uint8))
    return np.stack(out), suite_of


def foreground_mask(pixels: torch.Tensor, background: torch.Tensor,
                    threshold: float) -> torch.Tensor:  # fmt: skip
    """uint8 (N, 3, S, S), 255 where a camera's pixel differs from the background by more than
    `threshold` (on the [0, 1] scale) in any colour channel, else 0. `pixels` and `background`
    are uint8 (N, 9, S, S): the three cameras' RGB, stacked."""
    diff = (pixels.to(torch.int16) - background.to(torch.int16)).abs()
    cams = diff.unflatten(1, (len(CAMERAS), 3)).amax(dim=2)
    return (cams > threshold * 255.0).to(torch.uint8) * 255


def weighted_image_loss(reconstruction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                        weight: float) -> torch.Tensor:  # fmt: skip
    """Squared error of the 9-channel `reconstruction` against `target` (both on the [0, 1]
    scale), each pixel weighted 1 + `weight` where `mask` (uint8 (N, 3, S, S), per camera) marks
    foreground, divided by the weights' sum: plain MSE when nothing is foreground."""
    per_camera = (reconstruction - target).square().unflatten(1, (len(CAMERAS), 3))
    w = 1.0 + weight * (mask > 0).to(per_camera.dtype).unsqueeze(2)
    return (w * per_camera).sum() / (w.sum() * 3)


class Foreground:
    """The suites' backgrounds on a device, to mark the foreground of a batch of frames."""

    def __init__(self, pixels: list[np.ndarray], episodes: list[dict], train: list[int],
                 seed: int, threshold: float, device: torch.device) -> None:  # fmt: skip
        bg, suite_of = backgrounds(pixels, episodes, train, seed)
        self.background = torch.from_numpy(bg).to(device)
        self.suite_of = torch.from_numpy(suite_of).to(device)
        self.threshold = threshold

    def mask(self, pixels: torch.Tensor, pairs: np.ndarray) -> torch.Tensor:
        """`foreground_mask` of the frames `pixels` (uint8 (N, 9, S, S)), which are the
        (episode, frame) `pairs` of the store the backgrounds were made from."""
        episode = torch.as_tensor(pairs[:, 0], device=self.suite_of.device)
        return foreground_mask(pixels, self.background[self.suite_of[episode]], self.threshold)
