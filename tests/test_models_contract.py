"""The WorldModel contract, for every registered model (a new model joins by registering).

Each model runs at its `smoke` preset in both observation modes (pixels at 32 px when the
model allows it, else 64) on windows sampled from a real ReplayBuffer of short random
episodes, driven only through the interface the training loop uses.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np
import pytest
import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

from ccfit.config_base import PRESETS, ConfigError
from ccfit.models import ModelConfig, WorldModel, make_model
from ccfit.models.base import LossOutput, select_state
from ccfit.models.registry import config_class, model_class
from ccfit.train.update import UpdateStep, backbone_optimizer_state, load_backbone_optimizer_state

try:
    from replay_data import random_buffer
    from shipped import shipped_models
except ImportError:  # tests/ imported as a package
    from tests.replay_data import random_buffer
    from tests.shipped import shipped_models

NAMES = shipped_models()
MODES = ("state", "pixels")
B = 8
CLONING = [n for n in NAMES
           if "demo_bc_coef" in {f.name for f in dataclasses.fields(config_class(n))}]  # fmt: skip
"""The models that can clone the batch's demonstration windows (`demo_bc_coef`)."""


def smoke_config(name: str, mode: str) -> ModelConfig:
    cls = config_class(name)
    if mode == "state":
        return cls.preset("smoke", obs_mode="state")
    try:
        return cls.preset("smoke", obs_mode="pixels", image_size=32)
    except ConfigError:
        return cls.preset("smoke", obs_mode="pixels", image_size=64)


def build(name: str, mode: str, seed: int = 0, **fields) -> tuple[WorldModel, nn.Module]:
    """A model at its smoke preset (with `fields` changed) and its first task's heads."""
    torch.manual_seed(seed)
    model = make_model(dataclasses.replace(smoke_config(name, mode), **fields), "cpu")
    model.begin_task(0, 1000)
    return model, model.new_heads()


def batch_of(model: WorldModel, seed: int = 0):
    cfg = model.cfg
    return random_buffer(cfg, seed=seed).sample(cfg.batch_size, cfg.seq_len)


def update(model, heads, opt, head_opts, batch) -> tuple[LossOutput, dict]:
    """One update as the training loop makes it."""
    out = model.loss(batch, heads)
    opt.zero_grad(set_to_none=True)
    out.total.backward()
    nn.utils.clip_grad_norm_([p for g in opt.param_groups for p in g["params"]],
                             model.cfg.grad_clip)  # fmt: skip
    opt.step()
    return out, model.head_update(batch, heads, out, head_opts)


def ids(params) -> list[int]:
    return [id(p) for p in params]


def optimiser_params(opt: torch.optim.Optimizer) -> list[nn.Parameter]:
    return [p for g in opt.param_groups for p in g["params"]]


def all_finite(logs: dict) -> bool:
    """Scalars (0-d tensors, which the loop reduces when it logs, or floats), all finite."""
    return all((isinstance(v, float) or (isinstance(v, torch.Tensor) and v.dim() == 0))
               and math.isfinite(float(v)) for v in logs.values())  # fmt: skip


cases = pytest.mark.parametrize("name,mode", [(n, m) for n in NAMES for m in MODES])


def test_registry_lists_the_models():
    assert {"tdmpc2", "pwm"} <= set(NAMES)
    for name in NAMES:
        cls = config_class(name)
        assert issubclass(cls, ModelConfig) and issubclass(model_class(name), WorldModel)
        for preset in PRESETS:
            cfg = cls.preset(preset)
            assert cfg.type == name and cfg.seq_len >= 2 and cfg.batch_size >= 1
    with pytest.raises(ConfigError, match="unknown model 'nope'"):
        model_class("nope")


