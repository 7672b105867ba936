"""DreamerV3: faithfulness to the authors' 2023 recipe, the 2025 options, and the interface.

Each test pins a value or a gradient path of the recipe (DREAMERV3.md) so that a deviation
fails; sizes are tiny so the file runs in about a minute on one thread.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ccfit.config_base import ConfigError
from ccfit.continual.packnet import PackNet, PackNetConfig, prunable_weights
from ccfit.models.base import LATENT_KEY, Batch
from ccfit.models.dreamerv3 import DreamerV3, DreamerV3Config
from ccfit.models.dreamerv3.behavior import (
    behavior_losses,
    imagine,
    imagined_returns,
    replay_lambda_return,
)
from ccfit.models.dreamerv3.math import (
    ReturnNormalizer,
    TwoHot,
    categorical_kl,
    kl_loss,
    lambda_return,
    sample_onehot,
    symexp,
    symlog,
    unimix_logits,
)
from ccfit.models.dreamerv3.networks import normal_entropy, normal_log_prob
from ccfit.models.registry import make_model

L, B, S = 12, 4, 32


def tiny(obs_mode: str = "state", **kw) -> DreamerV3Config:
    sizes = dict(
        deter=32,
        hidden=32,
        stoch=4,
        classes=4,
        units=64,
        layers=1,
        cnn_depth=8,
        image_size=S,
        batch_size=B,
        seq_len=L,
        horizon=5,
    )
    return DreamerV3Config(obs_mode=obs_mode, **{**sizes, **kw})


def make(obs_mode: str = "state", seed: int = 0, **kw) -> tuple[DreamerV3, torch.nn.Module]:
    torch.manual_seed(seed)
    model = DreamerV3(tiny(obs_mode, **kw), device="cpu")
    return model, model.new_heads()


def make_batch(obs_mode: str = "state", length: int = L, size: int = B) -> Batch:
    """Smooth, learnable windows; window 1 crosses an episode boundary at row 6 after a
    success (terminated at row 5); rewards depend on the next observation."""
    t = torch.arange(length).float()[:, None, None]
    phase = torch.arange(size)[None, :, None]
    state = torch.sin(0.3 * t * torch.linspace(0.5, 2, 39) + phase)
    if obs_mode == "state":
        obs = {"state": state}
    else:
        yy, xx = torch.meshgrid(torch.arange(S), torch.arange(S), indexing="ij")
        cx = 8 + t.squeeze(-1) + 4 * torch.arange(size)[None, :]
        blob = ((xx - cx[..., None, None]) ** 2 + (yy - 16) ** 2 < 25).float()
        shade = torch.linspace(0.3, 1, 9)[None, None, :, None, None]
        obs = {
            "pixels": (blob[:, :, None] * shade * 255).to(torch.uint8),
            "proprio": state[..., :7].clone(),
        }
    is_first = torch.zeros(length, size, 1)
    terminated = torch.zeros(length, size, 1)
    if length > 6 and size > 1:
        is_first[6, 1] = 1.0
        terminated[5, 1] = 1.0
    reward = torch.cat([-(state[1:, :, :1] < 0).float(), torch.zeros(1, size, 1)])
    action = torch.sin(t + torch.arange(4)).expand(length, size, 4).clone()
    return Batch(
        obs, action, reward, terminated, is_first, torch.zeros(length, size, dtype=torch.long)
    )


def grads(loss: torch.Tensor, params) -> list[torch.Tensor | None]:
    return list(torch.autograd.grad(loss, list(params), retain_graph=True, allow_unused=True))


def nonzero(gs) -> bool:
    return any(g is not None and g.abs().sum() > 0 for g in gs)


# ------------------------------------------------------------------------------ config


def test_presets_defaults_and_validation():
    cfg = DreamerV3Config()
    assert (cfg.kl_dyn, cfg.kl_rep, cfg.free_nats, cfg.unimix) == (0.5, 0.1, 1.0, 0.01)
    assert (cfg.horizon, cfg.return_lambda, cfg.discount) == (15, 0.95, 0.997)
    assert (cfg.batch_size, cfg.seq_len, cfg.train_ratio, cfg.grad_clip) == (16, 64, 0.5, 1000)
    assert (cfg.actor_grad, cfg.critic_replay_scale) == ("dynamics", 0.0)
    paper = DreamerV3Config.preset("paper")
    assert (paper.deter, paper.hidden, paper.stoch, paper.classes) == (4096, 1024, 32, 32)
    assert (paper.units, paper.layers) == (1024, 5)
    assert DreamerV3Config.preset("cpu").deter == 128
    assert DreamerV3Config.preset("smoke").type == "dreamerv3"
    for bad in (
        dict(kl_dyn=-1.0),
        dict(actor_grad="ppo"),
        dict(imag_last=65),
        dict(obs_mode="pixels", image_size=48),
        dict(actor_min_std=2.0),
        dict(classes=1),
        dict(horizon=0.5),
        dict(vector_units=0),
        dict(vector_layers=-1),
    ):
        with pytest.raises(ConfigError):
            DreamerV3Config(**bad)


@pytest.mark.parametrize(
    "obs_mode, sizes, expected",
    [
        ("state", dict(deter=256, hidden=64, stoch=16, classes=8, units=128), 738_094),
        ("state", dict(vector_units=1024, vector_layers=5), 18_735_662),
        ("pixels", dict(vector_units=1024, vector_layers=5), 28_449_687),
    ],
)
def test_parameter_counts_equal_dreamerv3_torch_at_its_sizes(obs_mode, sizes, expected):
    """Trainable parameters (world model + actor + critic, no slow critic) equal those of
    object814/dreamerv3-torch counted at the same sizes (its `cpu` size, its defaults with
    39-D state, its defaults with 64 px 9-channel images + 7-D proprio): same layers."""
    cfg = DreamerV3Config(obs_mode=obs_mode, image_size=64, **sizes)
    with torch.device("meta"):
        model = DreamerV3(cfg, device="meta")
        heads = model.new_heads()
    trainable = [*model.backbone.parameters(), *heads.parameters()]
    assert sum(p.numel() for p in trainable if p.requires_grad) == expected


# ------------------------------------------------------------------------------ math


def test_symlog_symexp_and_twohot_round_trip():
    x = torch.tensor([-1e4, -3.0, -0.5, 0.0, 0.25, 7.0, 1e5])
    assert torch.allclose(symexp(symlog(x)), x, rtol=1e-5)
    assert torch.allclose(symlog(torch.tensor([math.e - 1])), torch.tensor([1.0]))
    twohot = TwoHot(255, -20.0, 20.0)
    assert torch.allclose(twohot.bins, torch.linspace(-20, 20, 255))
    y = torch.tensor([-1.0, -0.37, 0.0, 3.3, 250.0])[:, None]
    enc = twohot.encode(y)
    assert torch.allclose(enc.sum(-1), torch.ones(5)) and ((enc > 0).sum(-1) <= 2).all()
    assert torch.allclose(twohot.decode(enc), y, rtol=1e-4, atol=1e-5)
    # The weights interpolate linearly in symlog space between the two nearest bins.
    pos = (symlog(torch.tensor(-0.37)) + 20) / (40 / 254)
    assert torch.isclose(enc[1, int(pos) + 1], pos - int(pos), atol=1e-5)


def test_unimix_floor_and_finite_kl_of_one_hot_logits():
    onehot_logits = torch.tensor([[[1e4, -1e4, -1e4, -1e4]]])
    logp = unimix_logits(onehot_logits, 0.01)
    assert torch.allclose(logp.exp().min(), torch.tensor(0.01 / 4))
    assert torch.allclose(logp.exp().max(), torch.tensor(0.99 + 0.01 / 4))
    other = unimix_logits(torch.tensor([[[-1e4, 1e4, -1e4, -1e4]]]), 0.01)
    kl = categorical_kl(logp, other)
    hand = 0.9925 * math.log(0.9925 / 0.0025) + 0.0025 * math.log(0.0025 / 0.9925)
    assert torch.isfinite(kl).all() and torch.allclose(kl, torch.tensor([hand]), rtol=1e-4)
    # Without unimix the same KL is infinite (or NaN): the mix is what keeps it finite.
    raw = categorical_kl(unimix_logits(onehot_logits, 0.0), unimix_logits(other, 0.0))
    assert not torch.isfinite(raw).all()


def test_onehot_samples_follow_the_probabilities_with_straight_through_gradient():
    logits = torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4])).expand(50_000, 4).clone()
    logits.requires_grad_(True)
    torch.manual_seed(0)
    sample = sample_onehot(logits)
    hard = sample.detach().round()  # one-hot up to the rounding of onehot + p - sg(p)
    assert torch.allclose(sample.detach(), hard, atol=1e-6)
    assert torch.equal(hard.sum(-1), torch.ones(50_000))
    freq = hard.mean(0)  # binomial std <= 0.0022 at n = 50k
    assert torch.allclose(freq, torch.tensor([0.1, 0.2, 0.3, 0.4]), atol=0.01)
    # Straight through: the gradient is that of the probabilities.
    weights = torch.tensor([1.0, -2.0, 3.0, 0.5])
    (sample * weights).sum().backward()
    probs = F.softmax(logits.detach()[:1], -1)
    hand = probs * (weights - (probs * weights).sum())
    assert torch.allclose(logits.grad[:1], hand, atol=1e-6)


def test_kl_balancing_values_and_gradient_paths():
    torch.manual_seed(0)
    post = torch.randn(3, 5, 4, requires_grad=True)  # 3 rows, 5 latents, 4 classes
    prior = torch.randn(3, 5, 4, requires_grad=True)
    lp, lq = F.log_softmax(post, -1), F.log_softmax(prior, -1)
    dyn, rep = kl_loss(lp, lq, free_nats=0.0)
    hand = (lp.exp() * (lp - lq)).sum((-2, -1))  # KL summed over classes and latents
    assert torch.allclose(dyn, hand) and torch.allclose(rep, hand)
    assert not nonzero(grads(dyn.sum(), [post])) and nonzero(grads(dyn.sum(), [prior]))
    assert nonzero(grads(rep.sum(), [post])) and not nonzero(grads(rep.sum(), [prior]))


def test_free_nats_clamp_value_and_zero_gradient_below_one():
    post = torch.zeros(2, 3, 4)
    post[1, 0, 0] = 6.0  # row 1 far from the prior, row 0 close to it
    post.requires_grad_(True)
    prior = torch.zeros(2, 3, 4, requires_grad=True)
    lp, lq = F.log_softmax(post, -1), F.log_softmax(prior, -1)
    kl = categorical_kl(lp, lq)
    assert kl[0] < 1.0 < kl[1]
    dyn, rep = kl_loss(lp, lq, free_nats=1.0)
    assert dyn[0] == 1.0 and torch.isclose(dyn[1], kl[1])
    g_post, g_prior = torch.autograd.grad(dyn.sum() + rep.sum(), [post, prior])
    assert g_post[0].abs().sum() == 0 and g_prior[0].abs().sum() == 0
    assert g_post[1].abs().sum() > 0 and g_prior[1].abs().sum() > 0


def test_kl_terms_reach_the_right_rssm_parameters():
    """At row 0: dyn trains the prior (and the core feeding it), never the posterior or
    the encoder; rep trains the posterior and the encoder, never the prior."""
    model, _ = make(free_nats=0.0)
    rssm, enc = model.rssm, model.backbone.encoder
    batch = make_batch()
    embed = enc(batch.obs)
    deter, stoch, post, prior = rssm.observe(embed, batch.action, batch.is_first)
    dyn, rep = kl_loss(post[0], prior[0], 0.0)
    prior_net, post_net = list(rssm.img_out.parameters()), list(rssm.obs_out.parameters())
    assert nonzero(grads(dyn.sum(), prior_net)) and nonzero(grads(dyn.sum(), [rssm.initial]))
    assert not nonzero(grads(dyn.sum(), post_net + list(enc.parameters())))
    assert nonzero(grads(rep.sum(), post_net)) and nonzero(grads(rep.sum(), enc.parameters()))
    assert not nonzero(grads(rep.sum(), prior_net))


def test_lambda_return_against_hand_recursion():
    torch.manual_seed(1)
    H, gamma, lam = 4, 0.9, 0.7
    r, v = torch.randn(H, 2, 1), torch.randn(H + 1, 2, 1)
    c = torch.ones(H, 2, 1)
    c[1, 1] = 0.0  # window 1: arriving at s_2 ends the episode
    out = lambda_return(r, c, v, gamma, lam)
    hand = torch.zeros(H, 2, 1)
    nxt = v[H]
    for i in reversed(range(H)):
        hand[i] = r[i] + gamma * c[i] * ((1 - lam) * v[i + 1] + lam * nxt)
        nxt = hand[i]
    assert torch.allclose(out, hand)
    assert torch.allclose(out[1, 1], r[1, 1])  # continue 0: no bootstrapping past it
    assert torch.allclose(out[0, 1], r[0, 1] + gamma * ((1 - lam) * v[1, 1] + lam * r[1, 1]))
    mc = lambda_return(r, torch.ones(H, 2, 1), v, gamma, 1.0)  # lambda 1: Monte Carlo
    disc = gamma ** torch.arange(H).float()[:, None, None]
    assert torch.allclose(mc[0], (disc * r).sum(0) + gamma**H * v[H], atol=1e-6)


def test_return_normaliser_two_updates_exact_ema():
    norm = ReturnNormalizer(rate=0.01, q_low=0.05, q_high=0.95)
    x1 = torch.arange(101).float()  # percentiles 5 and 95
    x2 = torch.arange(101).float() * 10 - 300  # percentiles -250 and 650
    norm.update(x1)
    assert torch.isclose(norm.low, torch.tensor(0.05)) and torch.isclose(
        norm.high, torch.tensor(0.95)
    )
    assert norm.scale() == 1.0  # spread 0.9 < 1: not scaled up
    norm.update(x2)
    low, high = 0.99 * 0.05 + 0.01 * -250, 0.99 * 0.95 + 0.01 * 650
    assert torch.isclose(norm.low, torch.tensor(low)) and torch.isclose(
        norm.high, torch.tensor(high)
    )
    assert torch.isclose(norm.scale(), torch.tensor(high - low))


def test_replay_lambda_return_hand_values():
    gamma, lam = 0.9, 0.5
    r = torch.tensor([1.0, 2.0, 3.0, 4.0])[:, None, None]
    boot = torch.tensor([10.0, 20.0, 30.0, 40.0])[:, None, None]
    term = torch.tensor([0.0, 0.0, 1.0, 0.0])[:, None, None]
    valid = torch.tensor([1.0, 1.0, 1.0, 0.0])[:, None, None]
    out = replay_lambda_return(r, term, valid, boot, gamma, lam).flatten().tolist()
    g2 = 3.0  # terminated
    g1 = 2.0 + gamma * ((1 - lam) * 30.0 + lam * g2)
    g0 = 1.0 + gamma * ((1 - lam) * 20.0 + lam * g1)
    assert np.allclose(out, [g0, g1, g2, 40.0])
    valid[1] = 0.0  # row 1 ends its episode: G_1 = boot_1, G_0 bootstraps fully from it
    out = replay_lambda_return(r, term, valid, boot, gamma, lam).flatten().tolist()
    assert np.allclose(out[:2], [1.0 + gamma * 20.0, 20.0])


# ------------------------------------------------------------------------------ networks, RSSM


def test_zero_initialised_reward_and_critic_and_actor_bounds():
    model, heads = make()
    feat = torch.randn(7, model.cfg.feat_dim) * 3
    assert (heads.reward(feat) == 0).all() and (heads.critic(feat) == 0).all()
    assert heads.reward_mean(feat).abs().max() < 1e-6 and heads.value(feat).abs().max() < 1e-6
    assert (heads.cont(feat) != 0).all()  # only reward and critic start at zero
    assert torch.equal(heads.slow_value(feat), heads.value(feat))
    with torch.no_grad():
        heads.actor.out.bias.fill_(100.0)
        mean, std = heads.actor(feat)
        assert torch.allclose(std, torch.ones_like(std)) and torch.allclose(
            mean, torch.ones_like(mean)
        )
        heads.actor.out.bias.fill_(-100.0)
        mean, std = heads.actor(feat)
        assert torch.allclose(std, torch.full_like(std, 0.1))
        heads.actor.out.bias.zero_()
        heads.actor.out.weight.zero_()
        assert torch.allclose(heads.actor(feat)[1], 0.9 * torch.sigmoid(torch.tensor(2.0)) + 0.1)


def test_gru_is_the_2023_variant_and_learned_initial_state():
    model, _ = make()
    rssm = model.rssm
    with torch.no_grad():
        rssm.initial.uniform_(-2, 2)
    deter, stoch = rssm.initial_state(3)
    assert torch.allclose(deter, torch.tanh(rssm.initial).expand(3, -1))
    assert torch.equal(stoch, F.one_hot(rssm.prior(deter).argmax(-1), 4).float())
    assert rssm.gru_norm.eps == 1e-3 and isinstance(rssm.gru, torch.nn.Linear)
    h, z, a = (
        torch.randn(2, 32),
        F.one_hot(torch.randint(0, 4, (2, 4)), 4).float(),
        torch.rand(2, 4),
    )
    x = rssm.img_in(torch.cat([z.flatten(-2), a], -1))
    reset, cand, update = F.layer_norm(
        rssm.gru(torch.cat([h, x], -1)),
        (96,),
        eps=1e-3,
        weight=rssm.gru_norm.weight,
        bias=rssm.gru_norm.bias,
    ).chunk(3, -1)
    u = torch.sigmoid(update - 1)
    hand = u * torch.tanh(torch.sigmoid(reset) * cand) + (1 - u) * h
    assert torch.allclose(rssm.core(h, z, a), hand, atol=1e-6)
    # Actions outside [-1, 1] are clipped in value before the core.
    assert torch.allclose(rssm.core(h, z, 3 * a.sign()), rssm.core(h, z, a.sign()))


def test_episode_boundary_equals_separate_episodes():
    """Window 1 holds the end of one episode (rows 0-5) and the start of the next (6-11):
    its features equal those of the two episodes filtered separately."""
    model, _ = make()
    batch = make_batch()
    rssm = model.rssm

    def features(b: Batch) -> torch.Tensor:
        with torch.no_grad():
            deter, stoch, _, _ = rssm.observe(
                model.backbone.encoder(b.obs), b.action, b.is_first, sample=False
            )
            return rssm.feat(deter, stoch)

    whole = features(batch.select(torch.tensor([1])))
    first = features(make_sub(batch, 1, 0, 6))
    second = features(make_sub(batch, 1, 6, L))
    assert torch.allclose(whole[:6], first, atol=1e-6)
    assert torch.allclose(whole[6:], second, atol=1e-6)
    # Without the is_first flag the second part would continue the first episode.
    batch.is_first[6, 1] = 0.0
    assert not torch.allclose(features(batch.select(torch.tensor([1])))[6:], second, atol=1e-3)


def make_sub(batch: Batch, row: int, start: int, stop: int) -> Batch:
    pick = batch.select(torch.tensor([row]))
    cut = {k: v[start:stop] for k, v in pick.obs.items()}
    return Batch(
        cut,
        pick.action[start:stop],
        pick.reward[start:stop],
        pick.terminated[start:stop],
        pick.is_first[start:stop],
        pick.task[start:stop],
    )


@pytest.mark.parametrize("obs_mode", ["state", "pixels"])
def test_acting_step_by_step_reproduces_loss_posteriors(obs_mode):
    """observe/act one step at a time (posteriors sampled from the same RNG stream, actor in
    eval mode) give the deterministic states `loss` computes on the recorded episode."""
    model, heads = make(obs_mode)
    episode = make_batch(obs_mode, length=8, size=1)
    torch.manual_seed(5)
    state = model.initial_state(heads)
    actions = []
    for t in range(8):
        obs = {k: v[t, :1] for k, v in episode.obs.items()}
        if t < 3:  # seed steps with given actions, then the agent's own
            action = episode.action[t, :1].numpy()
            state = model.observe(obs, action, heads, state)
        else:
            action, state = model.act(obs, heads, state, eval_mode=True)
            assert action.shape == (1, 4) and np.abs(action).max() <= 1
            assert np.array_equal(state.action.numpy(), action)
        actions.append(torch.as_tensor(action[0]))
        if t == 7:
            last_deter = state.deter
    episode.action = torch.stack(actions)[:, None]
    episode.is_first[0] = 1.0
    torch.manual_seed(5)
    out = model.loss(episode, heads)
    assert torch.allclose(out.aux.deter[-1], last_deter, atol=1e-5)
    # The acting path at step 7 equals the loss's posterior; a different history does not.
    episode.action[2] += 0.5
    torch.manual_seed(5)
    assert not torch.allclose(model.loss(episode, heads).aux.deter[-1], last_deter, atol=1e-3)


def test_act_eval_is_the_tanh_mean_and_train_samples():
    model, heads = make()
    obs = {"state": torch.randn(1, 39)}
    state = model.initial_state(heads)
    a1, s1 = model.act(obs, heads, state, eval_mode=True)
    torch.manual_seed(0)
    a2, _ = model.act(obs, heads, state, eval_mode=False)
    mean, _ = heads.actor(model.rssm.feat(s1.deter, s1.stoch))
    assert np.allclose(a1, mean[0].detach().numpy()) and not np.allclose(a1, a2)
    assert a2.dtype == np.float32 and np.abs(a2).max() <= 1.0


def test_imagination_shapes_and_weights():
    model, heads = make()
    n, h = 6, model.cfg.horizon
    deter, stoch = model.rssm.initial_state(n)
    start_cont = torch.ones(n, 1)
    start_cont[0] = 0.0  # a terminal start contributes nothing
    traj = imagine(model.rssm, heads, deter, stoch, start_cont, h, 0.997)
    assert traj.feat.shape == (h + 1, n, model.cfg.feat_dim)
    assert traj.action.shape == (h, n, 4)
    assert traj.cont.shape == traj.weight.shape == (h + 1, n, 1)
    assert (traj.weight[:, 0] == 0).all() and torch.allclose(traj.weight[0, 1:], torch.ones(1))
    expected = torch.cumprod(0.997 * traj.cont, 0) / 0.997
    assert torch.allclose(traj.weight, expected)
    ret, value = imagined_returns(model.cfg, heads, traj)
    assert ret.shape == (h, n, 1) and value.shape == (h + 1, n, 1)


# ------------------------------------------------------------------------------ losses, gradients


def test_loss_terms_alignment_and_masks():
    """Reward/continue at row t + 1 predict transition t; rows whose transition crosses an
    episode boundary are masked; images are not averaged; inputs are not mutated."""
    model, heads = make("pixels")
    batch = make_batch("pixels")
    before = {k: v.clone() for k, v in batch.obs.items()}
    torch.manual_seed(0)
    out = model.loss(batch, heads)
    assert all(torch.equal(before[k], batch.obs[k]) for k in before)
    # Zero-initialised reward head: uniform two-hot logits, CE = log(255) on every row.
    assert math.isclose(out.logs["reward_loss"], math.log(255), rel_tol=1e-5)
    # Summed over 9 x 32 x 32 pixels: far above any per-pixel mean.
    assert out.logs["recon_pixels"] > 9 * S * S * 0.01
    parts = out.logs["recon"] + 0.5 * out.logs["dyn"] + 0.1 * out.logs["rep"]
    assert math.isclose(
        out.logs["total"], parts + out.logs["reward_loss"] + out.logs["cont_loss"], rel_tol=1e-5
    )
    # Continue target 1 - terminated[t], masked where row t + 1 starts an episode.
    feat = model.rssm.feat(out.aux.deter, out.aux.stoch)
    logit = heads.cont(feat[1:])
    target = 1 - batch.terminated[:-1]
    v = batch.valid()
    nll = F.binary_cross_entropy_with_logits(logit, target, reduction="none")
    assert math.isclose(
        out.logs["cont_loss"], float((nll * v).sum().detach() / v.sum()), rel_tol=1e-5
    )
    # Reward two-hot CE at row t + 1 toward reward[t], same mask (non-zero head this time).
    with torch.no_grad():
        heads.reward.out.weight.normal_(0, 0.5)
    torch.manual_seed(0)
    out = model.loss(batch, heads)
    feat = model.rssm.feat(out.aux.deter, out.aux.stoch)
    ce = heads.twohot.cross_entropy(heads.reward(feat[1:]), batch.reward[:-1])
    hand = float((ce * v).sum().detach() / v.sum())
    assert math.isclose(out.logs["reward_loss"], hand, rel_tol=1e-5)
    shifted = heads.twohot.cross_entropy(heads.reward(feat[:-1]), batch.reward[:-1])
    assert not math.isclose(out.logs["reward_loss"], float((shifted * v).sum().detach() / v.sum()))
    assert out.aux.start_cont[6, 1] == 1.0  # is_first row: not a terminal observation
    batch.is_first[6, 1] = 0.0  # now row 6 follows the success at row 5: terminal
    assert model.loss(batch, heads).aux.start_cont[6, 1] == 0.0


def test_reward_and_continue_gradients_reach_the_backbone():
    model, heads = make()
    batch = make_batch()
    torch.manual_seed(3)
    total = model.loss(batch, heads).total
    torch.manual_seed(3)
    task_terms = total - model.backbone_loss(batch)  # same samples: reward + continue
    backbone = [p for p in model.backbone.parameters()]
    assert nonzero(grads(task_terms, [model.rssm.gru.weight]))
    assert nonzero(grads(task_terms, model.backbone.encoder.parameters()))
    assert nonzero(grads(task_terms, heads.cont.parameters()))
    assert nonzero(grads(task_terms, backbone))


def test_backbone_loss_gives_no_gradient_to_heads():
    model, heads = make()
    model.backbone_loss(make_batch()).backward()
    assert all(p.grad is None for p in heads.parameters())
    assert nonzero([p.grad for p in model.backbone.parameters()])


def test_optimisers_cover_the_recipe_parameter_sets():
    model, heads = make()
    wm = model.world_model_optimizer(heads)
    ids = {id(p) for g in wm.param_groups for p in g["params"]}
    expected = [*model.backbone.parameters(), *heads.reward.parameters(), *heads.cont.parameters()]
    assert ids == {id(p) for p in expected}
    assert wm.defaults["lr"] == 1e-4 and wm.defaults["eps"] == 1e-8
    opts = model.head_optimizers(heads)
    assert set(opts) == {"actor", "critic"}
    assert {id(p) for g in opts["actor"].param_groups for p in g["params"]} == {
        id(p) for p in heads.actor.parameters()
    }
    assert {id(p) for g in opts["critic"].param_groups for p in g["params"]} == {
        id(p) for p in heads.critic.parameters()
    }
    assert all(o.defaults["lr"] == 3e-5 and o.defaults["eps"] == 1e-5 for o in opts.values())
    assert not any(p.requires_grad for p in heads.slow_critic.parameters())


@pytest.mark.parametrize("actor_grad", ["dynamics", "reinforce"])
def test_head_update_leaves_backbone_and_world_heads_bit_identical(actor_grad):
    model, heads = make(actor_grad=actor_grad, critic_replay_scale=0.3)
    batch = make_batch()
    opts = model.head_optimizers(heads)
    out = model.loss(batch, heads)
    frozen = {k: v.clone() for k, v in model.backbone.state_dict().items()}
    frozen.update(
        {
            f"h.{k}": v.clone()
            for k, v in heads.state_dict().items()
            if k.startswith(("reward.", "cont."))
        }
    )
    actor = [p.clone() for p in heads.actor.parameters()]
    critic = [p.clone() for p in heads.critic.parameters()]
    slow = [p.clone() for p in heads.slow_critic.parameters()]
    logs = model.head_update(batch, heads, out, opts)
    after = {**model.backbone.state_dict(), **{f"h.{k}": v for k, v in heads.state_dict().items()}}
    assert all(torch.equal(v, after[k]) for k, v in frozen.items())
    assert all(p.grad is None for p in model.backbone.parameters())
    assert all(p.grad is None for p in [*heads.reward.parameters(), *heads.cont.parameters()])
    assert logs["actor_grad_norm"] > 0
    assert any(not torch.equal(a, b) for a, b in zip(actor, heads.actor.parameters(), strict=True))
    assert any(
        not torch.equal(a, b) for a, b in zip(critic, heads.critic.parameters(), strict=True)
    )
    # Slow critic: 0.98 slow + 0.02 critic after the critic's step.
    for s0, s1, c1 in zip(
        slow, heads.slow_critic.parameters(), heads.critic.parameters(), strict=True
    ):
        assert torch.allclose(s1, 0.98 * s0 + 0.02 * c1, atol=1e-7)
    assert float(heads.retnorm.high) != 0.0  # statistics moved


def test_demo_cloning_reads_the_demonstration_windows_rows_with_a_real_transition_only():
    """`demo_bc_coef`: the actor's loss gains coef x the mean squared distance of its mean at
    row t's posterior to the demonstrated a_t, over the first `demos` windows' rows with a
    real transition; the critic's update is untouched, and without demonstrations in the
    batch the term is absent."""
    batch = dataclasses.replace(make_batch(), demos=2)  # window 1 ends an episode at row 5
    model, heads = make(demo_bc_coef=2.0)
    aux = model.loss(batch, heads).aux
    with torch.no_grad():
        feat = model.rssm.feat(aux.deter[:-1, :2], aux.stoch[:-1, :2])
        err = (heads.actor(feat)[0] - batch.action[:-1, :2]).pow(2).sum(-1)
    real = torch.ones(L - 1, 2)
    real[5, 1] = 0.0  # row 5 of window 1 is the episode's last observation: no transition
    by_hand = (err * real).sum() / real.sum()
    torch.testing.assert_close(model._demo_cloning(batch, heads, aux), by_hand)

    after = {}
    for demos in (2, 0):
        model, heads = make(demo_bc_coef=2.0)
        opts = model.head_optimizers(heads)
        out = model.loss(batch, heads)
        torch.manual_seed(3)  # the same imagination noise
        logs = model.head_update(dataclasses.replace(batch, demos=demos), heads, out, opts)
        after[demos] = (logs, [p.clone() for p in heads.actor.parameters()],
                        [p.clone() for p in heads.critic.parameters()])  # fmt: skip
    torch.testing.assert_close(after[2][0]["actor_demo_bc"], by_hand)
    assert "actor_demo_bc" not in after[0][0]
    assert all(torch.equal(a, b) for a, b in zip(after[2][2], after[0][2], strict=True))
    assert any(not torch.equal(a, b) for a, b in zip(after[2][1], after[0][1], strict=True))


def test_demo_cloning_alone_moves_the_actors_mean_to_the_demonstrated_action():
    """With no entropy bonus and zero-initialised reward and critic, imagination gives the
    actor no gradient: cloning alone must bring its mean to a demonstrated action."""
    model, heads = make(demo_bc_coef=1.0, actor_entropy=0.0, actor_lr=1e-3)
    target = torch.tensor([0.6, -0.4, 0.2, 0.8])
    batch = dataclasses.replace(make_batch(), demos=B)
    batch.action[:] = target
    opts = model.head_optimizers(heads)
    first = model.head_update(batch, heads, model.loss(batch, heads), opts)["actor_demo_bc"]
    for _ in range(300):
        last = model.head_update(batch, heads, model.loss(batch, heads), opts)["actor_demo_bc"]
    assert last < first / 20
    aux = model.loss(batch, heads).aux
    with torch.no_grad():
        mean, _ = heads.actor(model.rssm.feat(aux.deter[:-1], aux.stoch[:-1]))
    real = batch.valid().squeeze(-1) > 0  # the rows cloned: each has a demonstrated action
    assert (mean[real] - target).abs().mean() < 0.05  # the posteriors are sampled: not exact


def test_option_demo_bc_loss_nll_is_the_demonstrated_actions_negative_log_likelihood():
    """`demo_bc_loss='nll'`: the mean over the cloned rows of -log N(a_t; mean, std) under
    the actor's distribution at row t's posterior; unlike 'mse' it moves the actor's std."""
    batch = dataclasses.replace(make_batch(), demos=2)
    model, heads = make(demo_bc_coef=1.0, demo_bc_loss="nll")
    aux = model.loss(batch, heads).aux
    with torch.no_grad():
        mean, std = heads.actor(model.rssm.feat(aux.deter[:-1, :2], aux.stoch[:-1, :2]))
        nll = -normal_log_prob(batch.action[:-1, :2], mean, std).squeeze(-1)
        err = (mean - batch.action[:-1, :2]).pow(2).sum(-1)
    real = torch.ones(L - 1, 2)
    real[5, 1] = 0.0  # the episode's last observation in window 1: no transition
    by_hand = (nll * real).sum() / real.sum()
    torch.testing.assert_close(model._demo_cloning(batch, heads, aux), by_hand)
    mse_model, mse_heads = make(demo_bc_coef=1.0)  # the same seed: the same actor
    torch.testing.assert_close(
        mse_model._demo_cloning(batch, mse_heads, aux), (err * real).sum() / real.sum()
    )
    # The std's gradient: none from 'mse', some from 'nll'.
    for loss, moved in (("mse", False), ("nll", True)):
        model, heads = make(demo_bc_coef=1.0, demo_bc_loss=loss)
        aux = model.loss(batch, heads).aux
        bc = model._demo_cloning(batch, heads, aux)
        (grad,) = torch.autograd.grad(bc, heads.actor.out.bias)
        std_grad = grad[4:]  # the output's second half parameterises the std
        assert bool(std_grad.abs().max() > 0) is moved


