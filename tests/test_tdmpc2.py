"""TD-MPC2: layers, encoders, losses, updates and planning at smoke size."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ccfit.config_base import ConfigError
from ccfit.models.base import Batch
from ccfit.models.encoders import random_shift
from ccfit.models.layers import EnsembleMLP, SimNorm, TwoHot, mish, mlp, quantiles, symexp, symlog
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2_SIZES, TDMPC2Config, modules_in_eval
from ccfit.obs import stack_cameras

try:
    from replay_data import random_buffer
except ImportError:  # tests/ imported as a package
    from tests.replay_data import random_buffer

MODES = ("state", "pixels")
SIZE = 32  # pixel side for tests
B = 16


def make_cfg(mode: str, **kw) -> TDMPC2Config:
    return TDMPC2Config.preset("smoke", obs_mode=mode, image_size=SIZE, **kw)


def make_batch(cfg: TDMPC2Config, seed: int = 0, batch: int = B) -> Batch:
    """Windows of cfg.seq_len rows from a real buffer of short random episodes."""
    return random_buffer(cfg, seed=seed).sample(batch, cfg.seq_len)


def build(mode: str, seed: int = 0, **kw):
    torch.manual_seed(seed)
    model = TDMPC2(make_cfg(mode, **kw), device="cpu")
    heads = model.new_heads()
    return model, heads


def update(model, heads, opt, head_opts, batch):
    out = model.loss(batch, heads)
    opt.zero_grad(set_to_none=True)
    out.total.backward()
    params = [p for g in opt.param_groups for p in g["params"]]
    torch.nn.utils.clip_grad_norm_(params, model.cfg.grad_clip)
    opt.step()
    model.head_update(batch, heads, out, head_opts)
    return out


# ------------------------------------------------------------------------------------ layers


def test_two_hot_round_trip_and_symlog():
    th = TwoHot(101, -10.0, 10.0)
    x = torch.tensor([-1.0, -0.37, 0.0, 0.25, 3.0, 120.0, -500.0]).unsqueeze(-1)
    probs = th.encode(x)
    assert probs.shape == (7, 101)
    torch.testing.assert_close(probs.sum(-1), torch.ones(7))
    assert ((probs > 0).sum(-1) <= 2).all()
    torch.testing.assert_close(th.decode(probs), x, rtol=1e-4, atol=1e-5)
    # Values beyond the support clamp to its ends.
    big = th.decode(th.encode(torch.tensor([[1e9]])))
    torch.testing.assert_close(big, symexp(torch.tensor([[10.0]])))
    torch.testing.assert_close(symexp(symlog(x)), x)
    # Cross-entropy is smallest for logits matching the target.
    target = torch.tensor([[-0.5]])
    good = torch.log(th.encode(target) + 1e-8)
    bad = torch.log(th.encode(torch.tensor([[2.0]])) + 1e-8)
    assert th.cross_entropy(good, target).item() < th.cross_entropy(bad, target).item() - 1.0
    with pytest.raises(ValueError, match="num_bins"):
        TwoHot(1, -1.0, 1.0)


def test_closed_form_mish_equals_torch_mish_in_value_and_gradient():
    # the range covers both sides of the clamp and the tail where x n / (n + 2) is tiny
    x = torch.linspace(-60, 60, 24_001, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(mish, (x[::997].detach().clone().requires_grad_(),))
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        xd = x.detach().to(dtype).requires_grad_()
        ours, ref = mish(xd), torch.nn.functional.mish(xd)
        torch.testing.assert_close(ours, ref, rtol=tol, atol=tol)
        g_ours, g_ref = (torch.autograd.grad(y.sum(), xd)[0] for y in (ours, ref))
        torch.testing.assert_close(g_ours, g_ref, rtol=tol, atol=tol)
        with torch.no_grad():  # no autograd Function there; the same arithmetic
            assert torch.equal(mish(xd), ours.detach())
        assert torch.equal(mish(xd.detach()), ours.detach())
    tail = torch.tensor([-30.0, -15.0, -8.0])  # relative accuracy where the value is ~x e^x
    torch.testing.assert_close(mish(tail), torch.nn.functional.mish(tail), rtol=1e-5, atol=0)
    half = torch.linspace(-8, 30, 500, dtype=torch.float16)
    assert torch.isfinite(mish(half)).all()
    torch.testing.assert_close(mish(half).float(), torch.nn.functional.mish(half.float()),
                               rtol=2e-3, atol=2e-3)  # fmt: skip


def test_mish_off_the_cpu_is_one_kernel():
    # A GPU's eager step is launch-bound: off the CPU, mish dispatches torch's one Mish kernel,
    # not the closed form's seven (seen on the meta device, which runs no arithmetic).
    from torch.utils._python_dispatch import TorchDispatchMode

    class Ops(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.names = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.names.append(func.overloadpacket.__name__)
            return func(*args, **(kwargs or {}))

    ops = {}
    for device in ("meta", "cpu"):
        x = torch.ones(4, device=device)
        with Ops() as ops[device]:
            mish(x)
    assert ops["meta"].names == ["mish"]
    assert len(ops["cpu"].names) == 7 and "mish" not in ops["cpu"].names


def test_quantiles_are_torch_quantile_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    for n in (1, 2, 3, 240, 3841):
        x = torch.randn(n, generator=g) * 50
        qs = (0.0, 0.05, 0.5, 0.95, 1.0)
        assert torch.equal(quantiles(x, qs), torch.quantile(x, torch.tensor(qs)))


def test_simnorm_and_ensemble():
    z = SimNorm(8)(torch.randn(5, 32))
    torch.testing.assert_close(z.view(5, 4, 8).sum(-1), torch.ones(5, 4))
    torch.manual_seed(0)
    ens = EnsembleMLP(3, 6, [16, 16], 5)
    with torch.no_grad():
        for p in ens.parameters():
            p.normal_()
    x = torch.randn(2, 4, 6)
    out = ens(x)
    assert out.shape == (3, 2, 4, 5)
    # Each member equals an ordinary MLP holding that member's weights.
    ref = mlp(6, [16, 16], 5)
    with torch.no_grad():
        for k in range(3):
            for i, layer in enumerate(ens.hidden):
                ref[i].weight.copy_(layer.weight[k].T)
                ref[i].bias.copy_(layer.bias[k, 0])
                ref[i].ln.weight.copy_(layer.ln_weight[k, 0])
                ref[i].ln.bias.copy_(layer.ln_bias[k, 0])
            ref[-1].weight.copy_(ens.out.weight[k].T)
            ref[-1].bias.copy_(ens.out.bias[k, 0])
            torch.testing.assert_close(out[k], ref(x), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ens(x, members=torch.tensor([2, 0])), out[[2, 0]])
    # detach=True: gradients reach the input, not the weights.
    xi = x.clone().requires_grad_(True)
    ens(xi, detach=True).sum().backward()
    assert xi.grad is not None and all(p.grad is None for p in ens.parameters())


def test_stack_cameras_channel_order():
    cams = ("topview", "frontview", "gripperPOV")
    frames = {c: np.full((2, 8, 8, 3), 10 * (i + 1), dtype=np.uint8) for i, c in enumerate(cams)}
    frames["frontview"][..., 1] = 99
    out = stack_cameras(frames)
    assert out.shape == (2, 9, 8, 8) and out.dtype == np.uint8
    assert out[:, 0:3].max() == 10 and out[:, 6:9].min() == 30
    assert (out[:, 4] == 99).all() and (out[:, 3] == 20).all()
    with pytest.raises(ValueError, match="gripperPOV"):
        stack_cameras({c: frames[c] for c in cams[:2]})


def test_random_shift_is_edge_replicating_translation():
    torch.manual_seed(0)
    ramp = torch.arange(12, dtype=torch.uint8)
    x = (ramp[None, :] * 16 + ramp[:, None]).expand(20, 3, 12, 12).contiguous()  # v = 16j + i
    out = random_shift(x, 4)
    assert out.dtype == torch.uint8 and out.shape == x.shape
    i = (out.long() % 16)[:, :, :, 0]  # source row of each output row
    j = (out.long() // 16)[:, :, 0, :]  # source column of each output column
    for k in range(20):
        for src, ref in ((i[k, 0], i[k]), (j[k, 0], j[k])):
            shift = int(src[6]) - 6  # a middle pixel is never clamped
            assert -4 <= shift <= 4 and (ref == src).all()
            assert torch.equal(src, (torch.arange(12) + shift).clamp(0, 11))
    assert len({int(i[k, 0, 6]) for k in range(20)}) > 1  # shifts differ across images


# ------------------------------------------------------------------------------------ config


def test_config_validation_and_presets():
    with pytest.raises(ConfigError, match="state"):
        TDMPC2Config(obs_mode="rgb")
    with pytest.raises(ConfigError, match="valid: smoke, cpu, paper, 1M"):
        TDMPC2Config.preset("huge")
    with pytest.raises(ConfigError, match="multiple"):
        TDMPC2Config(latent_dim=30)
    with pytest.raises(ConfigError, match="TDMPC2Config.lr must be float, got 'fast'"):
        TDMPC2Config(lr="fast")
    with pytest.raises(ConfigError, match="num_elites"):
        TDMPC2Config(num_elites=600)
    with pytest.raises(ConfigError, match="discount_denom must be > 0"):
        TDMPC2Config(discount_denom=0.0)
    with pytest.raises(ConfigError, match="consistency_coef must be >= 0, got -1.0"):
        TDMPC2Config(consistency_coef=-1.0)
    assert TDMPC2Config().discount == pytest.approx(0.98)
    assert TDMPC2Config().type == "tdmpc2"
    paper = TDMPC2Config.preset("paper", obs_mode="pixels")
    assert (paper.latent_dim, paper.mlp_dim, paper.num_q, paper.obs_mode) == (512, 512, 5, "pixels")
    assert TDMPC2Config.preset("19M").latent_dim == TDMPC2_SIZES["19M"]["latent_dim"]
    sizes = [TDMPC2Config.preset(p).batch_size for p in ("smoke", "cpu", "paper", "1M")]
    assert sizes == [16, 64, 256, 256]
    smoke = TDMPC2Config.preset("smoke", horizon=5)
    assert (smoke.seq_len, smoke.horizon, smoke.grad_clip, smoke.train_ratio) == (4, 5, 20.0, 1.0)


# ------------------------------------------------------------------------------------ model


@pytest.mark.parametrize("mode", MODES)
def test_shapes_and_finiteness(mode):
    model, heads = build(mode)
    cfg = model.cfg
    batch = make_batch(cfg)
    z = model.encode(batch.obs)
    assert z.shape == (cfg.seq_len, B, cfg.latent_dim)
    torch.testing.assert_close(z.reshape(-1, 8).sum(-1), torch.ones(z.numel() // 8))  # SimNorm
    z0, a0 = z[0], batch.action[0]
    assert model.next(z0, a0).shape == (B, cfg.latent_dim)
    assert model.reward(z0, a0, heads).shape == (B, cfg.num_bins)
    assert model.termination(z0, heads).shape == (B, 1)
    assert model.Q(z0, a0, heads, "all").shape == (cfg.num_q, B, cfg.num_bins)
    assert model.Q(z0, a0, heads, "min").shape == (B, 1)
    action, info = model.pi(z0, heads)
    assert action.shape == (B, 4) and action.abs().max() <= 1
    out = model.loss(batch, heads)
    assert out.total.dim() == 0 and torch.isfinite(out.total)
    assert set(out.logs) >= {"consistency", "reward", "value", "termination"}
    assert all(np.isfinite(v) for v in out.logs.values())
    assert out.aux["zs"].shape == (cfg.seq_len, B, cfg.latent_dim)
    assert torch.equal(out.aux["mask"][1:], batch.rollout_mask())
    with pytest.raises(ValueError, match="avg"):
        model.Q(z0, a0, heads, "max")


def test_the_policy_samples_and_squashes_in_float32_under_bf16_autocast():
    """Under bfloat16 autocast the policy's Gaussian, tanh and log-prob stay float32: in
    bfloat16 a near-saturated action rounds to exactly +-1, where tanh passes no gradient."""
    model, heads = build("state")
    with torch.no_grad():
        heads.pi[-1].bias[:4] = 4.0  # means near saturation: tanh(4) = 0.99933
    z = model.encode(make_batch(model.cfg).obs)[0].detach()
    torch.manual_seed(0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        action, info = model.pi(z, heads)
    assert action.dtype == info["entropy"].dtype == torch.float32
    assert (action.abs() < 1).all()
    action.sum().backward()
    assert heads.pi[-1].bias.grad[:4].abs().min() > 0


@pytest.mark.parametrize("mode", MODES)
def test_overfit_one_batch(mode):
    model, heads = build(mode, lr=1e-3)
    batch = make_batch(model.cfg)
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    first = update(model, heads, opt, head_opts, batch).total.item()
    losses = [update(model, heads, opt, head_opts, batch).total.item() for _ in range(150)]
    last = float(np.mean(losses[-10:]))  # the TD targets move, so average out the wobble
    assert np.isfinite(last) and last < first / 3, (first, last)


@pytest.mark.parametrize("mode", MODES)
def test_state_dict_round_trip(mode, tmp_path):
    model, heads = build(mode, seed=0)
    batch = make_batch(model.cfg)
    update(model, heads, model.world_model_optimizer(heads), model.head_optimizers(heads), batch)
    torch.save({"model": model.state_dict(), "heads": heads.state_dict()}, tmp_path / "ck.pt")

    other, other_heads = build(mode, seed=1)
    ck = torch.load(tmp_path / "ck.pt")
    other.load_state_dict(ck["model"])
    other_heads.load_state_dict(ck["heads"])
    for m in (model, heads, other, other_heads):
        m.eval()
    with torch.no_grad():
        z, z2 = model.encode(batch.obs), other.encode(batch.obs)
        assert torch.equal(z, z2)
        a = batch.action[0]
        assert torch.equal(model.Q(z[0], a, heads, "all"), other.Q(z2[0], a, other_heads, "all"))
        assert torch.equal(
            model.Q(z[0], a, heads, "all", target=True),
            other.Q(z2[0], a, other_heads, "all", target=True),
        )
        assert torch.equal(model.reward(z[0], a, heads), other.reward(z2[0], a, other_heads))
        torch.manual_seed(3)
        l1 = model.loss(batch, heads).total
        torch.manual_seed(3)
        l2 = other.loss(batch, other_heads).total
        assert torch.equal(l1, l2)
    assert torch.equal(heads.q_scale, other_heads.q_scale)


def test_modules_in_eval_switches_every_submodule_and_restores_each_flag():
    model, heads = build("state", dropout=0.5)
    heads.reward.train(False)  # a mixed tree: the restore must not reset it to the top's flag
    trees = (model.backbone, heads)

    def flags():
        return [m.training for tree in trees for m in tree.modules()]

    before = flags()
    assert any(before) and not all(before)  # (target Qs too are in eval)
    za = torch.ones(8, model.cfg.latent_dim + 4)
    torch.nn.init.normal_(heads.qs.out.weight)  # zero-initialised: it would hide the dropout
    assert not torch.equal(heads.qs(za), heads.qs(za))  # dropout on while training
    with modules_in_eval(*trees):
        assert not any(flags())
        assert torch.equal(heads.qs(za), heads.qs(za))  # dropout off
    assert flags() == before


@pytest.mark.parametrize("mode", MODES)
def test_plan_actions_and_warm_start_state(mode):
    model, heads = build(mode)
    cfg = model.cfg
    batch = make_batch(cfg)
    obs = {k: v[0, :2] for k, v in batch.obs.items()}  # two episodes at once
    assert model.initial_state(heads, 2) is None
    state = None
    for ev in (False, False, True):
        a, state = model.act(obs, heads, state, eval_mode=ev)
        assert a.shape == (2, 4) and np.isfinite(a).all() and np.abs(a).max() <= 1.0
        assert state.shape == (2, cfg.horizon, 4) and state.abs().sum() > 0
    assert "prev_mean" not in dict(heads.named_buffers())  # the plan lives in the state only
    # Training mode is restored after acting.
    assert model.training and heads.training and not heads.target_qs.training
    # Eval actions are deterministic given the RNG state and the acting state; the state is
    # used (a warm start changes the plan) and not modified.
    kept = state.clone()
    runs = []
    for s in (state, state, None):
        torch.manual_seed(5)
        runs.append(model.act(obs, heads, s, eval_mode=True))
    assert np.array_equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert not np.array_equal(runs[0][0], runs[2][0])
    assert torch.equal(state, kept)
    with pytest.raises(ValueError, match="plan means of shape"):
        model.act(obs, heads, torch.zeros(2, cfg.horizon + 1, 4), eval_mode=True)


@pytest.mark.parametrize("mode", MODES)
def test_optimisers_and_head_update(mode):
    model, heads = build(mode)
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs == {"encoder": pytest.approx(model.cfg.lr * 0.3), "dynamics": model.cfg.lr,
                   "heads": model.cfg.lr}  # fmt: skip
    grouped = {id(p) for g in opt.param_groups for p in g["params"]}
    assert set(head_opts) == {"pi"} and head_opts["pi"].defaults["eps"] == 1e-5
    pi_ids = {id(p) for g in head_opts["pi"].param_groups for p in g["params"]}
    assert pi_ids == {id(p) for p in heads.pi.parameters()} and not grouped & pi_ids
    assert {id(p) for p in model.backbone.parameters()} <= grouped
    assert not {id(p) for p in heads.target_qs.parameters()} & grouped

    batch = make_batch(model.cfg)
    out = model.loss(batch, heads)
    before = [p.detach().clone() for p in model.backbone.parameters()]
    q_before = [p.detach().clone() for p in heads.qs.parameters()]
    pi_before = [p.detach().clone() for p in heads.pi.parameters()]
    with torch.no_grad():  # make online and target Qs differ so the Polyak step is visible
        for p in heads.qs.parameters():
            p.add_(0.1)
    logs = model.head_update(batch, heads, out, head_opts)
    assert set(logs) == {"pi_loss", "pi_grad_norm", "pi_entropy", "q_scale"}
    after = list(model.backbone.parameters())
    assert all(torch.equal(x, y) for x, y in zip(before, after, strict=True))
    assert all(
        torch.allclose(p - 0.1, q) for p, q in zip(heads.qs.parameters(), q_before, strict=True)
    )
    assert any(not torch.equal(x, y) for x, y in zip(pi_before, heads.pi.parameters(), strict=True))
    # Targets moved by tau towards the online Qs.
    for t, q in zip(heads.target_qs.parameters(), q_before, strict=True):
        torch.testing.assert_close(t, q + 0.1 * model.cfg.tau)


def test_demo_bc_clones_the_demonstrations_of_the_batch_and_nothing_else():
    """`demo_bc_coef`: the policy loss gains coef x the squared distance of the policy's mean
    to the actions of the batch's demonstration windows (its first `demos`), at rows with a
    real transition only, weighted per step as the Q term; the other windows and rows are
    not cloned. Updates with it alone pull the policy's mean to the demonstrated actions."""
    import dataclasses

    model, heads = build("state", demo_bc_coef=2.0)
    batch = dataclasses.replace(_boundary_batch(model), demos=2)
    out = model.loss(batch, heads)
    zs, mask = out.aux["zs"], out.aux["mask"]
    assert mask[1:, :2].sum() < mask[1:, :2].numel()  # a boundary inside a demo window

    def loss(demo_actions):
        torch.manual_seed(7)  # the same policy noise in both
        return model.pi_loss(zs, mask, heads, demo_actions)

    plain, _ = loss(None)
    cloned, logs = loss(batch.action[:-1, :2])
    with torch.no_grad():
        _, info = model.pi(zs, heads)
    err = (info["mean"][:-1, :2] - batch.action[:-1, :2]).pow(2).sum(-1, keepdim=True)
    rho = model.cfg.rho ** torch.arange(zs.shape[0] - 1, dtype=zs.dtype)
    by_hand = ((err * mask[1:, :2]).sum(dim=(1, 2)) / 2 * rho).sum() / zs.shape[0]
    torch.testing.assert_close(cloned - plain, 2.0 * by_hand)
    torch.testing.assert_close(logs["pi_demo_bc"], (err * mask[1:, :2]).sum((1, 2)).mean() / 2)
    # head_update passes the demonstrations' actions only where the batch has some
    seen = []

    def recording(zs, mask, h, demo_actions=None):
        seen.append(demo_actions)
        return torch.zeros((), requires_grad=True), {}

    model.pi_loss = recording
    head_opts = model.head_optimizers(heads)
    for demos in (2, 0):
        model.head_update(dataclasses.replace(batch, demos=demos), heads, out, head_opts)
    assert torch.equal(seen[0], batch.action[:-1, :2]) and seen[1] is None
    del model.pi_loss

    # cloning alone (Q's pull switched off) moves the mean to a demonstrated action
    model, heads = build("state", demo_bc_coef=1.0, entropy_coef=0.0)
    target = torch.tensor([0.6, -0.4, 0.2, 0.8])
    batch = dataclasses.replace(make_batch(model.cfg), demos=B)
    batch.action[:] = target
    batch.is_first.zero_()
    model.Q = lambda z, a, h, *args, **kw: torch.zeros(*a.shape[:-1], 1)
    opt = model.head_optimizers(heads)
    zs = model.loss(batch, heads).aux["zs"].detach()
    for _ in range(300):
        model.head_update(batch, heads, model.loss(batch, heads), opt)
    with torch.no_grad():
        _, info = model.pi(zs, heads)
    assert (info["mean"][:-1] - target).abs().max() < 0.05


