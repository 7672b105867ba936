"""Continual methods on a small real backbone trained with a real Adam loop (and on TD-MPC2)."""

import copy
import dataclasses
import math

import numpy as np
import pytest
import torch
from torch import nn

from ccfit.config_base import ConfigError
from ccfit.continual import METHODS, TaskData, make_method, method_config, method_names
from ccfit.continual import register_method as register
from ccfit.continual.base import ContinualMethod, MethodConfig
from ccfit.continual.er import reservoir_indices
from ccfit.continual.packnet import FREE, Phase
from ccfit.models.base import Batch
from ccfit.replay import ReplayBuffer

try:
    from shipped import shipped_methods
except ImportError:  # tests/ imported as a package
    from tests.shipped import shipped_methods

STATE, ACT = 6, 2


def method(name: str, num_tasks: int = 3, seed: int = 0, **options) -> ContinualMethod:
    return make_method(method_config(name, **options), num_tasks, seed)


class TinyBackbone(nn.Module):
    """Encoder (Linear + LayerNorm + Mish) and a linear latent dynamics."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = nn.Sequential(nn.Linear(STATE, 16), nn.LayerNorm(16), nn.Mish())
        self.dynamics = nn.Linear(16 + ACT, 16)

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        """One-step prediction from row 0, only where transition 0 is real."""
        s = batch.obs["state"]
        z = self.encoder(s[0])
        pred = self.dynamics(torch.cat([z, batch.action[0]], -1))
        err = (pred - self.encoder(s[1]).detach()).pow(2).mean(-1, keepdim=True)
        return (err * batch.valid()[0]).mean() + z.pow(2).mean()


def task_buffer(task: int, lengths: list[int]) -> ReplayBuffer:
    """Episodes of the given lengths (transitions) with a task-specific state offset; obs['id']
    is each row's number in the buffer (0, 1, ...), so kept windows can be traced back."""
    g = torch.Generator().manual_seed(100 + task)
    buffer = ReplayBuffer(capacity=None, seed=100 + task)
    row = 0
    for steps in lengths:
        obs = {
            "state": torch.randn(steps + 1, STATE, generator=g) + 2.0 * task,
            "id": torch.arange(row, row + steps + 1, dtype=torch.float32).view(-1, 1),
        }
        buffer.add_episode(obs, torch.randn(steps, ACT, generator=g), -torch.ones(steps) / 2,
                           torch.zeros(steps), task=task)  # fmt: skip
        row += steps + 1
    return buffer


def make_task_data(backbone: TinyBackbone, task: int, n: int, batch_size: int = 32,
                   seq_len: int = 2) -> TaskData:  # fmt: skip
    """A task whose replay holds n one-transition episodes (n real transitions)."""
    return TaskData.from_buffer(
        task,
        task_buffer(task, [1] * n),
        batch_size=batch_size,
        seq_len=seq_len,
        backbone_loss=backbone.backbone_loss,
    )


