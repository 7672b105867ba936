"""Observation encoders: `encoder(obs_dict) -> latent (..., latent_dim)`, SimNorm on the output.

- `StateEncoder`: MLP on the 39-D 'state'.
- `PixelEncoder`: the benchmark's fusion encoder. A TD-MPC2-style 4-conv branch reads the
  9-channel 'pixels' (topview, frontview, gripperPOV stacked by `ccfit.obs.stack_cameras`), an MLP
  branch reads the 7-D 'proprio', and a fusion MLP maps both to the latent.

Inputs may carry any number of leading dims (e.g. time-major (T, B, ...) batches).

Encoders are built from any config carrying the `EncoderSpec` fields (a TD-MPC2 or PWM config,
or an `EncoderSpec`), so this module depends on no model.

`save_encoder` / `load_frozen_encoder` store an encoder with the settings needed to rebuild it,
for the frozen-encoder diagnostic (pretrain once with `ccfit.pretrain`, then plug the same
weights into a model): safetensors weights with the settings in their header, and a JSON
sidecar recording how they were made.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch
from torch import nn

from ccdata.atomic import atomic_write
from ccfit.io import file_sha256
from ccfit.models.layers import Mish, NormedLinear, SimNorm, mlp


class StateEncoder(nn.Module):
    """MLP on obs['state'] with `num_layers - 1` hidden layers (at least one)."""

    def __init__(
        self, state_dim: int, enc_dim: int, num_layers: int, latent_dim: int, simnorm_dim: int
    ) -> None:
        super().__init__()
        self.state_dim = state_dim
        hidden = [enc_dim] * max(num_layers - 1, 1)
        self.net = mlp(state_dim, hidden, latent_dim, act=SimNorm(simnorm_dim))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = _require(obs, "state")
        if x.shape[-1] != self.state_dim:
            raise ValueError(f"'state' must end in {self.state_dim}, got {tuple(x.shape)}")
        return self.net(x.float())


def random_shift(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Shift each image (N, C, H, W) by up to `pad` pixels each way, repeating edge pixels.

    Same result as replicate-padding by `pad` and cropping at a random offset, but done with
    clamped gathers so that it also runs on uint8 (4x less memory traffic than float).
    """
    n, c, h, w = x.shape
    dy = torch.randint(-pad, pad + 1, (n, 1), device=x.device)
    dx = torch.randint(-pad, pad + 1, (n, 1), device=x.device)
    rows = (torch.arange(h, device=x.device) + dy).clamp(0, h - 1)  # (N, H)
    cols = (torch.arange(w, device=x.device) + dx).clamp(0, w - 1)  # (N, W)
    x = x.gather(2, rows[:, None, :, None].expand(n, c, h, w))
    return x.gather(3, cols[:, None, None, :].expand(n, c, h, w))


class SpatialSoftmax(nn.Module):
    """(N, K, H, W) feature maps -> (N, 3K): each map's expected (x, y) in [-1, 1] under a
    softmax over its pixels (one learned temperature), and its peak value (whether what it
    looks for is in view at all). A small thing's position comes out as two numbers a linear
    read-out gives back, where flattening a coarse map smears it over a few cells."""

    def __init__(self, height: int, width: int) -> None:
        super().__init__()
        self.log_temperature = nn.Parameter(torch.zeros(()))
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width),
                                indexing="ij")  # fmt: skip
        self.register_buffer("grid", torch.stack([xs.flatten(), ys.flatten()], -1),
                             persistent=False)  # fmt: skip

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        flat = maps.flatten(2)  # (N, K, HW)
        attention = torch.softmax(flat / self.log_temperature.exp(), dim=-1)
        where = attention @ self.grid  # (N, K, 2)
        return torch.cat([where.flatten(1), flat.amax(-1)], dim=-1)


IMAGE_TRUNKS = ("stacked", "per-camera")
"""How `PixelEncoder`'s conv stack reads the three cameras (`EncoderSpec.image_trunk`)."""


