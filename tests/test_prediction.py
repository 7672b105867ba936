"""The 'prediction' capability of the world models (what the offline track scores): open-loop
prediction measured in a space that does not move with training, and the backbone-only
optimiser the offline track steps."""

from __future__ import annotations

import pytest
import torch

from ccfit.models.base import LATENT_KEY, Batch, Prediction
from ccfit.models.encoders import FrozenEncoder, build_encoder
from ccfit.models.registry import MODELS, config_class, make_model

CONTEXT, HORIZON, B, SIZE = 3, 4, 5, 32


def windows(obs_mode: str, rows: int = CONTEXT + HORIZON, task: int = 0) -> Batch:
    """Random windows inside one episode each (row 0 starts it)."""
    g = torch.Generator().manual_seed(0)
    if obs_mode == "state":
        obs = {"state": torch.randn(rows, B, 39, generator=g)}
    else:
        obs = {"pixels": torch.randint(0, 256, (rows, B, 9, SIZE, SIZE), generator=g,
                                       dtype=torch.uint8),
               "proprio": torch.randn(rows, B, 7, generator=g)}  # fmt: skip
    first = torch.zeros(rows, B, 1)
    first[0] = 1.0
    return Batch(obs, torch.rand(rows, B, 4, generator=g) * 2 - 1, torch.zeros(rows, B, 1),
                 torch.zeros(rows, B, 1), first, torch.full((rows, B), task))  # fmt: skip


def frozen_encoder(obs_mode: str) -> FrozenEncoder:
    torch.manual_seed(7)
    spec = config_class("tdmpc2").preset("smoke", obs_mode=obs_mode, image_size=SIZE)
    return FrozenEncoder(build_encoder(spec), spec)


def model_of(name: str, obs_mode: str, frozen: bool):
    torch.manual_seed(0)
    cfg = config_class(name).preset("smoke", obs_mode=obs_mode, image_size=SIZE)
    encoder = frozen_encoder(obs_mode) if frozen else None
    if encoder is not None and hasattr(cfg, "latent_dim"):
        cfg = type(cfg).preset("smoke", obs_mode=obs_mode, image_size=SIZE,
                               latent_dim=encoder.latent_dim)  # fmt: skip
    model = make_model(cfg, "cpu", encoder=encoder)
    model.begin_task(0, 100)
    return model


CASES = [
    ("dreamerv3", "state", False),
    ("dreamerv3", "pixels", False),
    ("dreamerv3", "pixels", True),
    ("tdmpc2", "pixels", True),
    ("pwm", "pixels", True),
]


@pytest.mark.parametrize("name, obs_mode, frozen", CASES)
def test_open_loop_predicts_the_rows_after_the_context_without_seeing_them(name, obs_mode, frozen):
    model = model_of(name, obs_mode, frozen)
    assert "prediction" in type(model).capabilities and isinstance(model, Prediction)
    batch = windows(obs_mode)
    out = model.open_loop(batch, CONTEXT, HORIZON)
    keys = {"state"} if obs_mode == "state" else {"pixels", "proprio"}
    assert set(out.predicted) == set(out.target) == set(out.last) == ({LATENT_KEY} if frozen
                                                                       else keys)  # fmt: skip
    for k in out.predicted:
        assert out.predicted[k].shape == out.target[k].shape
        assert out.predicted[k].shape[:2] == (HORIZON, B) and out.last[k].shape[0] == B
    # The targets and the persistence prediction are the observed rows, in the measured space.
    if frozen:
        with torch.no_grad():
            z = model.replay_obs(batch.obs)[LATENT_KEY]
        torch.testing.assert_close(out.target[LATENT_KEY], z[CONTEXT:])
        torch.testing.assert_close(out.last[LATENT_KEY], z[CONTEXT - 1])
    elif obs_mode == "state":
        assert torch.equal(out.target["state"], batch.obs["state"][CONTEXT:])
        assert torch.equal(out.last["state"], batch.obs["state"][CONTEXT - 1])
    else:
        pixels = batch.obs["pixels"].flatten(-3).float() / 255.0
        assert torch.equal(out.target["pixels"], pixels[CONTEXT:])
        assert torch.equal(out.target["proprio"], batch.obs["proprio"][CONTEXT:])
    # Deterministic, and blind to the rows it predicts: change them, the prediction stays.
    again = model.open_loop(batch, CONTEXT, HORIZON)
    hidden = windows(obs_mode)
    for v in hidden.obs.values():
        v[CONTEXT:] = v[CONTEXT:].flip(1)
    blind = model.open_loop(hidden, CONTEXT, HORIZON)
    for k in out.predicted:
        assert torch.equal(out.predicted[k], again.predicted[k])
        assert torch.equal(out.predicted[k], blind.predicted[k])
        assert not torch.equal(out.target[k], blind.target[k])
    # The actions drive it: other actions, another prediction.
    pushed = windows(obs_mode)
    pushed.action[CONTEXT - 1 :] = -pushed.action[CONTEXT - 1 :]
    moved = model.open_loop(pushed, CONTEXT, HORIZON)
    assert any(not torch.equal(out.predicted[k], moved.predicted[k]) for k in out.predicted)


def test_a_model_predicting_in_its_own_latent_space_offers_no_measurement_space():
    predicting = [n for n, cls in MODELS.items() if "prediction" in cls.capabilities]
    assert {"dreamerv3", "tdmpc2", "pwm"} <= set(predicting)
    for name in predicting:
        cfg = config_class(name).preset("smoke", obs_mode="pixels", image_size=SIZE)
        assert MODELS[name].measurement_space(cfg, True) == "frozen-encoder latent"
    assert MODELS["tdmpc2"].measurement_space(config_class("tdmpc2")(), False) is None
    assert MODELS["pwm"].measurement_space(config_class("pwm")(), False) is None
    assert MODELS["dreamerv3"].measurement_space(config_class("dreamerv3")(), False) == "state"
    with pytest.raises(ValueError, match="frozen encoder"):
        model_of("tdmpc2", "state", False).open_loop(windows("state"), CONTEXT, HORIZON)


@pytest.mark.parametrize("name, frozen", [("dreamerv3", False), ("tdmpc2", True), ("pwm", True)])
def test_backbone_optimizer_steps_the_trainable_backbone_only(name, frozen):
    model = model_of(name, "pixels" if frozen else "state", frozen)
    opt = model.backbone_optimizer()
    stepped = {id(p) for g in opt.param_groups for p in g["params"]}
    trainable = {id(p) for p in model.backbone.parameters() if p.requires_grad}
    heads = {id(p) for p in model.new_heads().parameters()}
    assert stepped <= trainable and not stepped & heads
    if name != "pwm":  # PWM's inactive experts join when activated (they are in, unused)
        assert stepped == trainable
    if frozen:
        assert not any(id(p) in stepped for p in model.backbone.encoder.parameters())
    batch = windows("pixels" if frozen else "state", rows=model.cfg.seq_len)
    before = [p.detach().clone() for g in opt.param_groups for p in g["params"]]
    opt.zero_grad()
    model.backbone_loss(batch).backward()
    opt.step()
    after = [p for g in opt.param_groups for p in g["params"]]
    assert any(not torch.equal(a, b) for a, b in zip(after, before, strict=True))