def train(backbone, method, opt, data: TaskData, steps: int) -> None:
    for _ in range(steps):
        loss = data.backbone_loss(data.sample()) + method.penalty(backbone, data.backbone_loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
        method.after_step(backbone)


def snapshot(module: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.named_parameters()}


# ----------------------------------------------------------------------------- registry


def test_registry_names_and_errors():
    builtin = ["er", "ewc", "experts", "ft", "packnet"]
    assert set(builtin) <= set(method_names())  # tests may register more (test_seam.py)
    for name in builtin:
        built = method(name)
        assert isinstance(built, METHODS[name]) and isinstance(built.cfg, MethodConfig)
        assert METHODS[name].name == name == built.cfg.type
    with pytest.raises(ConfigError, match="unknown continual method 'si'.*er, ewc, experts, ft"):
        method_config("si")
    with pytest.raises(ConfigError, match="method 'ewc'.*lamda.*its options: lam, "):
        method_config("ewc", lamda=1.0)
    with pytest.raises(ValueError, match="already registered"):
        register("ft", METHODS["ft"].config_class)(ContinualMethod)
    with pytest.raises(ConfigError, match="at most 127 tasks"):
        method("packnet", num_tasks=128)
    with pytest.raises(ConfigError, match="fraction"):
        method_config("er", fraction=0.0)
    with pytest.raises(ConfigError, match="lam must be >= 0"):
        method_config("ewc", lam=-1.0)


def test_ft_changes_nothing():
    torch.manual_seed(0)
    bb = TinyBackbone()
    ft = method("ft")
    before = snapshot(bb)
    ft.before_task(0, bb)
    assert ft.penalty(bb, bb.backbone_loss).item() == 0.0
    ft.after_step(bb)
    ft.after_task(0, bb, make_task_data(bb, 0, 10))
    with ft.evaluating(0, bb):
        pass
    assert all(torch.equal(before[k], v) for k, v in bb.named_parameters())
    assert ft.wants_retrain_steps == 0 and ft.state_dict() == {}


# ----------------------------------------------------------------------------- ER


def test_reservoir_is_a_uniform_subset():
    rng = np.random.default_rng(0)
    counts = np.zeros(20)
    for _ in range(4000):
        idx = reservoir_indices(20, 5, rng)
        assert len(idx) == 5 and len(set(idx.tolist())) == 5 and np.all(np.diff(idx) > 0)
        counts[idx] += 1
    # Each item is kept with probability 5/20 = 0.25 (binomial sd ~0.007 over 4000 draws).
    np.testing.assert_allclose(counts / 4000, 0.25, atol=0.03)
    assert reservoir_indices(7, 0, rng).size == 0
    np.testing.assert_array_equal(reservoir_indices(7, 7, rng), np.arange(7))


LENGTHS = [250, 37, 1, 120, 250, 9, 200, 250, 64]
"""A task's replay as the loop leaves it: long failures, short successes (1181 transitions)."""


def test_er_keeps_a_fraction_of_transitions_as_windows_of_the_model_length():
    bb = TinyBackbone()
    buffer = task_buffer(0, LENGTHS)
    seq_len = 8
    data = TaskData.from_buffer(0, buffer, batch_size=16, seq_len=seq_len,
                                backbone_loss=bb.backbone_loss)  # fmt: skip
    er = method("er", fraction=0.05, replay_ratio=0.2, batch_size=4000, seed=3)
    assert er.penalty(bb, bb.backbone_loss).item() == 0.0 and er.replay_batch() is None
    er.after_task(0, bb, data)
    n = sum(LENGTHS)
    k = round(0.05 * n / (seq_len - 1))
    assert len(er.kept[0]) == k == er.memory.num_episodes == 8
    assert er.memory.size == k * seq_len  # seq_len / (seq_len - 1) rows per kept transition
    # About 5% of the task's transitions are kept (fewer where a window spans a boundary).
    assert 0.8 * 0.05 * n <= er.memory.num_transitions <= 0.05 * n + seq_len
    # Each replayed window is one kept chunk of the task's replay, rows in order, row 0
    # marked as a start, the task's own episode boundaries inside it kept.
    batch = er.replay_batch()
    assert batch.obs["id"].shape == (seq_len, 4000, 1)
    ids = batch.obs["id"][..., 0].long()
    assert set(ids[0].tolist()) == set(er.kept[0].tolist())
    assert torch.equal(ids, ids[0] + torch.arange(seq_len).unsqueeze(1))
    source_first = buffer.gather(ids[0], seq_len).is_first[..., 0]
    source_first[0] = 1.0
    assert torch.equal(batch.is_first[..., 0], source_first)
    # Uniform over the kept windows (each ~4000 / 8 = 500; binomial sd ~21).
    counts = np.unique(ids[0].numpy(), return_counts=True)[1]
    assert len(counts) == k and np.all(np.abs(counts - 4000 / k) < 110), counts
    with pytest.raises(ValueError, match="seq_len 2 differs from 8"):
        er.after_task(1, bb, make_task_data(bb, 1, 200))


def test_er_gives_a_sequence_model_its_context():
    """Replayed windows of a sequence model (DreamerV3 at seq_len 32) run through consecutive
    transitions of one episode, as its training windows do, instead of a single transition
    after the RSSM's initial state."""
    bb = TinyBackbone()
    buffer = task_buffer(0, [250] * 40)
    data = TaskData.from_buffer(0, buffer, batch_size=16, seq_len=32,
                                backbone_loss=bb.backbone_loss)  # fmt: skip
    er = method("er", batch_size=1024)
    er.after_task(0, bb, data)
    assert len(er.kept[0]) == round(0.05 * 10_000 / 31)
    transitions = er.replay_batch().rollout_mask()[..., 0].sum(0)  # from row 0, per window
    # A window is cut short only where it crosses into the next episode (31 / 251 of them).
    assert transitions.median() == 31 and transitions.mean() > 0.75 * 31


def test_er_replays_only_earlier_tasks_with_its_weight():
    torch.manual_seed(0)
    bb = TinyBackbone()
    er = method("er", fraction=0.05, replay_ratio=0.2, batch_size=64, seed=3)
    data0, data1 = make_task_data(bb, 0, 1000), make_task_data(bb, 1, 620)
    er.after_task(0, bb, data0)
    assert len(er.kept[0]) == 50 and set(er.replay_batch().task.flatten().tolist()) == {0}
    er.after_task(1, bb, data1)
    assert len(er.kept[1]) == 31 and er.memory.num_episodes == 81  # round(0.05 * 620) = 31
    with pytest.raises(ValueError, match="already added"):
        er.after_task(1, bb, data1)
    batch = er.replay_batch()
    for task in (0, 1):
        rows = batch.task[0] == task
        assert rows.any() and (batch.obs["state"][0, rows].mean() - 2.0 * task).abs() < 0.5
    # The penalty is r / (1 - r) = 0.25 times the backbone loss on the next replay sample.
    state = copy.deepcopy(er.state_dict())
    pen = er.penalty(bb, bb.backbone_loss)
    er.load_state_dict(state)
    expected = 0.25 * bb.backbone_loss(er.replay_batch())
    assert pen.item() == pytest.approx(expected.item(), rel=1e-6) and pen.item() > 0
    pen.backward()
    assert bb.dynamics.weight.grad.abs().sum() > 0
    # A fresh method restored from the state continues with the same replay batches.
    er.load_state_dict(state)
    other = method("er", fraction=0.05, replay_ratio=0.2, batch_size=64, seed=99)
    other.load_state_dict(copy.deepcopy(state))
    assert torch.equal(other.replay_batch().obs["id"], er.replay_batch().obs["id"])


def test_er_is_deterministic_per_seed():
    bb = TinyBackbone()
    runs = []
    for seed in (5, 5, 6):
        er = method("er", seed=seed, batch_size=16)
        er.after_task(0, bb, make_task_data(bb, 0, 400))
        runs.append((er.kept[0], er.replay_batch().obs["id"]))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert not torch.equal(runs[0][0], runs[2][0])  # the reservoir differs across seeds
    assert not torch.equal(runs[0][1], runs[2][1])


# ----------------------------------------------------------------------------- EWC


def test_ewc_fisher_anchor_and_quadratic_growth():
    torch.manual_seed(0)
    bb = TinyBackbone()
    ewc = method("ewc", lam=10.0, fisher_batches=4)
    assert ewc.penalty(bb, bb.backbone_loss).item() == 0.0
    data = make_task_data(bb, 0, 200)
    # Fisher by hand on the same four batches: mean of squared batch gradients.
    batches = [data.sample() for _ in range(4)]
    it = iter(batches)
    fixed = dataclasses.replace(data, sample=lambda: next(it))
    manual = {k: torch.zeros_like(p) for k, p in bb.named_parameters()}
    for b in batches:
        bb.zero_grad()
        bb.backbone_loss(b).backward()
        for k, p in bb.named_parameters():
            manual[k] += p.grad**2 / 4
    bb.zero_grad()
    ewc.after_task(0, bb, fixed)
    for k in manual:
        torch.testing.assert_close(ewc.fisher[k], manual[k])
    assert sum(f.sum() for f in ewc.fisher.values()) > 0

    assert ewc.penalty(bb, bb.backbone_loss).item() == 0.0  # at the anchor
    anchor = snapshot(bb)
    g = torch.Generator().manual_seed(1)
    direction = {k: torch.randn(v.shape, generator=g) for k, v in anchor.items()}
    values = []
    for scale in (0.25, 0.5, 1.0, 2.0):
        with torch.no_grad():
            for k, p in bb.named_parameters():
                p.copy_(anchor[k] + scale * direction[k])
        values.append(ewc.penalty(bb, bb.backbone_loss).item())
    # lambda * sum F d^2 * scale^2 (the authors' form, no 1/2): monotone, and x4 per doubling.
    quad = 10.0 * sum((manual[k] * direction[k] ** 2).sum().item() for k in manual)
    assert values == pytest.approx([quad * s**2 for s in (0.25, 0.5, 1.0, 2.0)], rel=1e-5)
    assert all(a < b for a, b in zip(values, values[1:], strict=False))
    # Gradient of the penalty: 2 lambda * F * (theta - theta*).
    bb.zero_grad()
    ewc.penalty(bb, bb.backbone_loss).backward()
    expected = 2.0 * 10.0 * manual["dynamics.weight"] * 2.0 * direction["dynamics.weight"]
    torch.testing.assert_close(bb.dynamics.weight.grad, expected)


@pytest.mark.parametrize("decay", [1.0, 0.5])
def test_ewc_accumulates_fisher_and_moves_anchor(decay):
    torch.manual_seed(0)
    bb = TinyBackbone()
    ewc = method("ewc", fisher_batches=3, fisher_decay=decay)
    data0, data1 = make_task_data(bb, 0, 100), make_task_data(bb, 1, 100)
    ewc.after_task(0, bb, data0)
    f0 = {k: v.clone() for k, v in ewc.fisher.items()}
    opt = torch.optim.Adam(bb.parameters(), lr=1e-2)
    train(bb, ewc, opt, data1, 10)
    probe = method("ewc", fisher_batches=3)
    # Two fresh samplers of task 1 with the same seed -> the same Fisher batches.
    ewc.after_task(1, bb, make_task_data(bb, 1, 100))
    probe.after_task(1, bb, make_task_data(bb, 1, 100))
    for k in f0:
        torch.testing.assert_close(ewc.fisher[k], decay * f0[k] + probe.fisher[k])
        assert torch.equal(ewc.anchor[k], dict(bb.named_parameters())[k].detach())


# ----------------------------------------------------------------------------- PackNet


def linear_weights(bb: TinyBackbone) -> dict[str, torch.Tensor]:
    return {"encoder.0.weight": bb.encoder[0].weight, "dynamics.weight": bb.dynamics.weight}


SHARED = ["encoder.0.bias", "encoder.1.weight", "encoder.1.bias", "dynamics.bias"]


def test_packnet_state_machine_freezing_and_masks():
    torch.manual_seed(0)
    bb = TinyBackbone()
    pn = method("packnet", num_tasks=3, retrain_steps=5)
    opt = torch.optim.Adam(bb.parameters(), lr=1e-2)
    data = [make_task_data(bb, t, 256) for t in range(3)]

    # ---- task 0: train, prune 75% of each layer by magnitude, retrain, freeze
    pn.before_task(0, bb)
    assert set(pn.owner) == set(linear_weights(bb))  # only Linear weights are prunable
    train(bb, pn, opt, data[0], 20)
    pre = {k: w.detach().clone() for k, w in linear_weights(bb).items()}
    pn.after_task(0, bb, data[0])
    assert pn.phase is Phase.PRUNED and pn.wants_retrain_steps == 5
    for name, w in linear_weights(bb).items():
        owner = pn.owner[name]
        assert int((owner == 0).sum()) == round(0.25 * w.numel())
        assert torch.all(w[owner == FREE] == 0)
        assert pre[name][owner == 0].abs().min() >= pre[name][owner == FREE].abs().max()
    with pytest.raises(RuntimeError, match="retrain steps still owed"):
        pn.before_task(1, bb)
    for _ in range(pn.wants_retrain_steps):
        train(bb, pn, opt, data[0], 1)
    assert pn.phase is Phase.FROZEN and pn.wants_retrain_steps == 0
    task0 = snapshot(bb)
    for name, w in linear_weights(bb).items():  # retraining left free weights at 0
        assert torch.all(w[pn.owner[name] == FREE] == 0)
        assert not torch.equal(w[pn.owner[name] == 0], pre[name][pn.owner[name] == 0])
    with pytest.raises(RuntimeError, match="outside training"):
        pn.after_step(bb)

    # ---- task 1 with the same Adam (momentum of frozen entries is non-zero)
    pn.before_task(1, bb)
    loss = data[1].backbone_loss(data[1].sample())
    opt.zero_grad()
    loss.backward()
    for name, w in linear_weights(bb).items():  # gradient hook: frozen entries get no gradient
        assert torch.all(w.grad[pn.owner[name] == 0] == 0)
        assert w.grad[pn.owner[name] == FREE].abs().sum() > 0
    opt.step()
    moved = [
        not torch.equal(w[pn.owner[n] == 0], task0[n][pn.owner[n] == 0])
        for n, w in linear_weights(bb).items()
    ]
    assert all(moved), "Adam's momentum alone should move frozen entries"
    pn.after_step(bb)  # ... and after_step writes them back exactly
    train(bb, pn, opt, data[1], 30)
    params = dict(bb.named_parameters())
    for name, w in linear_weights(bb).items():
        owned0 = pn.owner[name] == 0
        assert torch.equal(w[owned0], task0[name][owned0])
        assert w[~owned0].abs().sum() > 0  # the free weights did learn task 1
    for name in SHARED:  # biases and LayerNorm frozen after task 0
        assert torch.equal(params[name], task0[name])

    # evaluating(0) hides everything task 0 did not use, then restores it bit for bit
    before = snapshot(bb)
    with pn.evaluating(0, bb):
        for name in params:
            assert torch.equal(params[name], task0[name]), name
    assert all(torch.equal(before[k], v) for k, v in bb.named_parameters())
    with pn.evaluating(1, bb):  # the task in training uses its free weights
        assert all(torch.equal(before[k], v) for k, v in bb.named_parameters())
    with pytest.raises(ValueError, match="cannot evaluate task 2"):
        with pn.evaluating(2, bb):
            pass

    pn.after_task(1, bb, data[1])
    for name, w in linear_weights(bb).items():
        free_after_0 = w.numel() - round(0.25 * w.numel())
        assert int((pn.owner[name] == 1).sum()) == round(0.25 * free_after_0)
    for _ in range(pn.wants_retrain_steps):
        train(bb, pn, opt, data[1], 1)
    task1 = snapshot(bb)

    # ---- task 2 (last): not pruned, owns every free entry
    pn.before_task(2, bb)
    train(bb, pn, opt, data[2], 10)
    pn.after_task(2, bb, data[2])
    assert pn.phase is Phase.FROZEN and pn.wants_retrain_steps == 0
    for name, w in linear_weights(bb).items():
        assert not torch.any(pn.owner[name] == FREE)
        n1 = round(0.25 * (w.numel() - round(0.25 * w.numel())))
        assert float((pn.owner[name] == 2).float().mean()) == pytest.approx(
            1 - (round(0.25 * w.numel()) + n1) / w.numel()
        )
    # Every earlier task's backbone is recovered exactly under its mask.
    for task, snap in ((0, task0), (1, task1)):
        with pn.evaluating(task, bb):
            assert all(torch.equal(v, snap[k]) for k, v in bb.named_parameters()), task

    # Checkpoint round trip gives the same masks.
    twin = method("packnet", num_tasks=3, retrain_steps=5)
    twin.load_state_dict(pn.state_dict())
    with twin.evaluating(0, bb):
        assert all(torch.equal(v, task0[k]) for k, v in bb.named_parameters())


def test_packnet_without_retraining_freezes_at_once():
    torch.manual_seed(0)
    bb = TinyBackbone()
    pn = method("packnet", num_tasks=2, retrain_steps=0, keep_fraction=0.5)
    opt = torch.optim.Adam(bb.parameters(), lr=1e-2)
    data = make_task_data(bb, 0, 64)
    pn.before_task(0, bb)
    train(bb, pn, opt, data, 3)
    pn.after_task(0, bb, data)
    assert pn.phase is Phase.FROZEN and pn.wants_retrain_steps == 0
    assert float((pn.owner["dynamics.weight"] == 0).float().mean()) == pytest.approx(
        round(0.5 * bb.dynamics.weight.numel()) / bb.dynamics.weight.numel()
    )
    with pytest.raises(RuntimeError, match="expected task 1"):
        pn.before_task(2, bb)


# ----------------------------------------------------------------------------- TD-MPC2


def _tdmpc2_setup():
    from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config

    try:
        from replay_data import random_buffer
    except ImportError:  # tests/ imported as a package
        from tests.replay_data import random_buffer

    torch.manual_seed(0)
    cfg = TDMPC2Config.preset("smoke")
    model = TDMPC2(cfg, device="cpu")
    buffers = [random_buffer(cfg, seed=task, task=task, steps=(5, 30)) for task in range(2)]
    return cfg, model, buffers


def _task_data(model, buf, task):
    return TaskData.from_buffer(task, buf, batch_size=16, seq_len=model.cfg.seq_len,
                                backbone_loss=model.backbone_loss)  # fmt: skip


@pytest.mark.parametrize("name", ["ft", "er", "ewc", "packnet"])
def test_methods_on_tdmpc2_backbone(name):
    cfg, model, buffers = _tdmpc2_setup()
    kwargs = {
        "er": {"fraction": 0.25, "batch_size": 8},
        "ewc": {"fisher_batches": 3},
        "packnet": {"retrain_steps": 2},
    }.get(name, {})
    method_ = method(name, num_tasks=2, **kwargs)
    backbone = model.backbone
    penalties = []
    task0 = None
    for task in range(2):
        heads = model.new_heads()
        opt = model.world_model_optimizer(heads)
        head_params = snapshot(heads)
        method_.before_task(task, backbone)

        def update(task=task, heads=heads, opt=opt):
            out = model.loss(buffers[task].sample(16, cfg.seq_len), heads)
            pen = method_.penalty(backbone, model.backbone_loss)
            penalties.append(pen.item())
            opt.zero_grad()
            (out.total + pen).backward()
            nn.utils.clip_grad_norm_(model.parameters(), 20.0)
            opt.step()
            method_.after_step(backbone)

        for _ in range(4):
            update()
        method_.after_task(task, backbone, _task_data(model, buffers[task], task))
        for _ in range(method_.wants_retrain_steps):
            update()
        if task == 0:
            task0 = snapshot(backbone)
        assert not all(torch.equal(v, head_params[k]) for k, v in heads.named_parameters())
        with method_.evaluating(0, backbone):
            if name == "packnet":  # task 0's backbone exactly, during and after task 1
                assert all(torch.equal(v, task0[k]) for k, v in backbone.named_parameters())

    assert all(math.isfinite(p) for p in penalties)
    later = penalties[4 + (2 if name == "packnet" else 0) :]
    if name in ("ft", "packnet"):
        assert all(p == 0.0 for p in penalties)
    else:  # ER replays task 0 and EWC penalises drift during task 1
        assert all(p > 0 for p in later[1:])
    if name == "packnet":
        linears = [m for m in backbone.modules() if isinstance(m, nn.Linear)]
        assert len(method_.owner) == len(linears) > 0


@pytest.mark.parametrize("name,options", [*((n, {}) for n in shipped_methods()),
                                          ("er", {"through_heads": True})])  # fmt: skip
def test_an_update_under_a_method_reads_nothing_back_from_the_device(name, options, monkeypatch):
    """The second task's update under each method (its penalty, through the first task's
    stored heads where it uses them, and its `after_step`) runs on the meta device, so it
    reads nothing back to the host: on a GPU every read waits for the queued kernels."""
    import contextlib

    import ccfit.train.update as update_module
    from ccfit.continual.base import method_config_class
    from ccfit.models import make_model
    from ccfit.models.registry import config_class
    from ccfit.train.update import UpdateStep

    try:
        from replay_data import random_buffer
        from test_models_contract import HostReads
    except ImportError:  # tests/ imported as a package
        from tests.replay_data import random_buffer
        from tests.test_models_contract import HostReads

    real_adam = torch.optim.Adam  # fused Adam has no meta kernel; the unfused rule is the same
    monkeypatch.setattr(torch.optim, "Adam", lambda p, **kw: real_adam(p, **{**kw, "fused": False}))
    monkeypatch.setattr(update_module, "autocast_context", lambda *a: contextlib.nullcontext())
    torch.manual_seed(0)
    model_name = "pwm" if "experts" in method_config_class(name).REQUIRES else "tdmpc2"
    model = make_model(config_class(model_name).preset("smoke", obs_mode="state"), "cpu")
    cfg = model.cfg
    if name == "packnet":
        options = {"retrain_steps": 0}  # task 1 starts at once
    method_ = make_method(method_config_class(name)(**options), num_tasks=2)
    buffers = [random_buffer(cfg, seed=t, task=t, steps=(5, 30)) for t in range(2)]
    model.begin_task(0, 1000)
    method_.before_task(0, model.backbone)
    stored = {0: model.new_heads()}
    method_.after_task(0, model.backbone, _task_data(model, buffers[0], 0))
    model.begin_task(1, 1000)
    heads = model.new_heads()  # (PWM reads its current task here: once a task, not an update)
    for module in (model, heads, stored[0]):
        module.to("meta")
    model.device = torch.device("meta")
    method_.before_task(1, model.backbone)  # which moves the method's state to the backbone's
    step = UpdateStep(model, heads, method_, lambda batch, j: model.loss(batch, stored[j]).total)
    batch = buffers[1].sample(cfg.batch_size, cfg.seq_len).to("meta")
    with HostReads() as reads:
        logs = step(batch)
    assert reads.copies == [] and logs["total"].is_meta


@pytest.mark.parametrize("name", ["ewc", "packnet"])
def test_method_state_saved_on_the_cpu_works_on_the_backbones_device(name):
    """A resumed run loads method state on the CPU (`map_location='cpu'`) while the backbone
    may be on a GPU: the method moves its tensors to the backbone's device. Checked with
    PyTorch's 'meta' device, which, like a GPU, refuses to mix with CPU tensors."""
    torch.manual_seed(0)
    bb = TinyBackbone()
    data = make_task_data(bb, 0, 64)
    first = method(name, num_tasks=2, **({"retrain_steps": 0} if name == "packnet" else {}))
    first.before_task(0, bb)
    first.after_task(0, bb, data)
    state = copy.deepcopy(first.state_dict())
    moved = TinyBackbone().to("meta")
    resumed = method(name, num_tasks=2, **({"retrain_steps": 0} if name == "packnet" else {}))
    resumed.load_state_dict(state)
    resumed.before_task(1, moved)
    pen = resumed.penalty(moved, moved.backbone_loss)
    assert pen.device.type == "meta"
    resumed.after_step(moved)
    with resumed.evaluating(0, moved):
        pass
    tensors = [*getattr(resumed, "fisher", {}).values(), *getattr(resumed, "owner", {}).values()]
    assert tensors and all(t.device.type == "meta" for t in tensors)