@pytest.mark.parametrize("imag_cont", ["mode", "prob"])
def test_option_imag_cont_uses_the_continue_heads_mode_or_probability(imag_cont):
    """Imagined continue flags c_1..c_H: the continue head's prediction thresholded at 0.5
    ('mode', the recipe) or its probability ('prob'); the weights follow them."""
    model, heads = make(imag_cont=imag_cont)
    with torch.no_grad():  # a continue head whose probabilities are spread over (0, 1)
        heads.cont.out.weight.normal_(0, 2.0)
    n = 16
    deter, stoch = model.rssm.initial_state(n)
    with torch.no_grad():
        deter = deter + 0.5 * torch.randn_like(deter)
        torch.manual_seed(4)
        traj = imagine(model.rssm, heads, deter, stoch, torch.ones(n, 1), model.cfg.horizon,
                       model.cfg.discount, model.cfg.imag_cont)  # fmt: skip
        prob = torch.sigmoid(heads.cont(traj.feat[1:]))
    assert ((prob > 0.05) & (prob < 0.95)).any()  # the two forms differ here
    expected = prob if imag_cont == "prob" else (prob > 0.5).float()
    torch.testing.assert_close(traj.cont[1:], expected)
    weight = torch.cumprod(model.cfg.discount * traj.cont, 0) / model.cfg.discount
    torch.testing.assert_close(traj.weight, weight)
    with pytest.raises(ConfigError):
        tiny(imag_cont="sample")
    with pytest.raises(ConfigError):
        tiny(demo_bc_loss="l1")