@cases
def test_losses_and_head_update_are_finite(name, mode):
    model, heads = build(name, mode)
    batch = batch_of(model)
    assert batch.seq_len == model.cfg.seq_len and batch.size == model.cfg.batch_size
    out = model.loss(batch, heads)
    assert isinstance(out, LossOutput) and out.total.shape == () and torch.isfinite(out.total)
    assert out.logs and all_finite(out.logs)
    bb = model.backbone_loss(batch)
    assert bb.shape == () and torch.isfinite(bb) and bb.item() > 0
    out.total.backward()
    logs = model.head_update(batch, heads, out, model.head_optimizers(heads))
    assert logs and all_finite(logs)


@cases
def test_act_returns_actions_and_a_state_for_a_batch_of_episodes(name, mode):
    model, heads = build(name, mode)
    cfg, n = model.cfg, 3
    obs = {k: v[0, :n] for k, v in batch_of(model).obs.items()}
    for eval_mode in (False, True):
        state = model.initial_state(heads, n)
        for _ in range(2):  # twice in a row, with the state
            action, state = model.act(obs, heads, state, eval_mode=eval_mode)
            assert isinstance(action, np.ndarray) and action.shape == (n, cfg.action_dim)
            assert np.isfinite(action).all() and np.abs(action).max() <= 1.0
        state = model.observe(obs, np.zeros((n, cfg.action_dim), np.float32), heads, state)
        action, state = model.act(obs, heads, state, eval_mode=eval_mode)
        assert action.shape == (n, cfg.action_dim)
        # The episodes still running go on with their own state.
        keep = torch.tensor([2, 0])
        action, _ = model.act({k: v[keep] for k, v in obs.items()}, heads,
                              select_state(state, keep), eval_mode=eval_mode)  # fmt: skip
        assert action.shape == (2, cfg.action_dim)


@cases
def test_state_dict_round_trip_gives_the_same_loss(name, mode, tmp_path):
    model, heads = build(name, mode, seed=0)
    update(model, heads, model.world_model_optimizer(heads), model.head_optimizers(heads),
           batch_of(model))  # fmt: skip
    torch.save({"model": model.state_dict(), "heads": heads.state_dict()}, tmp_path / "ck.pt")
    other, other_heads = build(name, mode, seed=1)
    ck = torch.load(tmp_path / "ck.pt")
    other.load_state_dict(ck["model"])
    other_heads.load_state_dict(ck["heads"])
    batch = batch_of(model, seed=5)
    losses = []
    for m, h in ((model, heads), (other, other_heads)):
        torch.manual_seed(3)
        with torch.no_grad():
            losses.append((m.loss(batch, h).total, m.backbone_loss(batch)))
    assert torch.equal(losses[0][0], losses[1][0]) and torch.equal(losses[0][1], losses[1][1])


def _three_updates(name: str, mode: str) -> list[torch.Tensor]:
    model, heads = build(name, mode, seed=7)
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    for i in range(3):
        update(model, heads, opt, head_opts, batch_of(model, seed=i))
    return [t.detach().clone() for t in [*model.state_dict().values(),
                                         *heads.state_dict().values()]]  # fmt: skip


@cases
def test_same_seed_same_first_updates(name, mode):
    a, b = _three_updates(name, mode), _three_updates(name, mode)
    assert len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("name", NAMES)
def test_parameters_split_into_backbone_and_heads_and_optimisers(name):
    model, heads = build(name, "state")
    backbone, head = ids(model.backbone.parameters()), ids(heads.parameters())
    assert not set(backbone) & set(head)
    # The model holds no parameter outside its backbone.
    assert set(ids(model.parameters())) == set(backbone)
    # Every trainable parameter is stepped by exactly one optimiser, and the backbone's
    # trainable parameters all by the world-model optimiser.
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    assert head_opts and all(isinstance(o, torch.optim.Optimizer) for o in head_opts.values())
    stepped = ids(optimiser_params(opt))
    for o in head_opts.values():
        stepped += ids(optimiser_params(o))
    trainable = [p for p in [*model.backbone.parameters(), *heads.parameters()] if p.requires_grad]
    for p in trainable:
        assert stepped.count(id(p)) == 1
    assert set(ids(p for p in model.backbone.parameters() if p.requires_grad)) <= set(
        ids(optimiser_params(opt))
    )
    for o in head_opts.values():
        assert not set(ids(optimiser_params(o))) & set(backbone)


