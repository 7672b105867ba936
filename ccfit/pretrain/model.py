"""The autoencoder (the model's own pixel encoder + a decoder) and its held-out evaluation."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ccdata.render import CAMERAS
from ccfit.models.encoders import EncoderSpec, build_encoder
from ccfit.models.layers import mlp
from ccfit.pretrain.contrastive import ProjectionHead
from ccfit.pretrain.data import FrameStore
from ccfit.pretrain.foreground import Foreground

# =============================================================================== model


class PixelDecoder(nn.Module):
    """Latent -> (9-channel image on the [0, 1] scale, standardised proprio).

    A linear layer maps the latent to a (4c, b, b) grid with b = ceil(S / 8); three stride-2
    transposed convolutions (4c -> 2c -> c -> c) upsample it to 8b >= S, a 3x3 convolution
    gives the 9 channels, cropped to S x S. An MLP reconstructs the proprio.
    """

    def __init__(
        self, latent_dim: int, image_size: int, proprio_dim: int, channels: int, hidden: int
    ) -> None:
        super().__init__()
        c, self.image_size = channels, image_size
        self.base = math.ceil(image_size / 8)
        self.fc = nn.Sequential(nn.Linear(latent_dim, 4 * c * self.base**2), nn.ReLU())
        self.deconv = nn.Sequential(
            nn.Unflatten(-1, (4 * c, self.base, self.base)),
            nn.ConvTranspose2d(4 * c, 2 * c, 4, stride=2, padding=1), nn.ReLU(),
            nn.ConvTranspose2d(2 * c, c, 4, stride=2, padding=1), nn.ReLU(),
            nn.ConvTranspose2d(c, c, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(c, 9, 3, padding=1),
        )  # fmt: skip
        self.proprio = mlp(latent_dim, [hidden], proprio_dim)

    def forward(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = self.image_size
        # +0.5: an untrained decoder starts at mid-grey, the middle of the [0, 1] range
        img = self.deconv(self.fc(z))[..., :s, :s] + 0.5
        return img, self.proprio(z)


class Autoencoder(nn.Module):
    """The model's pixel encoder (built from `enc_cfg`) and a `PixelDecoder`."""

    def __init__(self, enc_cfg: EncoderSpec, decoder_channels: int, head: bool = False) -> None:
        super().__init__()
        self.encoder = build_encoder(enc_cfg)
        # the contrastive term's projection (`ccfit.pretrain.contrastive`); not saved with the
        # encoder
        self.head = ProjectionHead(enc_cfg.latent_dim) if head else None
        self.decoder = PixelDecoder(
            enc_cfg.latent_dim,
            enc_cfg.image_size,
            enc_cfg.proprio_dim,
            decoder_channels,
            enc_cfg.enc_dim,
        )

    def train(self, mode: bool = True) -> Autoencoder:
        super().train(mode)
        # The encoder's built-in random shift would move the input but not the target; this
        # module's own augmentation shifts both. No dropout or batch norm in the encoder, so
        # eval mode changes nothing else.
        self.encoder.train(False)
        return self

    def encode(self, pixels: torch.Tensor, proprio: torch.Tensor) -> torch.Tensor:
        return self.encoder({"pixels": pixels, "proprio": proprio})

    def forward(
        self, pixels: torch.Tensor, proprio: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decoder(self.encode(pixels, proprio))


# ============================================================================ evaluation


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else 10.0 * math.log10(1.0 / mse)


@torch.no_grad()
def evaluate_reconstruction(
    model: Autoencoder,
    store: FrameStore,
    pairs: np.ndarray,
    proprio_norm: tuple[torch.Tensor, torch.Tensor],
    batch_size: int,
    device: torch.device,
    foreground: Foreground | None = None,
) -> dict | None:
    """Per camera MSE and PSNR (dB, [0, 1] scale, reconstruction clamped to [0, 1]) over the
    frames `pairs`, plus the image and standardised-proprio MSE of the objective; given
    `foreground`, the MSE and PSNR over the foreground pixels alone and their share (the
    goal and objects are there: a whole-frame PSNR can be high with them missing)."""
    if len(pairs) == 0:
        return None
    was_training = model.training
    model.train(False)
    sq = torch.zeros(len(CAMERAS), dtype=torch.float64)
    obj_img, obj_prop = 0.0, 0.0
    fg_sq, fg_pixels = 0.0, 0
    mean, std = proprio_norm
    for start in range(0, len(pairs), batch_size):
        batch = pairs[start : start + batch_size]
        pix, prop = store.batch(batch)
        pix, prop = torch.from_numpy(pix).to(device), torch.from_numpy(prop).to(device)
        target = pix.float() / 255.0
        rec, rec_prop = model(pix, prop)
        obj_img += F.mse_loss(rec, target, reduction="sum").item()
        obj_prop += F.mse_loss(rec_prop, (prop - mean) / std, reduction="sum").item()
        err = (rec.clamp(0.0, 1.0) - target).square().unflatten(-3, (len(CAMERAS), 3))
        sq += err.sum(dim=(0, 2, 3, 4)).double().cpu()
        if foreground is not None:
            on = (foreground.mask(pix, batch) > 0).unsqueeze(2)
            fg_sq += float((err * on).sum())
            fg_pixels += int(on.sum())
    model.train(was_training)
    n = len(pairs)
    s = model.decoder.image_size
    per_cam = (sq / (n * 3 * s * s)).tolist()
    fg = {}
    if foreground is not None:
        fg_mse = fg_sq / max(3 * fg_pixels, 1)
        fg = {"foreground": {"mse": fg_mse, "psnr_db": _psnr(fg_mse),
                             "fraction": fg_pixels / (n * len(CAMERAS) * s * s)}}  # fmt: skip
    return {
        **fg,
        "frames": n,
        "cameras": {
            c: {"mse": m, "psnr_db": _psnr(m)} for c, m in zip(CAMERAS, per_cam, strict=True)
        },
        "image_mse": obj_img / (n * 9 * s * s),
        "proprio_mse": obj_prop / (n * mean.numel()),
    }
