"""The one path from environment / dataset observations to model tensors.

`obs_to_arrays` turns an env observation (one step) or a decoded dataset episode (a sequence)
into what replay stores, through the same channel-stacking code, so an encoder sees the same
layout online as in pretraining: topview, frontview, gripperPOV, each RGB, stacked into 9
channels. `model_input` batches such arrays into the tensors `WorldModel.act` reads.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

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


def model_input(arrays: Sequence[Mapping[str, np.ndarray]], device: torch.device
                ) -> dict[str, torch.Tensor]:  # fmt: skip
    """`obs_to_arrays` outputs of n observations -> model input tensors (n, ...) on
    `device` (one host-to-device copy per key)."""
    keys = arrays[0].keys()
    return {k: torch.from_numpy(np.stack([a[k] for a in arrays])).to(device, non_blocking=True)
            for k in keys}  # fmt: skip