# ------------------------------------------------------------------------------ 2025 options


def test_option_kl_dyn_scales_only_the_dynamics_term():
    totals = {}
    for scale in (0.5, 1.0):
        model, heads = make(seed=0, kl_dyn=scale)
        torch.manual_seed(1)
        totals[scale] = model.loss(make_batch(), heads).logs
    a, b = totals[0.5], totals[1.0]
    assert a["dyn"] == b["dyn"] and a["rep"] == b["rep"] and a["recon"] == b["recon"]
    assert a["dyn"] > 1.0
    assert math.isclose(b["total"] - a["total"], 0.5 * a["dyn"], rel_tol=1e-4)


@pytest.mark.parametrize("obs_mode", ["state", "pixels"])
def test_option_state_recon_scale_weighs_only_the_states_reconstruction(obs_mode):
    logs = {}
    for scale in (1.0, 100.0):
        model, heads = make(obs_mode, seed=0, state_recon_scale=scale)
        torch.manual_seed(1)
        logs[scale] = model.loss(make_batch(obs_mode), heads).logs
    a, b = logs[1.0], logs[100.0]
    for key in (
        "dyn",
        "rep",
        "reward_loss",
        "cont_loss",
        *(k for k in a if k.startswith("recon_")),
    ):
        assert a[key] == b[key], key
    if obs_mode == "state":
        assert a["recon_state"] > 0
        assert math.isclose(b["recon"] - a["recon"], 99.0 * a["recon_state"], rel_tol=1e-4)
        assert math.isclose(b["total"] - a["total"], 99.0 * a["recon_state"], rel_tol=1e-4)
    else:  # images and proprio keep their weights
        assert a["recon"] == b["recon"] and a["total"] == b["total"]
    with pytest.raises(ValueError, match="state_recon_scale"):
        tiny(state_recon_scale=0.0)