class PixelEncoder(nn.Module):
    """Conv branch on obs['pixels'] (uint8, 9 x S x S) + MLP branch on obs['proprio'], fused.

    Convs as TD-MPC2's 64 px encoder (7/2, 5/2, 3/2, 3/1, ReLU between); the flattened size is
    computed for any S >= 32. With `keypoints` K > 0 the branch keeps the first conv's half
    resolution instead (7/2, then 5/1 and 3/1 to K maps) and reads each map through a
    `SpatialSoftmax`: the goal marker and the objects are a pixel or two at 64 px, which the
    strided stack leaves out (docs/encoder.md). The image features go through a NormedLinear
    to `enc_dim`, are concatenated with the proprio branch's `enc_dim` features, and a fusion
    MLP maps them to the SimNorm latent. Random shifts (`shift` px) are applied in training
    mode only.

    `trunk` "per-camera" runs the conv stack on each camera's 3 channels apart (the same
    weights; the features side by side into the projection) instead of on the 9 stacked ones:
    stacked, the first conv adds up pixels of three views that share only their place in the
    image. The stack then computes three times as much after its first layer (a `cpu`
    pretraining step on all six suites took 0.29 s against 0.236: docs/encoder.md).
    """

    def __init__(
        self,
        image_size: int,
        proprio_dim: int,
        num_channels: int,
        enc_dim: int,
        num_layers: int,
        latent_dim: int,
        simnorm_dim: int,
        shift: int = 4,
        keypoints: int = 0,
        trunk: str = "stacked",
    ) -> None:
        super().__init__()
        if image_size < 32:
            raise ValueError(f"image_size must be >= 32, got {image_size}")
        if trunk not in IMAGE_TRUNKS:
            raise ValueError(f"image trunk must be one of {IMAGE_TRUNKS}, got {trunk!r}")
        self.image_size, self.proprio_dim, self.shift = image_size, proprio_dim, shift
        self.views = 3 if trunk == "per-camera" else 1  # conv inputs per frame
        self.view_channels = inputs = 9 // self.views
        c = num_channels
        if keypoints > 0:
            half = (image_size - 7) // 2 + 1  # the first conv's output side
            self.conv = nn.Sequential(
                nn.Conv2d(inputs, c, 7, stride=2), nn.ReLU(),
                nn.Conv2d(c, c, 5, stride=1, padding=2), nn.ReLU(),
                nn.Conv2d(c, keypoints, 3, stride=1, padding=1), SpatialSoftmax(half, half),
            )  # fmt: skip
        else:
            # Unpadded, the stack needs S >= 40 (64 -> 29 -> 13 -> 6 -> 4); below that the last
            # conv is padded so that 32 px still works (32 -> 13 -> 5 -> 2 -> 2).
            last_pad = 0 if image_size >= 40 else 1
            self.conv = nn.Sequential(
                nn.Conv2d(inputs, c, 7, stride=2), nn.ReLU(),
                nn.Conv2d(c, c, 5, stride=2), nn.ReLU(),
                nn.Conv2d(c, c, 3, stride=2), nn.ReLU(),
                nn.Conv2d(c, c, 3, stride=1, padding=last_pad), nn.Flatten(),
            )  # fmt: skip
        with torch.no_grad():
            flat = self.views * self.conv(torch.zeros(1, inputs, image_size, image_size)).shape[-1]
        self.conv_out = flat
        self.image_proj = NormedLinear(flat, enc_dim)
        self.proprio = mlp(proprio_dim, [enc_dim] * max(num_layers - 1, 1), enc_dim, act=Mish())
        self.fuse = mlp(2 * enc_dim, [enc_dim], latent_dim, act=SimNorm(simnorm_dim))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        pix, prop = _require(obs, "pixels"), _require(obs, "proprio")
        s = self.image_size
        if pix.shape[-3:] != (9, s, s):
            raise ValueError(f"'pixels' must end in (9, {s}, {s}), got {tuple(pix.shape)}")
        if prop.shape[-1] != self.proprio_dim:
            raise ValueError(f"'proprio' must end in {self.proprio_dim}, got {tuple(prop.shape)}")
        lead = pix.shape[:-3]
        x = pix.reshape(-1, 9, s, s)
        if self.training and self.shift > 0:
            x = random_shift(x, self.shift)
        x = x.float().div_(255.0).sub_(0.5)  # in place: these are the largest tensors here
        features = self.conv(x.reshape(-1, self.view_channels, s, s)).reshape(len(x), -1)
        img = self.image_proj(features).reshape(*lead, -1)
        return self.fuse(torch.cat([img, self.proprio(prop.float())], dim=-1))


def _require(obs: dict[str, torch.Tensor], key: str) -> torch.Tensor:
    if key not in obs:
        raise ValueError(f"observation lacks {key!r}; has {sorted(obs)}")
    return obs[key]