def _boundary_batch(model) -> Batch:
    """Windows of 4 rows whose episode ends at row 1: transitions 1 and 2 are not real."""
    cfg = model.cfg
    batch = make_batch(cfg, batch=8)
    batch.is_first.zero_()
    batch.is_first[2] = 1.0  # row 2 starts another episode
    batch.terminated.zero_()
    batch.terminated[0, :4] = 1.0  # half of the windows end on a success
    batch.action[1] = 0.0  # the filler transition of the episode's last row
    batch.reward[1] = 0.0
    return batch


def _junk_after_boundary(batch: Batch) -> Batch:
    """Everything from row 2 on (the next episode) replaced."""
    other = batch.select(torch.arange(batch.size))
    other.obs = {k: v.clone() for k, v in other.obs.items()}
    for v in other.obs.values():
        v[2:] = (v[2:] + 3) if v.dtype.is_floating_point else (255 - v[2:])
    other.action = other.action.clone()
    other.action[2:] = -other.action[2:] + 0.3
    other.reward = other.reward.clone()
    other.reward[2:] = -0.9
    other.terminated = other.terminated.clone()
    other.terminated[2] = 1.0
    return other


@pytest.mark.parametrize("mode", MODES)
def test_losses_ignore_rows_after_an_episode_boundary(mode):
    model, heads = build(mode)
    with torch.no_grad():  # non-zero values so that bootstraps and rewards matter
        for m in (heads.qs, heads.target_qs, heads.reward):
            for p in m.parameters():
                p.normal_(0, 0.1)
    batch = _boundary_batch(model)
    junk = _junk_after_boundary(batch)

    def losses(b):
        torch.manual_seed(1)
        out = model.loss(b, heads)
        backbone = model.backbone_loss(b).item()
        head_logs = model.head_update(b, heads, out, model.head_optimizers(heads))
        return out.logs, backbone, head_logs

    before = {k: v.clone() for k, v in heads.state_dict().items()}
    a = losses(batch)
    heads.load_state_dict(before)
    b = losses(junk)
    assert a[0] == b[0] and a[1] == b[1]
    assert a[2]["pi_loss"] == b[2]["pi_loss"]
    # The check can fail: without the boundary mark the junk changes every loss.
    heads.load_state_dict(before)
    unmarked, unmarked_junk = _boundary_batch(model), _junk_after_boundary(batch)
    unmarked.is_first.zero_()
    unmarked_junk.is_first.zero_()
    c, d = losses(unmarked), losses(unmarked_junk)
    assert all(c[0][k] != d[0][k] for k in ("consistency", "value", "termination")), (c, d)
    assert c[1] != d[1]