def _traj(model, heads, grad: bool):
    deter, stoch = model.rssm.initial_state(8)
    with torch.no_grad():
        deter = deter + 0.3 * torch.randn_like(deter)
    with torch.set_grad_enabled(grad):
        return imagine(
            model.rssm, heads, deter, stoch, torch.ones(8, 1), model.cfg.horizon, model.cfg.discount
        )


@pytest.mark.parametrize("actor_grad", ["dynamics", "reinforce"])
def test_option_actor_gradient_matches_its_estimator(actor_grad):
    """'dynamics': -(R - v) / scale, differentiated through the imagined rollout;
    'reinforce': -log pi(a) sg((R - v) / scale) with the *normalised* advantage."""
    model, heads = make(actor_grad=actor_grad, retnorm_rate=0.0)
    with torch.no_grad():  # non-zero reward/critic outputs and a return scale of 4
        heads.reward.out.weight.normal_(0, 0.5)
        heads.critic.out.weight.normal_(0, 0.5)
        heads.retnorm.low.fill_(-2.0)
        heads.retnorm.high.fill_(2.0)
    torch.manual_seed(2)
    traj = _traj(model, heads, grad=actor_grad == "dynamics")
    actor_loss, _, logs = behavior_losses(model.cfg, heads, traj)
    assert logs["return_scale"] == 4.0
    ret, value = imagined_returns(model.cfg, heads, traj)
    adv = (ret - value[:-1]) / 4.0
    mean, std = heads.actor(traj.feat[:-1].detach())
    bonus = 3e-4 * normal_entropy(std)
    if actor_grad == "dynamics":
        hand = -((adv + bonus) * traj.weight[:-1]).mean()
        assert traj.feat.requires_grad
    else:
        logp = normal_log_prob(traj.action, mean, std)
        hand = -((logp * adv.detach() + bonus) * traj.weight[:-1]).mean()
        assert not traj.feat.requires_grad and not traj.action.requires_grad
        unnormalised = -((logp * (ret - value[:-1]).detach() + bonus) * traj.weight[:-1]).mean()
        assert not torch.isclose(actor_loss, unnormalised, rtol=1e-3)
    assert torch.isclose(actor_loss, hand, rtol=1e-5)
    params = list(heads.actor.parameters())
    for g, h in zip(grads(actor_loss, params), grads(hand, params), strict=True):
        # The loss reuses imagination's actor outputs (one graph, another summation order):
        # equal up to float rounding relative to the gradient's scale.
        assert torch.allclose(g, h, rtol=1e-4, atol=1e-6 * float(h.abs().max()))
    if actor_grad == "dynamics":  # the gradient flows through the sampled actions
        no_path = -((adv.detach() + bonus) * traj.weight[:-1]).mean()
        assert not all(
            torch.allclose(g, h)
            for g, h in zip(grads(actor_loss, params), grads(no_path, params), strict=True)
        )