@pytest.mark.parametrize("name", NAMES)
def test_the_next_tasks_optimiser_continues_the_backbones_state(name):
    """`keep_backbone_optimizer`: the next task's world-model optimiser starts with exactly
    the backbone's Adam state (step counts, moments) of the last one; new heads start fresh."""
    model, heads = build(name, "state")
    step = UpdateStep(model, heads)
    for seed in range(2):
        step(batch_of(model, seed))
    carried = backbone_optimizer_state(step.optim, model.backbone)
    backbone = dict(model.backbone.named_parameters())
    assert carried and set(carried) <= set(backbone)
    model.begin_task(1, 1000)
    new_heads = model.new_heads()
    fresh = model.world_model_optimizer(new_heads)
    load_backbone_optimizer_state(fresh, model.backbone, carried)
    stepped = set(ids(optimiser_params(fresh)))
    kept = [n for n, p in backbone.items() if id(p) in stepped and n in carried]
    assert kept, "no backbone state carried over"
    for name_, param in backbone.items():
        if name_ in kept:
            held = fresh.state[param]
            assert held.keys() == carried[name_].keys()
            assert all(torch.equal(held[k], v) for k, v in carried[name_].items())
            assert held["exp_avg"] is not carried[name_]["exp_avg"]
        else:
            assert param not in fresh.state
    assert not any(p in fresh.state for p in new_heads.parameters())
    # The carried state steps as the optimiser's own (where Adam keeps each tensor).
    fresh.zero_grad(set_to_none=True)
    task1 = random_buffer(model.cfg, seed=2, task=1).sample(model.cfg.batch_size, model.cfg.seq_len)
    model.loss(task1, new_heads).total.backward()
    fresh.step()
    first = backbone[kept[0]]
    assert float(fresh.state[first]["step"]) == float(carried[kept[0]]["step"]) + 1


@cases
def test_loss_has_no_side_effect_and_head_update_leaves_backbone_parameters(name, mode):
    model, heads = build(name, mode)
    model.train()
    batch = batch_of(model)
    state = {k: v.clone() for k, v in [*model.state_dict().items(), *heads.state_dict().items()]}
    out = model.loss(batch, heads)
    model.backbone_loss(batch)
    now = [*model.state_dict().items(), *heads.state_dict().items()]
    assert all(torch.equal(state[k], v) for k, v in now), "loss changed the model or heads"
    before = {k: v.clone() for k, v in model.backbone.named_parameters()}
    heads_before = {k: v.clone() for k, v in heads.state_dict().items()}
    model.head_update(batch, heads, out, model.head_optimizers(heads))
    assert all(torch.equal(before[k], v) for k, v in model.backbone.named_parameters())
    assert any(not torch.equal(heads_before[k], v) for k, v in heads.state_dict().items())


@cases
def test_backbone_loss_trains_the_backbone_only(name, mode):
    model, heads = build(name, mode)
    model.backbone_loss(batch_of(model)).backward()
    assert all(p.grad is None or not p.grad.any() for p in heads.parameters())
    grads = [p.grad for p in model.backbone.parameters() if p.requires_grad]
    assert any(g is not None and g.abs().sum() > 0 for g in grads)


