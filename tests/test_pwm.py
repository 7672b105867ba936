"""PWM (mixture-of-experts TD-MPC2) and the progressive-experts continual method, smoke size."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from ccfit.config_base import ConfigError
from ccfit.continual import TaskData, make_method, method_config
from ccfit.models.base import Batch
from ccfit.models.pwm import PWM, PWMConfig, PWMHeads, gram_schmidt
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
from ccfit.replay import ReplayBuffer

try:
    from replay_data import random_buffer
except ImportError:  # tests/ imported as a package
    from tests.replay_data import random_buffer

SIZE = 32  # pixel side for tests
B = 8
K = 3


def new_method(name: str, num_tasks: int, **options):
    return make_method(method_config(name, **options), num_tasks)


def make_cfg(mode: str = "state", **kw) -> PWMConfig:
    kw = {"max_tasks": 4, **kw}
    return PWMConfig.preset("smoke", obs_mode=mode, image_size=SIZE, **kw)


def build(mode: str = "state", seed: int = 0, **kw) -> PWM:
    torch.manual_seed(seed)
    return PWM(make_cfg(mode, **kw), device="cpu")


def make_batch(cfg: PWMConfig, seed: int = 0, task: int = 0, batch: int = B) -> Batch:
    """Windows of cfg.seq_len rows of task `task` from a real buffer of random episodes."""
    return random_buffer(cfg, seed=seed, task=task).sample(batch, cfg.seq_len)


def make_buffer(task: int, episodes: int = 3, steps: int = 20) -> ReplayBuffer:
    """A real replay buffer of random state episodes of task `task` (task-dependent offset)."""
    rng = np.random.default_rng(10 + task)
    buf = ReplayBuffer(1000, seed=task)
    for _ in range(episodes):
        buf.add_episode(
            {"state": (rng.normal(size=(steps + 1, 39)) + task).astype(np.float32)},
            rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
            -rng.uniform(0, 1, steps).astype(np.float32),
            np.zeros(steps, np.float32),
            task=task,
        )
    return buf


def update(model, heads, opt, head_opts, batch, method=None, set_to_none=True):
    out = model.loss(batch, heads)
    total = out.total
    if method is not None:
        total = total + method.penalty(model.backbone, model.backbone_loss)
    opt.zero_grad(set_to_none=set_to_none)
    total.backward()
    nn.utils.clip_grad_norm_([p for g in opt.param_groups for p in g["params"]], 20.0)
    opt.step()
    if method is not None:
        method.after_step(model.backbone)
    model.head_update(batch, heads, out, head_opts)
    return out


def optimisers(model: PWM, heads: PWMHeads):
    return model.world_model_optimizer(heads), model.head_optimizers(heads)


def snapshot(module: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.named_parameters()}


def latent_and_action(model: PWM, n: int = 5, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    z = model.encode({"state": torch.randn(n, 39, generator=g)})
    return z, torch.rand(n, 4, generator=g) * 2 - 1


def randomise_router(model: PWM, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        w = model.dynamics.router.weight
        w.copy_(torch.randn(w.shape, generator=g))


# ------------------------------------------------------------------------------ config


def test_config_validation_and_presets():
    cfg = PWMConfig.preset("smoke")
    assert isinstance(cfg, PWMConfig) and cfg.experts_per_task == 3 and cfg.router == "task"
    assert (cfg.latent_dim, cfg.tau_init, cfg.tau_hold_min) == (32, 1.8, 100)
    paper = PWMConfig.preset("paper", obs_mode="pixels")
    assert (paper.latent_dim, paper.mlp_dim, paper.tau_hold_min) == (512, 512, 5000)
    assert paper.hold_steps() == 5000 and paper.hold_steps(1_000_000) == 50_000
    for bad, match in [
        ({"router": "token"}, "router must be one of"),
        ({"experts_per_task": 0}, "experts_per_task"),
        ({"tau_min": 1.9}, "tau_min <= tau_init"),
        ({"tau_hold_frac": 1.5}, "tau_hold_frac"),
        ({"task_steps": 0}, "task_steps"),
    ]:
        with pytest.raises(ValueError, match=match):
            PWMConfig.preset("smoke", **bad)
    with pytest.raises(ConfigError, match="valid: smoke, cpu, paper"):
        PWMConfig.preset("huge")
    assert cfg.type == "pwm" and (cfg.batch_size, cfg.seq_len, cfg.horizon) == (16, 4, 3)
    assert PWMConfig.preset("19M").latent_dim == 768
    assert PWMConfig.preset("cpu").tau_hold_min == 1000
    assert PWMConfig.preset("cpu").mlp_dim == TDMPC2Config.preset("cpu").mlp_dim
    with pytest.raises(ValueError, match="PWMConfig"):
        PWM(TDMPC2Config(), device="cpu")
    with pytest.raises(ValueError, match="TDMPC2Config"):
        TDMPC2(object(), device="cpu")


# ------------------------------------------------------------------------------ model


@pytest.mark.parametrize("mode", ["state", "pixels"])
def test_shapes_and_finiteness(mode):
    model = build(mode)
    heads = model.new_heads()
    cfg = model.cfg
    batch = make_batch(cfg)
    out = model.loss(batch, heads)
    assert out.total.ndim == 0 and torch.isfinite(out.total)
    assert out.logs["routing_entropy"] == pytest.approx(math.log(K), abs=0.01)  # near uniform
    out.total.backward()
    grads = [p.grad for p in model.dynamics.experts[0].parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    z = model.encode({k: v[0] for k, v in batch.obs.items()})
    nxt = model.next(z, batch.action[0])
    assert nxt.shape == (B, cfg.latent_dim)
    groups = nxt.view(B, -1, cfg.simnorm_dim).sum(-1)  # SimNorm output
    assert torch.allclose(groups, torch.ones_like(groups), atol=1e-5)
    w = model.routing_weights(z, batch.action[0], 0)
    assert w.shape == (B, K * cfg.max_tasks)
    obs = {k: v[0, :1] for k, v in batch.obs.items()}
    a, state = model.act(obs, heads, None, eval_mode=True)
    assert state.shape == (1, cfg.horizon, 4)
    assert a.shape == (1, 4) and np.all(np.abs(a) <= 1) and np.isfinite(a).all()


def test_overfit_one_batch():
    model = build(lr=1e-3)
    heads = model.new_heads()
    batch = make_batch(model.cfg)
    opt, popt = optimisers(model, heads)
    first = update(model, heads, opt, popt, batch).total.item()
    losses = [update(model, heads, opt, popt, batch).total.item() for _ in range(120)]
    last = float(np.mean(losses[-10:]))
    assert np.isfinite(last) and last < first / 3, (first, last)


def test_gram_schmidt_orthonormalises_in_order():
    x = torch.randn(4, 5, 16)
    q = gram_schmidt(x)
    gram = q @ q.transpose(-1, -2)
    assert torch.allclose(gram, torch.eye(5).expand(4, 5, 5), atol=1e-5)
    assert torch.equal(gram_schmidt(x[:, :3]), q[:, :3])  # earlier vectors ignore later ones

    model = build(orthogonalize=True)
    model.dynamics.add_group()
    z, a = latent_and_action(model)
    feats = model.dynamics.features(torch.cat([z, a], -1))
    assert feats.shape == (5, 2 * K, model.cfg.mlp_dim)
    gram = feats @ feats.transpose(-1, -2)
    assert torch.allclose(gram, torch.eye(2 * K).expand(5, -1, -1), atol=1e-5)
    plain = build(orthogonalize=False)
    plain.dynamics.add_group()
    raw = plain.dynamics.features(torch.cat([z, a], -1))
    off = (raw @ raw.transpose(-1, -2)) * (1 - torch.eye(2 * K))
    assert off.abs().max() > 1.0  # without the flag the features are far from orthogonal


def test_state_dict_round_trip(tmp_path):
    model = build(seed=0)
    method = new_method("experts", num_tasks=3)
    for task in range(2):
        model.begin_task(task)
        method.before_task(task, model.backbone)
    heads = model.new_heads()
    randomise_router(model)
    model.dynamics.tau[1] = 0.9
    batch = make_batch(model.cfg, task=1)
    update(model, heads, *optimisers(model, heads), batch, method)
    torch.save({"model": model.state_dict(), "heads": heads.state_dict()}, tmp_path / "ck.pt")

    other = build(seed=1)
    other_heads = other.new_heads()
    ck = torch.load(tmp_path / "ck.pt")
    other.load_state_dict(ck["model"])
    other_heads.load_state_dict(ck["heads"])
    dyn, odyn = model.dynamics, other.dynamics
    assert (odyn.num_active, int(odyn.num_frozen), int(other_heads.task_index)) == (2 * K, 1, 1)
    assert torch.equal(odyn.tau, dyn.tau) and torch.equal(odyn.tau_updates, dyn.tau_updates)
    flags = [p.requires_grad for p in odyn.experts.parameters()]
    assert flags == [p.requires_grad for p in dyn.experts.parameters()]
    assert not any(p.requires_grad for p in odyn.experts[0].parameters())  # frozen group 0
    assert all(p.requires_grad for p in odyn.experts[K].parameters())
    model.eval()
    other.eval()
    with torch.no_grad():
        torch.manual_seed(3)
        l1 = model.loss(batch, heads).total
        torch.manual_seed(3)
        l2 = other.loss(batch, other_heads).total
    assert torch.equal(l1, l2)
    z, a = latent_and_action(model)
    assert torch.equal(model.routing_weights(z, a, 1), other.routing_weights(z, a, 1))


def test_heads_route_planning_and_must_match_the_batch():
    model = build()
    model.dynamics.add_group()
    randomise_router(model)
    model.begin_task(1)
    heads = model.new_heads()
    assert isinstance(heads, PWMHeads) and int(heads.task_index) == 1
    seen = []
    forward = model.dynamics.forward
    model.dynamics.forward = lambda z, a, task=None: seen.append(task) or forward(z, a, task)
    obs = {"state": torch.randn(1, 39)}
    model.act(obs, heads, None, eval_mode=True)
    assert seen and all(int(t) == 1 for t in seen)
    with pytest.raises(ValueError, match="heads trained on a batch of another task"):
        model.loss(make_batch(model.cfg, task=0), heads)
    # A window routes with the task of its row 0: rows of a task-0 episode that follow a
    # boundary (masked out of the losses) neither raise nor change the routing.
    batch = make_batch(model.cfg, task=1)
    batch.is_first[2:] = 1.0
    batch.task[2:] = 0
    seen.clear()
    model.loss(batch, heads)
    model.backbone_loss(batch)
    assert seen and all(torch.equal(t, torch.ones(B, dtype=torch.long)) for t in seen)
    with pytest.raises(ValueError, match="outside 0..3"):
        model.begin_task(4)
    with pytest.raises(TypeError, match="PWMHeads"):
        model.loss(make_batch(model.cfg, task=1), TDMPC2(model.cfg, device="cpu").new_heads())


def test_state_router_depends_on_the_latent():
    model = build(router="state")
    randomise_router(model)
    z, a = latent_and_action(model)
    w = model.routing_weights(z, a, 0)
    assert not torch.allclose(w[0], w[1])  # per-sample routing
    assert model.dynamics.router.in_features == model.cfg.latent_dim + 4 + 1
    task_model = build()
    randomise_router(task_model)
    w = task_model.routing_weights(z, a, 0)
    assert torch.equal(w[0], w[1])  # task routing ignores the state


# ------------------------------------------------------------------------------ routing


def test_expert_growth_and_masking():
    model = build()
    method = new_method("experts", num_tasks=4)
    z, a = latent_and_action(model)
    dyn = model.dynamics
    for task in range(3):
        method.before_task(task, model.backbone)
        assert dyn.num_active == K * (task + 1)
        randomise_router(model, seed=task)
        w = model.routing_weights(z, a, task)
        assert torch.all(w[:, : dyn.num_active] > 0)
        assert torch.all(w[:, dyn.num_active :] == 0)  # inactive experts: exactly 0
        assert torch.allclose(w.sum(-1), torch.ones(5))
        for e, expert in enumerate(dyn.experts):
            trainable = task * K <= e < (task + 1) * K
            assert all(p.requires_grad == trainable for p in expert.parameters()), (task, e)
    per_expert = sum(p.numel() for p in dyn.experts[0].parameters())
    shared = sum(p.numel() for p in [*dyn.router.parameters(), *dyn.head.parameters()])
    enc = sum(p.numel() for p in model.backbone.encoder.parameters())
    assert model.num_parameters()["backbone"] == enc + shared + K * per_expert
    with pytest.raises(RuntimeError, match="expected task 3"):
        method.before_task(4, model.backbone)


def test_routing_overrides():
    model = build()
    dyn = model.dynamics
    z, a = latent_and_action(model)
    with pytest.raises(ValueError, match="only one expert group"):
        with model.routing_override("prior"):
            pass
    for _ in range(2):
        dyn.add_group()
    randomise_router(model)
    n = dyn.num_active
    learnt = model.routing_weights(z, a, 2)[:, :n]
    prior, new = learnt[:, : n - K], learnt[:, n - K :]
    with model.routing_override("prior"):
        w = model.routing_weights(z, a, 2)
    assert torch.all(w[:, n - K :] == 0)
    assert torch.allclose(w[:, : n - K], prior / prior.sum(-1, keepdim=True), atol=1e-6)
    with model.routing_override("new"), model.routing_task(2):
        w = model.routing_weights(z, a, 2)
        out_new = model.next(z, a)
    assert torch.all(w[:, : n - K] == 0)
    assert torch.allclose(w[:, n - K : n], new / new.sum(-1, keepdim=True), atol=1e-6)
    with model.routing_override("uniform"):
        w = model.routing_weights(z, a, 2)
    assert torch.all(w[:, :n] == 1.0 / n) and torch.all(w[:, n:] == 0)
    with model.routing_override(None):
        assert torch.equal(model.routing_weights(z, a, 2)[:, :n], learnt)
    # The ablation reaches the dynamics: 'new' mixes only the newest experts' features.
    feats = dyn.features(torch.cat([z, a], -1))
    w_new = (new / new.sum(-1, keepdim=True)).unsqueeze(-1)
    expected = dyn.head((w_new * feats[:, n - K :]).sum(-2))
    assert torch.allclose(out_new.detach(), expected.detach(), atol=1e-6)
    with pytest.raises(ValueError, match="valid:"):
        with model.routing_override("old"):
            pass


def _schedule(cfg: PWMConfig, tau: float, count: int, hold: int, entropy: float, steps: int):
    """The authors' schedule by hand: `steps` training forwards of the dynamics at `entropy`,
    held while fewer than `hold` forwards have run, clipped. Returns (tau, count)."""
    target = cfg.tau_target_frac * math.log(K)
    for _ in range(steps):
        if count >= hold:
            tau = min(max(tau + cfg.tau_rate * math.tanh(target - entropy), cfg.tau_min),
                      cfg.tau_max)  # fmt: skip
        count += 1
    return tau, count


def test_temperature_schedule():
    """The temperature steps once per training forward of the dynamics (seq_len - 1 per update),
    the hold counted in those forwards, as the authors' router does."""
    hold = 5  # forwards: the second update (3 forwards each at seq_len 4) crosses it
    model = build(tau_hold_min=hold, tau_hold_frac=0.0, tau_rate=0.05)
    heads = model.new_heads()
    cfg = model.cfg
    forwards = cfg.seq_len - 1
    assert forwards >= 2
    opt, popt = optimisers(model, heads)
    expected, count = cfg.tau_init, 0
    for i in range(8):
        out = update(model, heads, opt, popt, make_batch(cfg, seed=i))
        # With the 'task' router the weights depend on the task and tau alone: every forward of
        # the update sees the same entropy.
        entropies = out.aux["routing_entropies"]
        assert entropies.shape == (forwards,) and torch.allclose(entropies, entropies[0])
        expected, count = _schedule(cfg, expected, count, hold, float(entropies[0]), forwards)
        assert model.tau == pytest.approx(expected, abs=1e-6), i
        if count <= hold:
            assert model.tau == pytest.approx(cfg.tau_init)
    assert int(model.dynamics.tau_updates[0]) == 8 * forwards
    assert model.tau < cfg.tau_init  # near-uniform routing: entropy above target, tau falls
    assert torch.all(model.dynamics.tau[1:] == cfg.tau_init)  # other tasks keep theirs
    # No update outside training updates.
    before = model.dynamics.tau.clone()
    with torch.no_grad():
        model.loss(make_batch(cfg), heads)
    model.backbone_loss(make_batch(cfg))
    assert torch.equal(model.dynamics.tau, before)
    # Clipping at tau_min, and the hold from the task's steps.
    fast = build(tau_hold_min=0, tau_rate=10.0)
    fast_heads = fast.new_heads()
    update(fast, fast_heads, *optimisers(fast, fast_heads), make_batch(cfg))
    assert fast.tau == fast.cfg.tau_min
    fast.begin_task(1, task_steps=400_000)
    assert int(fast.dynamics.tau_hold[1]) == 20_000 and int(fast.dynamics.tau_hold[0]) == 0


