"""Keypoint image features (`SpatialSoftmax`, `PixelEncoder(keypoints=K)`)."""

import json

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from ccfit.models.encoders import (
    EncoderSpec,
    SpatialSoftmax,
    build_encoder,
    load_frozen_encoder,
    save_encoder,
)


def test_a_peak_comes_out_as_its_position_and_its_height():
    """A map that is flat but for one high cell gives that cell's (x, y) on [-1, 1] and the
    peak; a flat map gives the centre."""
    soft = SpatialSoftmax(5, 9)
    maps = torch.zeros(2, 2, 5, 9)
    maps[0, 0, 4, 0] = 50.0  # bottom-left
    maps[0, 1, 0, 8] = 50.0  # top-right
    out = soft(maps)
    assert out.shape == (2, 6)
    x0, y0, x1, y1, peak0, peak1 = out[0].tolist()
    assert (round(x0, 3), round(y0, 3), round(x1, 3), round(y1, 3)) == (-1.0, 1.0, 1.0, -1.0)
    assert (peak0, peak1) == (50.0, 50.0)
    assert torch.allclose(out[1, :4], torch.zeros(4), atol=1e-6)


def test_a_keypoint_encoder_encodes_saves_and_loads(tmp_path):
    """An encoder with keypoints has the latent of its spec, is saved with them in its settings
    and loads back to the same function; an encoder file from before keypoints existed (no
    such setting) still loads, as the strided stack."""
    spec = EncoderSpec(image_size=64, enc_dim=32, num_channels=8, latent_dim=16,
                       keypoints=6)  # fmt: skip
    torch.manual_seed(0)
    encoder = build_encoder(spec)
    obs = {"pixels": torch.randint(0, 255, (3, 9, 64, 64), dtype=torch.uint8),
           "proprio": torch.randn(3, 7)}  # fmt: skip
    encoder.eval()
    z = encoder(obs)
    assert z.shape == (3, 16) and encoder.conv_out == 18  # 6 maps: x, y and peak each
    path = tmp_path / "enc.safetensors"
    save_encoder(encoder, spec, path)
    frozen, saved = load_frozen_encoder(path)
    assert saved["keypoints"] == 6 and torch.equal(frozen(obs), z)

    old = EncoderSpec(image_size=64, enc_dim=32, num_channels=8, latent_dim=16)
    old_path = tmp_path / "old.safetensors"
    save_encoder(build_encoder(old), old, old_path)
    with safe_open(str(old_path), framework="pt") as f:  # its settings as written before
        header, state = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118
    header["spec"] = json.dumps({k: v for k, v in json.loads(header["spec"]).items()
                                 if k != "keypoints"})  # fmt: skip
    save_file(state, str(old_path), metadata=header)
    frozen, saved = load_frozen_encoder(old_path)
    assert "keypoints" not in saved and frozen.encoder.conv_out == 8 * 4 * 4