class HostReads(TorchDispatchMode):
    """On the meta device, which holds no data, what would read the device's data back to the
    host (a wait for the device, on a GPU): a scalar read (`.item()`, `bool()`) fails there; a
    copy to the CPU is recorded and answered with an uninitialised CPU tensor."""

    def __init__(self) -> None:
        super().__init__()
        self.copies: list[tuple[int, ...]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        src = args[0] if args else None
        if (func is torch.ops.aten._to_copy.default and src.is_meta
                and torch.device(kwargs.get("device") or src.device).type == "cpu"):  # fmt: skip
            self.copies.append(tuple(src.shape))
            return torch.empty(src.shape, dtype=kwargs.get("dtype") or src.dtype)
        return func(*args, **kwargs)


@cases
def test_an_update_reads_nothing_back_and_an_act_only_its_actions(name, mode, monkeypatch):
    """An update as the loop makes it (`UpdateStep`) runs on the meta device, so nothing in it
    reads the device's data back; an act reads back exactly its actions (n, A). On a GPU a
    read waits for every queued kernel: one per update would starve the device. A model that
    can clone demonstrations does, on a batch with some."""
    import ccfit.train.update as update_module

    real_adam = torch.optim.Adam  # fused Adam has no meta kernel; the unfused rule is the same
    monkeypatch.setattr(torch.optim, "Adam", lambda p, **kw: real_adam(p, **{**kw, "fused": False}))
    monkeypatch.setattr(update_module, "autocast_context", lambda *a: contextlib.nullcontext())
    clones = name in CLONING
    model, heads = build(name, mode, **({"demo_bc_coef": 0.5} if clones else {}))
    batch = dataclasses.replace(batch_of(model), demos=2 if clones else 0)
    model.to("meta")
    heads.to("meta")
    model.device = torch.device("meta")
    meta = batch.to("meta")
    obs = {k: v[0, :2] for k, v in meta.obs.items()}
    with HostReads() as reads:
        logs = UpdateStep(model, heads)(meta)
        assert reads.copies == [] and all(v.is_meta for v in logs.values())
        action, _ = model.act(obs, heads, model.initial_state(heads, 2), eval_mode=False)
    assert reads.copies == [(2, model.cfg.action_dim)] and action.shape == (2, model.cfg.action_dim)


def test_the_models_that_clone_demonstrations():
    # The cloning tests run over CLONING: an empty list would pass them all unseen.
    assert set(CLONING) == {"tdmpc2", "pwm", "dreamerv3"}


@pytest.mark.parametrize("name", CLONING)
def test_demo_cloning_needs_demonstrations_in_the_batch_and_an_online_run(name):
    """`--model.demo_bc_coef` clones what `--train.demo_fraction` puts in each batch: without
    it, or offline, one clear refusal."""
    from ccfit.config import TaskRunConfig
    from ccfit.config_parse import parse_cli
    from ccfit.offline.config import OfflineConfig

    with pytest.raises(ConfigError, match="demo_bc_coef must be >= 0"):
        dataclasses.replace(smoke_config(name, "state"), demo_bc_coef=-1.0)
    args = ["--task", "pick-cube", "--preset", "smoke", f"--model.type={name}",
            "--model.demo_bc_coef=0.5"]  # fmt: skip
    with pytest.raises(ConfigError, match="--train.demo_fraction puts in each batch"):
        parse_cli(TaskRunConfig, args)
    assert parse_cli(TaskRunConfig, [*args, "--train.demo_fraction=0.25"]).model.demo_bc_coef == 0.5
    with pytest.raises(ConfigError, match="the offline track fits every episode alike"):
        parse_cli(OfflineConfig, ["--suite", "Grasp", f"--model.type={name}",
                                  "--model.demo_bc_coef=0.5"])  # fmt: skip


@pytest.mark.parametrize("name", NAMES)
def test_bf16_autocast_updates_and_acts(name):
    """`--train.autocast=bf16`: an update is finite and keeps float32 parameters; actions come
    back as float32 arrays."""
    from ccfit.train.compiled import autocast

    model, heads = build(name, "state")
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    batch = batch_of(model)
    with autocast(torch.device("cpu"), "bf16"):
        out, logs = update(model, heads, opt, head_opts, batch)
        obs = {k: v[0, :2] for k, v in batch.obs.items()}
        with torch.no_grad():
            action, _ = model.act(obs, heads, model.initial_state(heads, 2), eval_mode=True)
    assert torch.isfinite(out.total) and all_finite(logs)
    assert all(p.dtype == torch.float32 for p in [*model.parameters(), *heads.parameters()])
    assert action.dtype == np.float32 and np.isfinite(action).all()