def test_an_offline_update_steps_the_temperature_as_an_online_one():
    """Offline (`ccfit fit`, no heads) the temperature steps in `after_backbone_update`, with the
    schedule and entropy feedback of online training: once per forward of the update's rollout,
    held, then tau += rate * tanh(H* - H). Before the hook existed an offline PWM never left
    tau_init."""
    hold = 4
    model = build(tau_hold_min=hold, tau_hold_frac=0.0, tau_rate=0.05)
    cfg, expected, count = model.cfg, model.cfg.tau_init, 0
    forwards = cfg.seq_len - 1
    model.begin_task(0, task_steps=10)
    for i in range(6):
        batch = make_batch(cfg, seed=i)
        z = model.encode({k: v[0] for k, v in batch.obs.items()})
        entropy = float(torch.special.entr(model.routing_weights(z, batch.action[0], 0)).sum(-1)
                        .mean())  # fmt: skip
        model.after_backbone_update(batch)
        expected, count = _schedule(cfg, expected, count, hold, entropy, forwards)
        assert model.tau == pytest.approx(expected, abs=1e-6), i
    assert int(model.dynamics.tau_updates[0]) == 6 * forwards and model.tau < cfg.tau_init
    assert torch.all(model.dynamics.tau[1:] == cfg.tau_init)