def test_replay_value_loss_averages_over_every_row_as_the_2025_code():
    from ccfit.models.dreamerv3.behavior import replay_value_loss

    model, heads = make(seed=0)
    torch.manual_seed(3)
    feat = torch.randn(6, 2, model.cfg.feat_dim)
    logits = torch.randn(6, 2, model.cfg.reward_bins)
    target = torch.randn(6, 2, 1)
    mask = torch.ones(6, 2, 1)
    mask[-1], mask[3:, 1] = 0, 0  # the last row and an episode boundary
    per_row = heads.twohot.cross_entropy(logits, target) + model.cfg.slow_critic_reg * (
        heads.twohot.cross_entropy(logits, heads.slow_value(feat))
    )
    expected = (per_row * mask).sum() / mask.numel()
    assert torch.isclose(replay_value_loss(model.cfg, heads, logits, feat, target, mask), expected)


def test_option_critic_replay_value_reaches_backbone_and_critic():
    outs, models = {}, {}
    for scale in (0.0, 0.3):
        model, heads = make(seed=0, critic_replay_scale=scale)
        torch.manual_seed(4)
        with torch.no_grad():  # a zero output layer passes no gradient to the features
            heads.critic.out.weight.normal_(0, 0.1)
        out = model.loss(make_batch(), heads)
        out.total.backward()
        outs[scale], models[scale] = out, (model, heads)
    off, on = outs[0.0], outs[0.3]
    assert "replay_value_loss" not in off.logs and off.aux.replay is None
    assert math.isclose(
        on.logs["total"] - off.logs["total"], 0.3 * on.logs["replay_value_loss"], rel_tol=1e-4
    )
    mask = on.aux.replay.mask
    assert mask[-1].sum() == 0 and mask[5, 1] == 0 and mask[4, 1] == 1  # last row, boundary
    enc_off = [p.grad for p in models[0.0][0].backbone.encoder.parameters()]
    enc_on = [p.grad for p in models[0.3][0].backbone.encoder.parameters()]
    assert not all(
        torch.allclose(a, b) for a, b in zip(enc_off, enc_on, strict=True)
    )  # reaches backbone
    for _, heads in models.values():  # the critic's gradient comes from head_update only
        assert all(p.grad is None for p in heads.critic.parameters())
    critics = {}
    for scale, (model, heads) in models.items():
        torch.manual_seed(5)
        model.head_update(make_batch(), heads, outs[scale], model.head_optimizers(heads))
        critics[scale] = [p.detach().clone() for p in heads.critic.parameters()]
    assert not all(torch.equal(a, b) for a, b in zip(critics[0.0], critics[0.3], strict=True))


