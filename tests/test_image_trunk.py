"""The per-camera conv trunk (`PixelEncoder(trunk="per-camera")`, `EncoderSpec.image_trunk`)."""

import pytest
import torch

from ccfit.models.encoders import EncoderSpec, build_encoder, load_frozen_encoder, save_encoder
from ccfit.models.tdmpc2 import TDMPC2Config
from ccfit.pretrain.config import PretrainConfig

SPEC = dict(image_size=64, enc_dim=32, num_channels=8, latent_dim=16)  # fmt: skip


def _obs(n: int = 2) -> dict[str, torch.Tensor]:
    return {"pixels": torch.randint(0, 255, (n, 9, 64, 64), dtype=torch.uint8),
            "proprio": torch.randn(n, 7)}  # fmt: skip


def test_each_camera_goes_through_the_trunk_alone():
    """A camera's conv features change with its own pixels only: changing the front camera
    (channels 3-5) moves its third of the features and leaves the other two. Stacked, the
    first conv mixes the cameras, and every feature moves."""
    torch.manual_seed(0)
    apart = build_encoder(EncoderSpec(**SPEC, image_trunk="per-camera")).eval()
    stacked = build_encoder(EncoderSpec(**SPEC)).eval()
    assert apart.conv_out == 3 * stacked.conv_out
    obs = _obs()
    changed = {**obs, "pixels": obs["pixels"].clone()}
    changed["pixels"][:, 3:6] = 255 - changed["pixels"][:, 3:6]

    def features(encoder, o):  # what the conv stack gives inside the encoder's forward
        seen = []
        hook = encoder.conv.register_forward_hook(lambda m, i, out: seen.append(out))
        try:
            encoder(o)
        finally:
            hook.remove()
        return seen[0].reshape(len(o["pixels"]), encoder.views, -1)

    before, after = features(apart, obs), features(apart, changed)
    moved = [not torch.equal(before[:, k], after[:, k]) for k in range(3)]
    assert moved == [False, True, False]
    assert not torch.equal(features(stacked, obs), features(stacked, changed))


def test_a_per_camera_encoder_saves_loads_and_reaches_the_model_config(tmp_path):
    """The trunk is a setting of the encoder file: it loads back to the same function, and a
    pretraining run and a model preset take it as given; anything else is refused."""
    spec = EncoderSpec(**SPEC, image_trunk="per-camera")
    torch.manual_seed(0)
    encoder = build_encoder(spec).eval()
    obs = _obs(3)
    path = tmp_path / "enc.safetensors"
    save_encoder(encoder, spec, path)
    frozen, saved = load_frozen_encoder(path)
    assert saved["image_trunk"] == "per-camera" and torch.equal(frozen(obs), encoder(obs))
    pretrain = PretrainConfig.preset("smoke", image_trunk="per-camera")
    assert pretrain.encoder_config().image_trunk == "per-camera"
    assert pretrain.identity()["image_trunk"] == "per-camera"
    assert "image_trunk" not in PretrainConfig.preset("smoke").identity()  # legacy value
    assert TDMPC2Config.preset("smoke", obs_mode="pixels").image_trunk == "stacked"
    with pytest.raises(ValueError, match="image_trunk must be one of"):
        EncoderSpec(**SPEC, image_trunk="per-view")
    with pytest.raises(ValueError, match="image_trunk must be one of"):
        PretrainConfig.preset("smoke", image_trunk="per-view")
    with pytest.raises(ValueError, match="image_trunk must be one of"):
        TDMPC2Config.preset("smoke", obs_mode="pixels", image_trunk="per-view")


def test_an_encoder_file_from_before_the_trunk_setting_loads_as_stacked(tmp_path):
    """A weights file whose settings have no `image_trunk` (every encoder made before it)
    loads as the stacked trunk it was, computing what it computed."""
    import json

    from safetensors.torch import save_file

    from ccfit.models.encoders import ENCODER_FORMAT

    spec = EncoderSpec(**SPEC)
    torch.manual_seed(0)
    encoder = build_encoder(spec).eval()
    old = {k: v for k, v in spec.__dict__.items() if k != "image_trunk"}
    path = tmp_path / "old.safetensors"
    save_file({k: v.contiguous() for k, v in encoder.state_dict().items()}, str(path),
              metadata={"format": ENCODER_FORMAT, "spec": json.dumps(old)})  # fmt: skip
    frozen, saved = load_frozen_encoder(path)
    obs = _obs(3)
    assert "image_trunk" not in saved and frozen.encoder.views == 1
    assert torch.equal(frozen(obs), encoder(obs))
