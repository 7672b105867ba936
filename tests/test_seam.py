"""The world-model seam is one place: a toy model defined only here registers itself and runs
the loop and a smoke curriculum under every backbone method, with nothing changed elsewhere.

The toy also counts what the loop calls (the DreamerV3/embodied habit: test the loop with a
fake agent), so the loop's contract is checked exactly: seed steps are observed, not acted;
fractional update ratios accumulate; every episode starts from `initial_state`.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn

from ccfit.config import CurriculumConfig, TaskRunConfig, resolve
from ccfit.continual.packnet import prunable_weights
from ccfit.curriculum import METRICS_JSON, Curriculum
from ccfit.models.base import Batch, LossOutput, WorldModel
from ccfit.models.registry import ModelConfig, model_names, register_model
from ccfit.train import RunLogger, Trainer, build_model, make_replay

CALLS: Counter = Counter()


@dataclass
class ToyConfig(ModelConfig):
    """A linear world model on the 39-D state."""

    PRESETS = {
        "smoke": dict(batch_size=8, seq_len=3, train_ratio=0.5),
        "cpu": dict(batch_size=32, seq_len=3),
        "paper": dict(batch_size=256, seq_len=3),
    }

    latent: int = 16
    """Latent width."""


@register_model("toy", ToyConfig)
class ToyModel(WorldModel):
    def __init__(self, cfg: ToyConfig, device=None, encoder=None) -> None:
        super().__init__()
        if cfg.obs_mode != "state":
            raise ValueError("the toy reads state observations only")
        self.cfg, self.device = cfg, torch.device(device or "cpu")
        self.backbone = nn.ModuleDict({
            "encoder": nn.Linear(cfg.state_dim, cfg.latent),
            "dynamics": nn.Linear(cfg.latent + cfg.action_dim, cfg.latent),
        })  # fmt: skip
        self.to(self.device)

    def new_heads(self) -> nn.Module:
        c = self.cfg
        return nn.ModuleDict({"reward": nn.Linear(c.latent + c.action_dim, 1),
                              "pi": nn.Linear(c.latent, c.action_dim)}).to(self.device)  # fmt: skip

    def world_model_optimizer(self, heads):
        params = [p for p in self.backbone.parameters() if p.requires_grad]
        return torch.optim.Adam(params + list(heads["reward"].parameters()), lr=1e-3)

    def head_optimizers(self, heads):
        return {"pi": torch.optim.Adam(heads["pi"].parameters(), lr=1e-3)}

    def _latents(self, batch: Batch):
        z = self.backbone["encoder"](batch.obs["state"])
        za = torch.cat([z[:-1], batch.action[:-1]], -1)
        return z, za

    def backbone_loss(self, batch: Batch) -> torch.Tensor:
        z, za = self._latents(batch)
        err = (self.backbone["dynamics"](za) - z[1:].detach()).pow(2).mean(-1, keepdim=True)
        return (err * batch.valid()).mean()

    def loss(self, batch: Batch, heads) -> LossOutput:
        CALLS["loss"] += 1
        z, za = self._latents(batch)
        reward = (heads["reward"](za) - batch.reward[:-1]).pow(2) * batch.valid()
        total = self.backbone_loss(batch) + reward.mean()
        return LossOutput(total, {"reward": float(reward.mean().detach())}, aux=z.detach())

    def head_update(self, batch, heads, out, optimizers) -> dict:
        CALLS["head_update"] += 1
        z = out.aux
        a = torch.tanh(heads["pi"](z))
        loss = -heads["reward"](torch.cat([z, a], -1)).mean()
        optimizers["pi"].zero_grad()
        loss.backward()
        optimizers["pi"].step()
        return {"pi_loss": float(loss.detach())}

    def initial_state(self, heads):
        CALLS["initial_state"] += 1
        return 0  # steps seen in this episode

    def act(self, obs, heads, state, *, eval_mode):
        CALLS["act_eval" if eval_mode else "act_train"] += 1
        z = self.backbone["encoder"](obs["state"])
        return torch.tanh(heads["pi"](z)).cpu().numpy(), state + 1

    def observe(self, obs, action, heads, state):
        CALLS["observe"] += 1
        assert action.shape == (self.cfg.action_dim,)
        return state + 1


pytestmark = pytest.mark.usefixtures("short_episodes")
SMOKE_TRAIN = {"steps": 200, "seed_steps": 60, "eval_interval": 100, "checkpoint_interval": 100}


def test_toy_is_registered_beside_the_builtin_models():
    assert {"toy", "tdmpc2", "pwm"} <= set(model_names())


def test_loop_calls_the_model_as_its_contract_says(tmp_path, monkeypatch):
    import ccfit.train.loop
    from ccdata.env import make_env

    eval_lengths = []

    def evaluate_and_count(*args, **kwargs):
        result = real_evaluate(*args, **kwargs)
        eval_lengths.extend(result.lengths)
        return result

    real_evaluate = ccfit.train.loop.evaluate
    monkeypatch.setattr(ccfit.train.loop, "evaluate", evaluate_and_count)

    cfg = resolve(TaskRunConfig, {"task": "reach-xy", "preset": "smoke", "seed_dataset": None,
                                  "model": {"type": "toy"}, "train": dict(SMOKE_TRAIN)})
    model = build_model(cfg, torch.device("cpu"))
    heads = model.new_heads()
    env = make_env("reach-xy", render=False)
    buffer = make_replay(cfg, model, "reach-xy", 0, None)
    buffer.add_episode({"state": np.zeros((6, 39), np.float32)}, np.zeros((5, 4), np.float32),
                       np.zeros(5, np.float32), np.zeros(5, np.float32))  # sampleable at once
    trainer = Trainer(env=env, model=model, heads=heads, config=cfg.train, seed=0,
                      obs_mode="state", task_id="reach-xy", buffer=buffer,
                      logger=RunLogger(tmp_path), progress=False)  # fmt: skip
    CALLS.clear()
    trainer.run()
    env.close()
    steps, seed_steps = SMOKE_TRAIN["steps"], SMOKE_TRAIN["seed_steps"]
    assert CALLS["observe"] == seed_steps  # random steps are observed, never acted
    assert CALLS["act_train"] == steps - seed_steps
    # train_ratio 0.5: one update every second step once replay holds a window
    assert CALLS["loss"] == CALLS["head_update"] == trainer.updates
    assert trainer.updates == (steps - seed_steps) // 2
    # three evaluations (steps 0, 100, 200) of one episode each, one act per step
    assert len(eval_lengths) == 3 and CALLS["act_eval"] == sum(eval_lengths)
    # every episode, training or evaluation, starts from a fresh acting state
    assert CALLS["initial_state"] == trainer.episode_index + 3


@pytest.mark.parametrize("method", ["ft", "er", "ewc", "packnet"])
def test_toy_runs_a_curriculum_under_every_backbone_method(tmp_path, method):
    options = {"er": {"batch_size": 8}, "ewc": {"fisher_batches": 2},
               "packnet": {"retrain_steps": 5}}.get(method, {})  # fmt: skip
    cfg = resolve(CurriculumConfig, {
        "suite": "Reach", "preset": "smoke", "seed_dataset": None, "model": {"type": "toy"},
        "method": {"type": method, **options}, "train": dict(SMOKE_TRAIN),
    })  # fmt: skip
    before = None
    if method == "packnet":
        model = build_model(cfg, torch.device("cpu"))
        before = {id(p) for p in model.backbone.parameters() if p.dim() >= 2}
        assert before == prunable_weights(model.backbone)
    result = Curriculum(cfg, tmp_path / "run", tmp_path / "scratch", progress=False).run()
    saved = json.loads((tmp_path / "run" / METRICS_JSON).read_text())
    assert saved == json.loads(json.dumps(result))
    assert result["model"] == "toy" and result["method"] == method
    assert np.isfinite(result["fwt"]) and len(result["end_of_task"]) == 4
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["model"]["type"] == "toy" and config["method"]["type"] == method
