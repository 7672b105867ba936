"""ER through the stored heads (`--method.through_heads=true`): each kept window also goes
through its own task's frozen heads, whose gradient reaches the backbone only; and the run's
seed reaches ER's reservoir."""

from __future__ import annotations

import numpy as np
import torch

from ccdata import make_env
from ccfit.config import CurriculumConfig, TrainConfig
from ccfit.config_parse import resolve
from ccfit.continual.base import ReplayLosses, TaskData, make_method, method_config
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
from ccfit.replay import ReplayBuffer
from ccfit.train import Evaluator, Trainer


def _random_buffer(seed: int, episodes: int = 4, steps: int = 30) -> ReplayBuffer:
    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(10_000, seed=seed)
    for _ in range(episodes):
        term = np.zeros(steps, np.float32)
        term[-1] = 1.0
        buf.add_episode({"state": rng.normal(size=(steps + 1, 39)).astype(np.float32)},
                        rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
                        -rng.uniform(0, 1, steps).astype(np.float32), term)  # fmt: skip
    return buf


def _finished_task(model: TDMPC2, buffer: ReplayBuffer) -> TaskData:
    return TaskData.from_buffer(0, buffer, batch_size=8, seq_len=model.cfg.seq_len,
                                backbone_loss=model.backbone_loss)  # fmt: skip


def test_replay_through_stored_heads_trains_the_backbone_only(short_episodes):
    torch.manual_seed(0)
    model = TDMPC2(TDMPC2Config.preset("smoke", batch_size=8, episode_length=short_episodes),
                   device="cpu")  # fmt: skip
    heads0 = model.new_heads().requires_grad_(False).eval()
    before = {k: v.clone() for k, v in heads0.state_dict().items()}
    er = make_method(resolve(CurriculumConfig, {"suite": "Reach", "method": {
        "type": "er", "through_heads": True, "fraction": 0.5}}).method, 4, seed=0)  # fmt: skip
    er.after_task(0, model.backbone, _finished_task(model, _random_buffer(0)))
    stored = [heads0]
    losses = ReplayLosses(model.backbone_loss, lambda b, j: model.loss(b, stored[j]).total)

    # The penalty through the stored heads is the whole loss, not the backbone terms alone...
    # (the same replayed windows for both: the sampler is rewound)
    sampler = er.memory.generator.get_state()
    with_heads = er.penalty(model.backbone, losses)
    er.memory.generator.set_state(sampler)
    backbone_only = er.penalty(model.backbone, ReplayLosses(model.backbone_loss, None))
    assert float(with_heads.detach()) != float(backbone_only.detach())
    # ...and its gradient reaches the backbone, never the frozen heads.
    with_heads.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0
               for p in model.backbone.parameters())  # fmt: skip
    assert all(p.grad is None for p in heads0.parameters())

    # A trainer with this method on the next task leaves the stored heads bit-identical.
    cfg = TrainConfig(steps=60, seed_steps=20, eval_interval=60, eval_episodes=1,
                      checkpoint_interval=60, buffer_capacity=1000, device="cpu",
                      episode_steps=short_episodes)  # fmt: skip
    env = make_env("reach-xz", render=False, episode_steps=short_episodes)
    evaluator = Evaluator(model, {1: "reach-xz"}, seed=0, obs_mode="state", image_size=64,
                          episodes=1, episode_steps=short_episodes)  # fmt: skip
    trainer = Trainer(env=env, model=model, heads=model.new_heads(), config=cfg, seed=0,
                      evaluator=evaluator,
                      obs_mode="state", task_id="reach-xz", task_index=1, method=er,
                      buffer=_random_buffer(1), progress=False,
                      stored_heads_loss=lambda b, j: model.loss(b, stored[j]).total)  # fmt: skip
    trainer.run()
    env.close()
    evaluator.close()
    assert trainer.updates > 0
    after = heads0.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_the_runs_seed_reaches_the_er_reservoir():
    model = TDMPC2(TDMPC2Config.preset("smoke", batch_size=8), device="cpu")
    data = _finished_task(model, _random_buffer(0, episodes=10))

    def kept(seed: int) -> np.ndarray:
        cfg = resolve(CurriculumConfig, {"suite": "Reach", "seed": seed,
                                         "method": {"type": "er"}})  # fmt: skip
        er = make_method(cfg.method, len(cfg.tasks), cfg.seed)
        er.after_task(0, model.backbone, data)
        return er.kept[0]

    windows = round(0.05 * data.num_transitions / (model.cfg.seq_len - 1))
    assert len(kept(0)) == windows > 0
    assert torch.equal(kept(0), kept(0))
    assert not torch.equal(kept(0), kept(1))


def test_replay_through_stored_pwm_heads_leaves_their_task_alone():
    """ER through a finished task's stored heads computes that task's loss; the loss has no
    side effect, so the finished task's router temperature (and its schedule) stay put."""
    from ccfit.models.pwm import PWM, PWMConfig

    torch.manual_seed(0)
    model = PWM(PWMConfig.preset("smoke", batch_size=8, tau_hold_min=0), device="cpu")
    model.begin_task(0, 100)
    heads0 = model.new_heads().requires_grad_(False).eval()
    er = make_method(method_config("er", through_heads=True, fraction=0.5), 4)
    er.after_task(0, model.backbone, _finished_task(model, _random_buffer(0)))
    model.begin_task(1, 100)
    model.train()
    tau, updates = model.dynamics.tau.clone(), model.dynamics.tau_updates.clone()
    losses = ReplayLosses(model.backbone_loss, lambda b, j: model.loss(b, [heads0][j]).total)
    for _ in range(3):
        er.penalty(model.backbone, losses).backward()
    assert torch.equal(model.dynamics.tau, tau)
    assert torch.equal(model.dynamics.tau_updates, updates)
