"""Each seam is one place: a toy model, a toy continual method and a toy analysis, defined only
here, register themselves and run the loop and smoke curricula, with nothing changed
elsewhere (the toy model under every backbone method, the toy method under the toy model, the
toy analysis for every model offering its capability).

The toy also counts what the loop calls (the DreamerV3/embodied habit: test the loop with a
fake agent), so the loop's contract is checked exactly: seed steps are observed, not acted;
fractional update ratios accumulate; every episode starts from `initial_state`.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from ccfit.analysis import register_analysis, stage_callbacks
from ccfit.config import CurriculumConfig, TaskRunConfig
from ccfit.config_base import check
from ccfit.config_parse import resolve
from ccfit.continual import ContinualMethod, MethodConfig, register_method
from ccfit.continual.packnet import prunable_weights
from ccfit.curriculum import METRICS_JSON, Curriculum
from ccfit.models.base import Batch, LossOutput, WorldModel
from ccfit.models.registry import ModelConfig, model_names, register_model
from ccfit.train import RunLogger, Trainer, build_model, make_evaluator, make_replay

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
    capabilities = frozenset({"toy-probe"})

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

    def initial_state(self, heads, n=1):
        CALLS["initial_state"] += n
        return torch.zeros(n, dtype=torch.long)  # steps seen in each episode

    def act(self, obs, heads, state, *, eval_mode):
        n = obs["state"].shape[0]
        assert state.shape == (n,)
        CALLS["act_eval" if eval_mode else "act_train"] += n
        CALLS["act_calls_eval" if eval_mode else "act_calls_train"] += 1
        z = self.backbone["encoder"](obs["state"])
        # A deterministic policy that depends on the acting state (the step in the episode).
        a = torch.tanh(heads["pi"](z) + 0.01 * state.unsqueeze(-1).float())
        return a.detach().cpu().numpy(), state + 1

    def observe(self, obs, action, heads, state):
        CALLS["observe"] += 1
        assert action.shape == (obs["state"].shape[0], self.cfg.action_dim)
        return state + 1


@dataclass
class AnchorConfig(MethodConfig):
    """A method anchoring the backbone to where it started: strength * squared distance."""

    strength: float = 1.0
    """Weight of the squared distance."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.strength >= 0, f"toy-anchor: strength must be >= 0, got {self.strength}")


@register_method("toy-anchor", AnchorConfig)
class Anchor(ContinualMethod):
    def before_task(self, task_index, backbone) -> None:
        CALLS["before_task"] += 1
        if task_index == 0:
            self.start = {k: v.detach().clone() for k, v in backbone.named_parameters()}

    def penalty(self, backbone, losses) -> torch.Tensor:
        CALLS["penalty"] += 1
        return self.cfg.strength * sum(
            ((p - self.start[k]) ** 2).sum() for k, p in backbone.named_parameters()
        )

    def after_task(self, task_index, backbone, task_data) -> None:
        CALLS["after_task"] += 1

    def state_dict(self) -> dict:
        return {"start": getattr(self, "start", {})}

    def load_state_dict(self, state: dict) -> None:
        self.start = state["start"]


PROBED: list[tuple[str, int]] = []


@register_analysis("toy-probe")
def probe(stage) -> None:
    """Records which model and how many stored heads it saw after each task."""
    PROBED.append((stage.cfg.model.type, len(stage.stored_heads)))


try:
    from short_episodes import EPISODE_STEPS
except ImportError:  # tests/ imported as a package
    from tests.short_episodes import EPISODE_STEPS

SMOKE_TRAIN = {"steps": 200, "seed_steps": 60, "eval_interval": 100, "checkpoint_interval": 100,
               "episode_steps": EPISODE_STEPS}  # fmt: skip


def test_toy_is_registered_beside_the_builtin_models():
    assert {"toy", "tdmpc2", "pwm"} <= set(model_names())