def test_a_task_routes_only_over_its_own_and_earlier_groups():
    """Task t's softmax spans the groups 0..t: adding a group (fresh experts, router rows near
    0) leaves a finished task's weights and next latent exactly as they were. Before the scope,
    a new group took a large share of task 0's routing at once."""
    model = build()
    method = new_method("experts", num_tasks=3)
    dyn = model.dynamics
    z, a = latent_and_action(model)
    method.before_task(0, model.backbone)
    randomise_router(model)
    weights0 = model.routing_weights(z, a, 0)
    with model.routing_task(0):
        next0 = model.next(z, a).detach()
    for task in (1, 2):
        method.before_task(task, model.backbone)
        assert torch.equal(model.routing_weights(z, a, 0), weights0)
        with model.routing_task(0):
            assert torch.equal(model.next(z, a).detach(), next0)
    for task in range(3):  # task t: weight on groups 0..t, exactly 0 beyond
        w = model.routing_weights(z, a, task)
        assert torch.all(w[:, : (task + 1) * K] > 0) and torch.all(w[:, (task + 1) * K :] == 0)
    # routing_scope='all' (the toolkit before the scope): a new group takes task 0's weight.
    wide = build(routing_scope="all")
    wide_method = new_method("experts", num_tasks=2)
    wide_method.before_task(0, wide.backbone)
    randomise_router(wide)
    before = wide.routing_weights(z, a, 0)
    wide_method.before_task(1, wide.backbone)
    after = wide.routing_weights(z, a, 0)
    assert torch.all(after[:, K : 2 * K] > 0) and not torch.allclose(after[:, :K], before[:, :K])
    with pytest.raises(ConfigError, match="routing_scope"):
        make_cfg(routing_scope="every")
    # The temperature's entropy target counts the experts the task routes over.
    assert dyn.target_entropy(0) == pytest.approx(0.75 * math.log(K))
    assert dyn.target_entropy(2) == pytest.approx(0.75 * math.log(3 * K))
    assert wide.dynamics.target_entropy(0) == pytest.approx(0.75 * math.log(2 * K))
    with pytest.raises(ValueError, match="not active"), wide.routing_override("new"):
        wide.routing_weights(z, a, 3)  # group 3 was never added
    # A batch mixing tasks (replay) routes each row in its own task's scope.
    mixed = model.routing_weights(z[:2], a[:2], torch.tensor([0, 2]))
    assert torch.all(mixed[0, K:] == 0) and torch.all(mixed[1, : dyn.num_active] > 0)