def test_td_target_stops_at_termination():
    model, heads = build("state")
    batch = make_batch(model.cfg)
    z = model.encode(batch.obs)[1:]
    reward = batch.reward[:-1]
    ones = torch.ones_like(reward)
    with torch.no_grad():
        for p in heads.target_qs.parameters():  # non-zero values so a bootstrap would show
            p.normal_()
        td = model._td_target(z, reward, ones, heads)
        td_live = model._td_target(z, reward, torch.zeros_like(ones), heads)
    assert torch.equal(td, reward) and not torch.equal(td_live, reward)


@pytest.mark.parametrize("mode", MODES)
def test_acts_in_real_env(mode):
    import ccdata
    from ccfit.obs import model_input, obs_to_arrays

    env = ccdata.make_env("reach-xy", seed=0, image_size=SIZE, render=mode == "pixels")
    obs, _ = env.reset(seed=0)
    model, heads = build(mode)
    state = model.initial_state(heads)
    for _ in range(3):
        x = model_input([obs_to_arrays(obs, mode)], model.device)
        action, state = model.act(x, heads, state, eval_mode=False)
        assert action.shape == (1, 4) and np.abs(action).max() <= 1.0
        obs, reward, *_ = env.step(action[0].astype(np.float32))
        assert -1.0 <= reward <= 0.0
    env.close()