# ------------------------------------------------------------------------------ learning, seams


@pytest.mark.parametrize(("obs_mode", "steps"), [("state", 300), ("pixels", 150)])
def test_world_model_overfits_one_batch(obs_mode, steps):
    """The world-model loss on one fixed batch falls by >= 90% (tiny model, lr 1e-3)."""
    model, heads = make(obs_mode, model_lr=1e-3)
    batch = make_batch(obs_mode)
    opt = model.world_model_optimizer(heads)
    first = last = None
    for _ in range(steps):
        out = model.loss(batch, heads)
        opt.zero_grad()
        out.total.backward()
        opt.step()
        first = first if first is not None else out.logs["total"]
        last = out.logs["total"]
    assert last <= 0.1 * first, (first, last)


def test_packnet_prunes_every_backbone_weight_including_the_gru():
    for obs_mode in ("state", "pixels"):
        model, _ = make(obs_mode)
        backbone = model.backbone
        prunable = prunable_weights(backbone)
        weights = [(n, p) for n, p in backbone.named_parameters() if p.dim() >= 2]
        missing = [n for n, p in weights if id(p) not in prunable]
        assert not missing, missing
        assert id(model.rssm.gru.weight) in prunable
    packnet = PackNet(PackNetConfig(keep_fraction=0.25, retrain_steps=0), num_tasks=2)
    packnet.before_task(0, backbone)
    packnet.after_task(0, backbone, None)
    zero = float((model.rssm.gru.weight == 0).float().mean())
    assert math.isclose(zero, 0.75, abs_tol=0.01)
    owned = float((packnet.owner["rssm.gru.weight"] == 0).float().mean())
    assert math.isclose(owned, 0.25, abs_tol=0.01)