@dataclasses.dataclass(frozen=True)
class EncoderSpec:
    """The settings that define an encoder (a subset of the TD-MPC2 / PWM config fields)."""

    obs_mode: str = "pixels"
    """'state' or 'pixels'."""
    state_dim: int = 39
    """Size of the 'state' vector."""
    proprio_dim: int = 7
    """Size of the 'proprio' vector (pixel mode)."""
    image_size: int = 64
    """Side S of the (9, S, S) pixel input, at least 32."""
    enc_dim: int = 256
    """Hidden width of the encoder MLPs."""
    num_enc_layers: int = 2
    """Encoder depth in linear layers."""
    num_channels: int = 32
    """Channels of each conv layer (pixel mode)."""
    latent_dim: int = 512
    """Latent width, a multiple of `simnorm_dim`."""
    simnorm_dim: int = 8
    """SimNorm group size."""
    image_shift: int = 4
    """Random-shift augmentation pad in pixels (training mode only)."""
    keypoints: int = 0
    """Image features as this many keypoints (`SpatialSoftmax`: each feature map's expected
    position and peak, at half the image's resolution); 0: TD-MPC2's strided conv stack,
    flattened."""
    image_trunk: str = "stacked"
    """The conv stack on the 9 channel-stacked channels ('stacked', TD-MPC2's) or on each
    camera's 3 apart ('per-camera', `PixelEncoder`)."""

    def __post_init__(self) -> None:
        if self.obs_mode not in ("state", "pixels"):
            raise ValueError(f"encoder obs_mode must be 'state' or 'pixels', got {self.obs_mode!r}")
        if self.image_trunk not in IMAGE_TRUNKS:
            raise ValueError(f"encoder image_trunk must be one of {IMAGE_TRUNKS}, "
                             f"got {self.image_trunk!r}")  # fmt: skip
        for f in dataclasses.fields(self):
            if f.name in ("obs_mode", "image_trunk"):  # the two that are not counts
                continue
            value, low = getattr(self, f.name), 0 if f.name in ("image_shift", "keypoints") else 1
            if type(value) is not int or value < low:
                raise ValueError(f"encoder {f.name} must be an int >= {low}, got {value!r}")
        if self.latent_dim % self.simnorm_dim:
            raise ValueError(f"encoder latent_dim {self.latent_dim} must be a multiple of "
                             f"simnorm_dim {self.simnorm_dim}")  # fmt: skip
        if self.image_size < 32:
            raise ValueError(f"encoder image_size must be >= 32, got {self.image_size}")

    @classmethod
    def of(cls, cfg) -> EncoderSpec:
        """The spec of a model config (any object with these fields)."""
        return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cls)})


def build_encoder(cfg) -> nn.Module:
    """The encoder for `cfg.obs_mode` ('state' or 'pixels'); `cfg`: an `EncoderSpec` or a
    model config with its fields."""
    if cfg.obs_mode == "state":
        return StateEncoder(
            cfg.state_dim, cfg.enc_dim, cfg.num_enc_layers, cfg.latent_dim, cfg.simnorm_dim
        )
    if cfg.obs_mode == "pixels":
        return PixelEncoder(
            cfg.image_size,
            cfg.proprio_dim,
            cfg.num_channels,
            cfg.enc_dim,
            cfg.num_enc_layers,
            cfg.latent_dim,
            cfg.simnorm_dim,
            cfg.image_shift,
            cfg.keypoints,
            cfg.image_trunk,
        )
    raise ValueError(f"unknown obs_mode {cfg.obs_mode!r}; valid: state, pixels")


ENCODER_FORMAT = "ccfit-encoder-v1"


class FrozenEncoder(nn.Module):
    """A pretrained encoder whose weights never change: no gradients, always in eval mode
    (no augmentation), whatever `.train()` is called with."""

    def __init__(self, encoder: nn.Module, cfg) -> None:
        super().__init__()
        self.encoder = encoder.requires_grad_(False).eval()
        self.obs_mode, self.latent_dim = cfg.obs_mode, cfg.latent_dim

    def train(self, mode: bool = True) -> FrozenEncoder:
        return super().train(False)

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        with torch.no_grad():
            return self.encoder(obs)


SIDECAR_SUFFIX = ".json"
"""A safetensors encoder `X.safetensors` has its JSON sidecar at `X.json`."""


def sidecar_path(path: str | Path) -> Path:
    """The JSON sidecar of an encoder weights file (`enc.safetensors` -> `enc.json`)."""
    return Path(path).with_suffix(SIDECAR_SUFFIX)