# ------------------------------------------------------------------------------ continual


def _task_data(model: PWM, buf: ReplayBuffer, task: int) -> TaskData:
    return TaskData.from_buffer(task, buf, batch_size=B, seq_len=model.cfg.seq_len,
                                backbone_loss=model.backbone_loss)  # fmt: skip


@pytest.mark.parametrize("freeze_shared,keep_optimizer",
                         [(True, False), (True, True), (False, False)])  # fmt: skip
def test_progressive_experts_freeze_prior_experts_exactly(freeze_shared, keep_optimizer):
    """Earlier experts stay exactly as they were through task 1's updates (stale gradients and
    Adam state included); with `freeze_shared` so do the output head, the router's tau column
    and task 0's router column, and then task 0's dynamics is exactly what it was after task
    0, also when task 1 starts from task 0's Adam state (`keep_backbone_optimizer`)."""
    from ccfit.train.update import backbone_optimizer_state, load_backbone_optimizer_state

    model = build()
    method = new_method("experts", num_tasks=2, freeze_shared=freeze_shared)
    dyn = model.dynamics
    z, a = latent_and_action(model)
    buffers = [make_buffer(0), make_buffer(1)]
    moved_before_restore, carried = False, {}
    for task in range(2):
        model.begin_task(task)
        method.before_task(task, model.backbone)
        heads = model.new_heads()
        opt, popt = optimisers(model, heads)
        if task == 1 and keep_optimizer:
            load_backbone_optimizer_state(opt, model.backbone, carried)
        if task == 1:
            prior = snapshot(dyn.experts[:K])
            router, head = snapshot(dyn.router), snapshot(dyn.head)
            with model.routing_task(0):
                next0 = model.next(z, a).detach()
            new = snapshot(dyn.experts[K : 2 * K])
            # Stale gradients + Adam state on the frozen experts: Adam would move them.
            for p in dyn.experts[:K].parameters():
                p.grad = torch.zeros_like(p)
            opt.add_param_group({"params": list(dyn.experts[:K].parameters())})
        for step in range(4):
            batch = buffers[task].sample(B, model.cfg.seq_len)
            out = model.loss(batch, heads)
            opt.zero_grad(set_to_none=False)
            out.total.backward()
            if task == 1 and step == 0:  # momentum from a fake earlier step
                for p in dyn.experts[:K].parameters():
                    opt.state[p] = {"step": torch.tensor(1.0), "exp_avg": torch.ones_like(p),
                                    "exp_avg_sq": torch.ones_like(p)}  # fmt: skip
            opt.step()
            if task == 1:
                moved_before_restore |= any(
                    not torch.equal(v, prior[k]) for k, v in dyn.experts[:K].named_parameters()
                )
            method.after_step(model.backbone)
            model.head_update(batch, heads, out, popt)
        method.after_task(task, model.backbone, _task_data(model, buffers[task], task))
        carried = backbone_optimizer_state(opt, model.backbone)
    assert moved_before_restore  # the restore is what keeps them fixed
    assert all(torch.equal(v, prior[k]) for k, v in dyn.experts[:K].named_parameters())
    assert not any(torch.equal(v, new[k]) for k, v in dyn.experts[K : 2 * K].named_parameters())
    weight = dyn.router.weight
    assert not torch.equal(weight[:, 1], router["weight"][:, 1])  # task 1's column trains
    assert torch.equal(weight[:, 0], router["weight"][:, 0])  # task 0's gets no gradient
    tau_column = torch.equal(weight[:, -1], router["weight"][:, -1])
    same_head = all(torch.equal(v, head[k]) for k, v in dyn.head.named_parameters())
    with model.routing_task(0):
        same_next0 = torch.equal(model.next(z, a).detach(), next0)
    assert tau_column == same_head == same_next0 == freeze_shared
    state = method.state_dict()
    fresh = new_method("experts", num_tasks=2, freeze_shared=freeze_shared)
    fresh.load_state_dict(state)
    assert fresh.task == 1 and set(fresh.stored) == set(method.stored)