def test_the_toys_join_no_other_modules_cases():
    # Registered on import, so present while later modules are collected: the tests
    # parametrised over the shipped registries must not pick them up by collection order.
    from ccfit.continual import method_names

    try:
        from shipped import shipped_methods, shipped_models
    except ImportError:  # tests/ imported as a package
        from tests.shipped import shipped_methods, shipped_models

    assert "toy-anchor" in method_names() and "toy-anchor" not in shipped_methods()
    assert "toy" not in shipped_models() and {"dreamerv3", "pwm", "tdmpc2"} <= set(shipped_models())
    assert {"er", "ewc", "experts", "ft", "packnet"} <= set(shipped_methods())


def test_loop_calls_the_model_as_its_contract_says(tmp_path, monkeypatch):
    import ccfit.train.evaluate
    from ccdata.env import make_env

    eval_lengths = []

    def play_and_count(*args, **kwargs):
        episodes = real_play(*args, **kwargs)
        eval_lengths.append([len(e.rewards) for e in episodes])
        return episodes

    real_play = ccfit.train.evaluate.play_episodes
    monkeypatch.setattr(ccfit.train.evaluate, "play_episodes", play_and_count)

    train = {**SMOKE_TRAIN, "eval_episodes": 3}
    cfg = resolve(
        TaskRunConfig,
        {
            "task": "reach-xy",
            "preset": "smoke",
            "seed_dataset": None,
            "model": {"type": "toy"},
            "train": train,
        },
    )
    model = build_model(cfg, torch.device("cpu"))
    heads = model.new_heads()
    env = make_env("reach-xy", render=False, episode_steps=EPISODE_STEPS)
    buffer = make_replay(cfg, model, "reach-xy", 0, None)
    buffer.add_episode(
        {"state": np.zeros((6, 39), np.float32)},
        np.zeros((5, 4), np.float32),
        np.zeros(5, np.float32),
        np.zeros(5, np.float32),
    )  # sampleable at once
    evaluator = make_evaluator(cfg, model, {0: "reach-xy"})
    trainer = Trainer(env=env, model=model, heads=heads, config=cfg.train, seed=0,
                      obs_mode="state", task_id="reach-xy", buffer=buffer, evaluator=evaluator,
                      logger=RunLogger(tmp_path), progress=False)  # fmt: skip
    CALLS.clear()
    trainer.run()
    env.close()
    evaluator.close()
    steps, seed_steps = SMOKE_TRAIN["steps"], SMOKE_TRAIN["seed_steps"]
    assert CALLS["observe"] == seed_steps  # random steps are observed, never acted
    assert CALLS["act_train"] == CALLS["act_calls_train"] == steps - seed_steps
    # train_ratio 0.5: one update every second step once replay holds a window
    assert CALLS["loss"] == CALLS["head_update"] == trainer.updates
    assert trainer.updates == (steps - seed_steps) // 2
    # Three evaluations (steps 0, 100, 200) of three episodes each, played together: one act
    # per step of each running episode, one act call per step of the longest.
    assert len(eval_lengths) == 3 and all(len(lengths) == 3 for lengths in eval_lengths)
    assert CALLS["act_eval"] == sum(map(sum, eval_lengths))
    assert CALLS["act_calls_eval"] == sum(map(max, eval_lengths))
    # every episode, training or evaluation, starts from a fresh acting state
    assert CALLS["initial_state"] == trainer.episode_index + 3 * 3


