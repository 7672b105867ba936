"""DreamerV3's encoder, decoder and heads.

Layers follow the 2023 code: Linear (no bias when a norm follows) -> LayerNorm (eps 1e-3)
-> SiLU; weights truncated-normal with variance 1 / fan_avg. The CNN halves the image with
kernel-4 stride-2 convolutions, doubling the depth, down to 4 x 4; the decoder mirrors it.
Vector inputs pass through symlog before their MLP, vector targets are predicted in symlog
space, images in [0, 1] (MSE summed over C x H x W, the recipe's scale).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ccfit.models.base import LATENT_KEY
from ccfit.models.dreamerv3.config import DreamerV3Config
from ccfit.models.dreamerv3.math import symexp, symlog

NORM_EPS = 1e-3


def init_weights(module: nn.Module) -> None:
    """Truncated normal with variance 1 / mean(fan_in, fan_out), zero bias (use `.apply`)."""
    if isinstance(module, nn.Linear | nn.Conv2d | nn.ConvTranspose2d):
        fan_in, fan_out = nn.init._calculate_fan_in_and_fan_out(module.weight)
        # 0.8796 is the std of a unit normal truncated at +-2: correct it back to `std`.
        std = math.sqrt(2.0 / (fan_in + fan_out)) / 0.87962566103423978
        nn.init.trunc_normal_(module.weight, std=std, a=-2 * std, b=2 * std)
        if module.bias is not None:
            nn.init.zeros_(module.bias)


def dense(in_dim: int, out_dim: int) -> nn.Sequential:
    """Linear -> LayerNorm -> SiLU (the bias is the norm's)."""
    return nn.Sequential(
        nn.Linear(in_dim, out_dim, bias=False), nn.LayerNorm(out_dim, eps=NORM_EPS), nn.SiLU()
    )


def mlp(in_dim: int, units: int, layers: int) -> nn.Sequential:
    """`layers` dense layers of width `units` (identity when layers = 0)."""
    dims = [in_dim] + [units] * layers
    return nn.Sequential(*(dense(dims[i], dims[i + 1]) for i in range(layers)))


class ChannelNorm(nn.LayerNorm):
    """LayerNorm over the channels of an (N, C, H, W) map, at every pixel."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def cnn_stages(image_size: int) -> int:
    """Stride-2 stages from `image_size` down to 4 x 4."""
    return int(math.log2(image_size // 4))


class Encoder(nn.Module):
    """obs -> embedding (..., out_dim): CNN on 'pixels' and symlog-MLP on 'proprio' (pixel
    mode) or on 'state' (state mode), concatenated. With a frozen pretrained encoder its
    output is the embedding (no gradient reaches it); 'latent' observations are such outputs
    cached in replay."""

    def __init__(self, cfg: DreamerV3Config, frozen: nn.Module | None = None) -> None:
        super().__init__()
        self.mode, self.frozen = cfg.obs_mode, frozen
        if frozen is not None:
            self.out_dim = frozen.latent_dim
            return
        vec_dim = cfg.state_dim if cfg.obs_mode == "state" else cfg.proprio_dim
        self.vector = mlp(vec_dim, cfg.vector_width, cfg.vector_depth)
        self.out_dim = cfg.vector_width if cfg.vector_depth else vec_dim
        if cfg.obs_mode == "pixels":
            self.image_size = cfg.image_size
            convs: list[nn.Module] = []
            ch_in, ch = 9, cfg.cnn_depth
            for _ in range(cnn_stages(cfg.image_size)):
                convs += [
                    nn.Conv2d(ch_in, ch, 4, 2, 1, bias=False),
                    ChannelNorm(ch, eps=NORM_EPS),
                    nn.SiLU(),
                ]
                ch_in, ch = ch, 2 * ch
            self.cnn = nn.Sequential(*convs, nn.Flatten())
            self.out_dim += ch_in * 16

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        if LATENT_KEY in obs:
            if self.frozen is None:
                raise ValueError(f"{LATENT_KEY!r} observations need a frozen encoder")
            return obs[LATENT_KEY].float()
        if self.frozen is not None:
            return self.frozen(obs).float()
        if self.mode == "state":
            return self.vector(symlog(_get(obs, "state").float()))
        pix = _get(obs, "pixels")
        s = self.image_size
        if pix.shape[-3:] != (9, s, s):
            raise ValueError(f"'pixels' must end in (9, {s}, {s}), got {tuple(pix.shape)}")
        lead = pix.shape[:-3]
        img = pix.reshape(-1, 9, s, s).float() / 255.0 - 0.5  # a new tensor: inputs untouched
        img = self.cnn(img).reshape(*lead, -1)
        return torch.cat([img, self.vector(symlog(_get(obs, "proprio").float()))], -1)


class Decoder(nn.Module):
    """Model state -> reconstructions of the observation; `loss` is summed per row.

    Targets: 'state' (state mode), 'pixels' + 'proprio' (pixel mode) or, with a frozen
    encoder, its latent (`LATENT_KEY`): the frozen encoder is the model's view of the
    observation, so the world model reconstructs that view (which replay can cache)."""

    def __init__(self, cfg: DreamerV3Config, frozen_dim: int | None = None) -> None:
        super().__init__()
        self.vectors: dict[str, int] = {}
        if frozen_dim is not None:
            self.vectors[LATENT_KEY] = frozen_dim
        elif cfg.obs_mode == "state":
            self.vectors["state"] = cfg.state_dim
        else:
            self.vectors["proprio"] = cfg.proprio_dim
        out = sum(self.vectors.values())
        self.state_scale = cfg.state_recon_scale
        self.vector = nn.Sequential(
            mlp(cfg.feat_dim, cfg.vector_width, cfg.vector_depth),
            nn.Linear(cfg.vector_width if cfg.vector_depth else cfg.feat_dim, out),
        )
        self.image = frozen_dim is None and cfg.obs_mode == "pixels"
        if self.image:
            stages = cnn_stages(cfg.image_size)
            self.top = cfg.cnn_depth * 2 ** (stages - 1)
            self.project = nn.Linear(cfg.feat_dim, 16 * self.top)
            convs: list[nn.Module] = []
            ch = self.top
            for _ in range(stages - 1):
                convs += [
                    nn.ConvTranspose2d(ch, ch // 2, 4, 2, 1, bias=False),
                    ChannelNorm(ch // 2, eps=NORM_EPS),
                    nn.SiLU(),
                ]
                ch //= 2
            convs.append(nn.ConvTranspose2d(ch, 9, 4, 2, 1))
            self.cnn = nn.Sequential(*convs)

    def loss(
        self, feat: torch.Tensor, obs: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(loss per row (...), per-target mean losses): symlog-MSE summed over vector dims
        (the state's times `state_recon_scale` in the loss; the logged parts are unscaled),
        MSE summed over C x H x W for images."""
        parts: dict[str, torch.Tensor] = {}
        pred = self.vector(feat).split(list(self.vectors.values()), -1)
        for (key, _), p in zip(self.vectors.items(), pred, strict=True):
            parts[key] = (p - symlog(_get(obs, key).float())).pow(2).sum(-1)
        if self.image:
            img = self._image(feat)
            target = _get(obs, "pixels").reshape(img.shape).float() / 255.0
            parts["pixels"] = (img - target).pow(2).sum((1, 2, 3)).reshape(feat.shape[:-1])
        weighted = [self.state_scale * v if k == "state" else v for k, v in parts.items()]
        total = torch.stack(weighted).sum(0)
        return total, {k: v.detach().mean() for k, v in parts.items()}

    def _image(self, feat: torch.Tensor) -> torch.Tensor:
        """Decoded images (N, 9, S, S) in [0, 1] scale for model states (..., feat)."""
        x = self.project(feat.reshape(-1, feat.shape[-1])).reshape(-1, self.top, 4, 4)
        return self.cnn(x) + 0.5

    def predict(self, feat: torch.Tensor) -> dict[str, torch.Tensor]:
        """The observation decoded from model states (..., feat), in the observation's own
        space (vectors mapped back from symlog, images in [0, 1]), each (..., D) flat: what
        open-loop predictions are measured in."""
        pred = self.vector(feat).split(list(self.vectors.values()), -1)
        out = {key: symexp(p) for key, p in zip(self.vectors, pred, strict=True)}
        if self.image:
            out["pixels"] = self._image(feat).reshape(*feat.shape[:-1], -1)
        return out


class Head(nn.Module):
    """MLP -> Linear(out_dim); `zero_init` zeroes the output layer (reward, critic), so the
    first predictions are exactly 0 and early returns are not dominated by noise."""

    def __init__(self, cfg: DreamerV3Config, out_dim: int, zero_init: bool = False) -> None:
        super().__init__()
        self.net = mlp(cfg.feat_dim, cfg.units, cfg.layers)
        self.out = nn.Linear(cfg.units if cfg.layers else cfg.feat_dim, out_dim)
        self.apply(init_weights)
        if zero_init:
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.out(self.net(feat))


class Actor(Head):
    """Normal(tanh(mean), std) with std = (max - min) sigmoid(x + 2) + min per action dim."""

    def __init__(self, cfg: DreamerV3Config) -> None:
        super().__init__(cfg, 2 * cfg.action_dim)
        self.min_std, self.max_std = cfg.actor_min_std, cfg.actor_max_std

    def forward(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std), each (..., action_dim)."""
        mean, std = super().forward(feat).chunk(2, -1)
        std = (self.max_std - self.min_std) * torch.sigmoid(std + 2.0) + self.min_std
        return torch.tanh(mean), std


def normal_log_prob(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """log N(x; mean, std) summed over the last dim -> (..., 1)."""
    z = (x - mean) / std
    lp = -0.5 * z.pow(2) - std.log() - 0.5 * math.log(2 * math.pi)
    return lp.sum(-1, keepdim=True)


def normal_entropy(std: torch.Tensor) -> torch.Tensor:
    """Entropy of independent normals summed over the last dim -> (..., 1)."""
    return (std.log() + 0.5 * math.log(2 * math.pi * math.e)).sum(-1, keepdim=True)


def bernoulli_nll(logit: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return F.binary_cross_entropy_with_logits(logit, target, reduction="none")


def _get(obs: dict[str, torch.Tensor], key: str) -> torch.Tensor:
    if key not in obs:
        raise ValueError(f"observation lacks {key!r}; has {sorted(obs)}")
    return obs[key]
