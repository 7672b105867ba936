"""The one path from environment / dataset observations to model tensors.

Live frames (`obs_to_tensors`, one env step) and offline frames (`stack_cameras` on a whole
decoded episode) go through the same channel-stacking code, so an encoder sees the same layout
online as in pretraining: topview, frontview, gripperPOV, each RGB, stacked into 9 channels.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from ccdata.render import CAMERAS

OBS_MODES: tuple[str, ...] = ("state", "pixels")
"""'state': the 39-D privileged state; 'pixels': 9-channel images plus 7-D proprio."""


def check_mode(mode: str) -> str:
    if mode not in OBS_MODES:
        raise ValueError(f"unknown observation mode {mode!r}; valid: {', '.join(OBS_MODES)}")
    return mode


def stack_cameras(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """Camera images (..., H, W, 3) uint8 keyed by camera -> (..., 9, H, W) uint8.

    Works on one frame (H, W, 3) or a sequence (T, H, W, 3).
    """
    missing = [c for c in CAMERAS if c not in images]
    if missing:
        raise ValueError(f"missing camera images {missing}; need all of {list(CAMERAS)}")
    frames = [np.asarray(images[c]) for c in CAMERAS]
    shape = frames[0].shape
    for cam, f in zip(CAMERAS, frames, strict=True):
        if f.shape != shape or f.shape[-1] != 3 or f.dtype != np.uint8:
            raise ValueError(
                f"camera {cam!r}: expected uint8 (..., H, W, 3) like {shape}, "
                f"got {f.dtype} {f.shape}"
            )
    # (..., H, W, 3) -> (..., 3, H, W), then concatenate the cameras along channels.
    chw = [np.moveaxis(f, -1, -3) for f in frames]
    return np.ascontiguousarray(np.concatenate(chw, axis=-3))


def obs_to_arrays(obs: Mapping[str, np.ndarray], mode: str) -> dict[str, np.ndarray]:
    """Env observation dict -> the arrays stored in replay for `mode` (one step or a sequence)."""
    check_mode(mode)
    if mode == "state":
        return {"state": np.asarray(obs["state"], dtype=np.float32)}
    return {
        "pixels": stack_cameras(obs),
        "proprio": np.asarray(obs["proprio"], dtype=np.float32),
    }


def obs_to_tensors(obs: Mapping[str, np.ndarray], mode: str) -> dict[str, torch.Tensor]:
    """Env observation dict -> CPU tensors: {'state'} or {'pixels' (9,S,S) uint8, 'proprio'}."""
    return {k: torch.from_numpy(v) for k, v in obs_to_arrays(obs, mode).items()}