def test_experts_needs_a_pwm_model():
    torch.manual_seed(0)
    tdmpc2 = TDMPC2(TDMPC2Config.preset("smoke"), device="cpu")
    method = new_method("experts", num_tasks=2)
    with pytest.raises(ValueError, match="method 'experts' needs a backbone with expert groups"):
        method.before_task(0, tdmpc2.backbone)


@pytest.mark.parametrize("name", ["er", "ewc", "packnet"])
def test_pwm_under_monolithic_methods(name):
    model = build()
    kwargs = {"er": {"fraction": 0.25, "batch_size": 4}, "ewc": {"fisher_batches": 2},
              "packnet": {"retrain_steps": 2}}[name]  # fmt: skip
    method_ = new_method(name, num_tasks=2, **kwargs)
    backbone = model.backbone
    buffers = [make_buffer(0), make_buffer(1)]
    penalties, task0 = [], None
    for task in range(2):
        model.begin_task(task)
        method_.before_task(task, backbone)
        heads = model.new_heads()
        opt, popt = optimisers(model, heads)

        def step(task=task, heads=heads, opt=opt, popt=popt):
            batch = buffers[task].sample(B, model.cfg.seq_len)
            out = update(model, heads, opt, popt, batch, method_)
            penalties.append(float(method_.penalty(backbone, model.backbone_loss).detach()))
            return out

        for _ in range(3):
            assert torch.isfinite(step().total)
        method_.after_task(task, backbone, _task_data(model, buffers[task], task))
        for _ in range(method_.wants_retrain_steps):
            step()
        if task == 0:
            task0 = snapshot(backbone)
    assert model.dynamics.num_active == K  # no growth outside the 'experts' method
    assert all(math.isfinite(p) for p in penalties)
    if name in ("er", "ewc"):
        assert all(p > 0 for p in penalties[-3:])
    else:
        with method_.evaluating(0, backbone):
            assert all(torch.equal(v, task0[k]) for k, v in backbone.named_parameters())
        linears = [m for m in backbone.modules() if isinstance(m, nn.Linear)]
        active = [m for m in linears if m.weight.requires_grad]
        assert len(method_.owner) == len(active) < len(linears)  # inactive experts skipped