def test_frozen_encoder_embeds_caches_and_is_reconstructed():
    from ccfit.models.encoders import FrozenEncoder, build_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config

    torch.manual_seed(0)
    enc_cfg = TDMPC2Config(obs_mode="state", enc_dim=32, latent_dim=64, num_enc_layers=2)
    frozen = FrozenEncoder(build_encoder(enc_cfg), enc_cfg)
    model = DreamerV3(tiny(), device="cpu", encoder=frozen)
    heads = model.new_heads()
    before = {k: v.clone() for k, v in frozen.state_dict().items()}
    batch = make_batch()
    cached = model.replay_obs(batch.obs)
    assert set(cached) == {LATENT_KEY} and cached[LATENT_KEY].shape == (L, B, 64)
    torch.manual_seed(1)
    raw = model.loss(batch, heads)
    torch.manual_seed(1)
    out = model.loss(
        Batch(cached, batch.action, batch.reward, batch.terminated, batch.is_first, batch.task),
        heads,
    )
    assert math.isclose(raw.logs["total"], out.logs["total"], rel_tol=1e-6)
    assert "recon_latent" in out.logs  # the decoder reconstructs what the encoder covers
    opt = model.world_model_optimizer(heads)
    opt.zero_grad()
    out.total.backward()
    opt.step()
    assert all(torch.equal(v, frozen.state_dict()[k]) for k, v in before.items())
    state = model.initial_state(heads)
    action, state = model.act({"state": batch.obs["state"][0, :1]}, heads, state, eval_mode=True)
    assert action.shape == (1, 4)
    with pytest.raises(ConfigError):
        DreamerV3(tiny("pixels"), device="cpu", encoder=frozen)


def test_registered_and_built_from_its_config():
    from ccfit.models.registry import config_class

    assert config_class("dreamerv3") is DreamerV3Config
    model = make_model(DreamerV3Config.preset("smoke"), "cpu")
    assert isinstance(model, DreamerV3) and model.device == torch.device("cpu")
    assert all(p.device.type == "cpu" for p in model.new_heads().parameters())