def save_encoder(encoder: nn.Module, cfg, path: str | Path, metadata: dict | None = None) -> None:
    """Write `encoder` (built by `build_encoder(cfg)`; `cfg` a model config or an
    `EncoderSpec`) and its settings atomically.

    A path ending in `.safetensors` gets safetensors weights whose header metadata holds the
    format and the settings (so the weights file alone rebuilds the encoder), plus a JSON sidecar
    (`sidecar_path`) with the settings, the weights' SHA-256 and `metadata` (e.g. how it was
    trained). Any other suffix gets the older single `torch.save` file (no sidecar).
    """
    if isinstance(encoder, FrozenEncoder):
        encoder = encoder.encoder
    spec = dataclasses.asdict(EncoderSpec.of(cfg))
    state = {k: v.detach().cpu().contiguous() for k, v in encoder.state_dict().items()}
    path = Path(path)
    if path.suffix != ".safetensors":
        payload = {"format": ENCODER_FORMAT, "spec": spec, "state_dict": state}
        atomic_write(path, lambda tmp: torch.save(payload, tmp))
        return
    from safetensors.torch import save_file

    header = {"format": ENCODER_FORMAT, "spec": json.dumps(spec, sort_keys=True)}
    atomic_write(path, lambda tmp: save_file(state, tmp, metadata=header))
    sidecar = {
        "format": ENCODER_FORMAT,
        "weights": path.name,
        "weights_sha256": weights_sha256(path),
        "spec": spec,
        **(metadata or {}),
    }
    text = json.dumps(sidecar, indent=2, sort_keys=True) + "\n"
    atomic_write(sidecar_path(path), lambda tmp: Path(tmp).write_text(text))


def weights_sha256(path: str | Path) -> str:
    """The SHA-256 of an encoder file's bytes: what names its weights wherever it lies."""
    return file_sha256(path)


def read_encoder_sidecar(path: str | Path) -> dict:
    """The JSON sidecar of a safetensors encoder (settings, training record); ValueError if
    absent or unreadable."""
    side = sidecar_path(path)
    try:
        return json.loads(side.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"cannot read encoder sidecar {side}: {err}") from err


def _read_checkpoint(path: Path) -> tuple[dict, dict]:
    """(spec, state_dict) of either file format; ValueError for anything unreadable."""
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic == b"PK\x03\x04":  # torch.save's zip container
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # noqa: BLE001 - any unpickling failure means a bad file
            raise ValueError(f"cannot read encoder checkpoint {path}: {err}") from err
        if not isinstance(ck, dict) or ck.get("format") != ENCODER_FORMAT:
            raise ValueError(f"{path} is not a {ENCODER_FORMAT} encoder checkpoint")
        spec, state = ck.get("spec"), ck.get("state_dict")
        if not isinstance(spec, dict) or not isinstance(state, dict):
            raise ValueError(f"{path} lacks its encoder settings or weights (spec, state_dict)")
        return dict(spec), state
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            header = f.metadata() or {}
            state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - not a dict
    except Exception as err:  # noqa: BLE001 - a corrupt header raises various errors
        raise ValueError(f"cannot read encoder checkpoint {path}: {err}") from err
    if header.get("format") != ENCODER_FORMAT or "spec" not in header:
        raise ValueError(f"{path} is not a {ENCODER_FORMAT} encoder checkpoint")
    try:
        spec = json.loads(header["spec"])
    except json.JSONDecodeError as err:
        raise ValueError(f"encoder checkpoint {path}: its settings are not JSON ({err})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"encoder checkpoint {path}: its settings are not a JSON object")
    return spec, state


def load_frozen_encoder(
    path: str | Path, device: torch.device | str = "cpu"
) -> tuple[FrozenEncoder, dict]:
    """Rebuild an encoder written by `save_encoder` (safetensors or torch file) and freeze it.

    Returns (frozen encoder on `device`, its settings); pass the settings into the model's
    config (e.g. `TDMPC2Config.preset(..., **spec)`) so latent size and inputs agree.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"encoder checkpoint not found: {path}")
    spec, state = _read_checkpoint(path)
    try:
        cfg = EncoderSpec(**spec)
    except (TypeError, ValueError) as err:
        raise ValueError(f"encoder checkpoint {path} has invalid settings: {err}") from err
    encoder = build_encoder(cfg)
    try:
        encoder.load_state_dict(state)
    except RuntimeError as err:  # torch lists the keys and shapes over several lines
        detail = " ".join(str(err).split())
        raise ValueError(f"encoder checkpoint {path} does not match its settings: {detail}"
                         ) from err  # fmt: skip
    return FrozenEncoder(encoder, cfg).to(device), spec