def test_packnet_with_experts_activated_later():
    """Parameters that become trainable after task 0 (a manually grown mixture) are picked up
    by PackNet: they train in task 1 while task 0's weights stay exact."""
    model = build()
    method = new_method("packnet", num_tasks=2, retrain_steps=1)
    backbone = model.backbone
    buffers = [make_buffer(0), make_buffer(1)]
    task0 = None
    for task in range(2):
        model.begin_task(task)
        if task == 1:
            model.dynamics.add_group()
            new = snapshot(model.dynamics.experts[K : 2 * K])
        method.before_task(task, backbone)
        heads = model.new_heads()
        opt, popt = optimisers(model, heads)
        for _ in range(3 if task == 0 else 2):
            update(model, heads, opt, popt, buffers[task].sample(B, model.cfg.seq_len), method)
        if task == 0:
            method.after_task(task, backbone, _task_data(model, buffers[task], task))
            for _ in range(method.wants_retrain_steps):
                update(model, heads, opt, popt, buffers[task].sample(B, model.cfg.seq_len), method)
            task0 = {k: v.detach().clone() for k, v in backbone.named_parameters()
                     if v.requires_grad}  # fmt: skip
    experts = model.dynamics.experts[K : 2 * K]
    assert not any(torch.equal(v, new[k]) for k, v in experts.named_parameters())
    for k, v in backbone.named_parameters():
        if k in task0:  # what task 0 trained: its kept weights and every shared parameter
            owner = method.owner.get(k)
            fixed = torch.ones_like(v, dtype=torch.bool) if owner is None else owner == 0
            assert torch.equal(v[fixed], task0[k][fixed]), k


def _three_updates():
    model = build(seed=7, orthogonalize=True)
    heads = model.new_heads()
    opt, popt = optimisers(model, heads)
    for i in range(3):
        update(model, heads, opt, popt, make_batch(model.cfg, seed=i))
    return [p.detach().clone() for p in [*model.parameters(), *heads.parameters()]]


def test_same_seed_same_updates():
    a, b = _three_updates(), _three_updates()
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