@pytest.mark.parametrize("workers", [0, 2])
def test_batched_evaluation_plays_the_episodes_of_sequential_play(tmp_path, workers):
    """A deterministic policy plays the same episodes, bit for bit, whether the evaluation
    layouts play side by side (what the loop does; `workers`: their environments in that many
    processes) or one after the other, here."""
    from ccfit.train import EnvPool, eval_seeds, play_episodes

    cfg = resolve(TaskRunConfig, {"task": "reach-xy", "preset": "smoke", "seed_dataset": None,
                                  "model": {"type": "toy"},
                                  "train": {"episode_steps": EPISODE_STEPS}})  # fmt: skip
    torch.manual_seed(0)
    model = build_model(cfg, torch.device("cpu"))
    heads = model.new_heads()
    with torch.no_grad():  # a policy that reaches: the hand moves toward the goal
        enc, pi = model.backbone["encoder"], heads["pi"]
        enc.weight.zero_(), enc.bias.zero_(), pi.weight.zero_(), pi.bias.zero_()
        for i in range(3):  # z_i = goal_i - hand_i (39-D state: hand at 0:3, goal at 36:39)
            enc.weight[i, 36 + i], enc.weight[i, i] = 1.0, -1.0
            pi.weight[i, i] = 50.0
    seeds = eval_seeds(0, 0, 6)
    pool = EnvPool("state", 64, workers, episode_steps=EPISODE_STEPS)
    here = EnvPool("state", 64, episode_steps=EPISODE_STEPS)
    together = play_episodes(pool.get("reach-xy", 6), model, heads, obs_mode="state",
                             seeds=seeds, record=True)  # fmt: skip
    alone = [play_episodes(here.get("reach-xy", 1), model, heads, obs_mode="state", seeds=[s],
                           record=True)[0] for s in seeds]  # fmt: skip
    pool.close(), here.close()
    assert len({len(e.rewards) for e in together}) > 2, "episodes of one length test less"
    assert any(e.success for e in together)
    for a, b in zip(together, alone, strict=True):
        assert a.rewards == b.rewards and a.success == b.success
        assert np.array_equal(a.action, b.action)
        assert all(np.array_equal(a.obs[k], b.obs[k]) for k in a.obs)


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
    assert len(result["end_of_task"]) == 4
    # FWT by hand from the records: the composition task's curve during its stage, rebased to
    # 0, minus the from-scratch curve, trapezoids over the shared evaluation points, / budget.
    records = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    steps = SMOKE_TRAIN["steps"]
    seq = {r["task_step"]: r["normalized_return"] for r in records if r["task_index"] == 3}
    scratch = json.loads((Path(result["scratch_dir"]) / "done.json").read_text())
    scr = {r["task_step"]: r["normalized_return"] for r in scratch}
    points = sorted(seq)
    assert points == sorted(scr) == list(range(0, steps + 1, SMOKE_TRAIN["eval_interval"]))
    diff = [seq[t] - scr[t] for t in points]
    area = sum((diff[k] + diff[k + 1]) / 2 * (points[k + 1] - points[k])
               for k in range(len(points) - 1))  # fmt: skip
    assert result["fwt"] == pytest.approx(area / steps)
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["model"]["type"] == "toy" and config["method"]["type"] == method


def test_a_method_and_an_analysis_join_by_registering(tmp_path):
    cfg = resolve(CurriculumConfig, {
        "suite": "Reach", "preset": "smoke", "seed_dataset": None, "model": {"type": "toy"},
        "method": {"type": "toy-anchor", "strength": 0.5}, "train": dict(SMOKE_TRAIN),
    })  # fmt: skip
    assert stage_callbacks(cfg) == [probe]
    CALLS.clear()
    PROBED.clear()
    Curriculum(cfg, tmp_path / "run", tmp_path / "scratch", progress=False,
               callbacks=stage_callbacks(cfg)).run()  # fmt: skip
    assert CALLS["before_task"] == CALLS["after_task"] == 4 and CALLS["penalty"] > 0
    assert PROBED == [("toy", 1), ("toy", 2), ("toy", 3), ("toy", 4)]
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["method"] == {"type": "toy-anchor", "strength": 0.5}
    # The analysis is the toy capability's only: a built-in model does not get it.
    other = resolve(CurriculumConfig, {"suite": "Reach", "preset": "smoke"})
    assert probe not in stage_callbacks(other)