def test_frozen_encoder_round_trip(tmp_path):
    from ccfit.models.encoders import load_frozen_encoder, save_encoder

    source, _ = build("pixels", seed=3)
    save_encoder(source.backbone.encoder, source.cfg, tmp_path / "enc.pt")
    frozen, spec = load_frozen_encoder(tmp_path / "enc.pt")
    assert spec["image_size"] == SIZE and spec["latent_dim"] == source.cfg.latent_dim
    torch.manual_seed(0)
    model = TDMPC2(make_cfg("pixels"), device="cpu", encoder=frozen)
    heads = model.new_heads()
    model.train()
    assert not frozen.training  # no augmentation, ever
    batch = make_batch(model.cfg)
    source.eval()
    with torch.no_grad():
        assert torch.equal(model.encode(batch.obs), source.encode(batch.obs))
    opt = model.world_model_optimizer(heads)
    assert "encoder" not in {g["name"] for g in opt.param_groups}
    before = [p.clone() for p in frozen.parameters()]
    update(model, heads, opt, model.head_optimizers(heads), batch)
    assert all(torch.equal(x, y) for x, y in zip(before, frozen.parameters(), strict=True))
    with pytest.raises(ValueError, match="latent"):
        TDMPC2(make_cfg("pixels", latent_dim=64), device="cpu", encoder=frozen)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read"):
        load_frozen_encoder(tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not found"):
        load_frozen_encoder(tmp_path / "missing.pt")


def test_frozen_encoder_latents_cached_in_replay(tmp_path):
    """With a frozen encoder, replay stores latents; losses equal those from stored frames."""
    from ccfit.models.base import LATENT_KEY
    from ccfit.models.encoders import load_frozen_encoder, save_encoder
    from ccfit.replay import ReplayBuffer

    source, _ = build("pixels", seed=3)
    save_encoder(source.backbone.encoder, source.cfg, tmp_path / "enc.pt")
    frozen, _ = load_frozen_encoder(tmp_path / "enc.pt")
    torch.manual_seed(0)
    model = TDMPC2(make_cfg("pixels"), device="cpu", encoder=frozen)
    heads = model.new_heads()
    frames = ReplayBuffer(1000, seed=5)
    cached = ReplayBuffer(1000, seed=5, obs_transform=model.replay_obs)
    g = torch.Generator().manual_seed(1)
    for steps in (7, 12):
        ep = {
            "obs": {
                "pixels": torch.randint(0, 256, (steps + 1, 9, SIZE, SIZE), generator=g).byte(),
                "proprio": torch.randn(steps + 1, model.cfg.proprio_dim, generator=g),
            },
            "action": torch.rand(steps, 4, generator=g) * 2 - 1,
            "reward": -torch.rand(steps, generator=g),
            "terminated": torch.zeros(steps),
        }
        frames.add_episode(**ep)
        cached.add_episode(**ep)
    a = frames.sample(B, model.cfg.seq_len)
    b = cached.sample(B, model.cfg.seq_len)
    assert set(b.obs) == {LATENT_KEY}
    assert b.obs[LATENT_KEY].shape == (model.cfg.seq_len, B, model.cfg.latent_dim)
    with torch.no_grad():
        torch.testing.assert_close(model.encode(b.obs), model.encode(a.obs))
        torch.manual_seed(2)
        loss_frames = model.loss(a, heads).total
        torch.manual_seed(2)
        loss_cached = model.loss(b, heads).total
    torch.testing.assert_close(loss_cached, loss_frames)
    # A trainable encoder stores frames and refuses latents.
    plain, _ = build("pixels")
    assert plain.replay_obs(a.obs) is a.obs
    with pytest.raises(ValueError, match="frozen encoder"):
        plain.encode(b.obs)
