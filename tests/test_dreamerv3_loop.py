"""DreamerV3 in the real training loop: a smoke curriculum (Grasp, 3 tasks, state obs) under ft
and packnet, PackNet's frozen task-0 weights across every backbone weight matrix (the GRU's
included), and a killed single-task run resuming to the uninterrupted result.

One module-scoped fixture runs both curricula (tens of seconds on a loaded 2-core machine;
evaluation episodes dominate). A stage callback (the curriculum's public hook) snapshots the
backbone and the method's state after each task; nothing is mocked.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ccfit.config import CurriculumConfig, TaskRunConfig
from ccfit.config_parse import resolve
from ccfit.continual.packnet import prunable_weights
from ccfit.curriculum import METRICS_JSON, Curriculum, Stage
from ccfit.models.dreamerv3 import DreamerV3
from ccfit.train import METRICS

try:
    from metrics_by_hand import bwt_by_hand
    from short_episodes import EPISODE_STEPS
except ImportError:  # tests/ imported as a package
    from tests.metrics_by_hand import bwt_by_hand
    from tests.short_episodes import EPISODE_STEPS

SUITE = "Grasp"
TASKS = ("pick-cube", "place-cube", "pnp-cube")
STEPS = 60
TRAIN = {"steps": STEPS, "seed_steps": 30, "eval_interval": STEPS, "checkpoint_interval": 30,
         "eval_episodes": 1, "device": "cpu", "episode_steps": EPISODE_STEPS}  # fmt: skip
METHODS = {"ft": {}, "packnet": {"retrain_steps": 5}}


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / METRICS).read_text().splitlines() if x.strip()]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("dv3_curriculum")
    return _run_curricula(root)


def _run_curricula(root: Path) -> dict[str, SimpleNamespace]:
    out = {}
    for method, options in METHODS.items():
        cfg = resolve(CurriculumConfig, {
            "suite": SUITE, "preset": "smoke", "seed_dataset": None, "train": dict(TRAIN),
            "model": {"type": "dreamerv3"}, "method": {"type": method, **options},
        })  # fmt: skip
        stages: list[dict] = []

        def snapshot(stage: Stage, stages=stages) -> None:
            stages.append({
                "backbone": {n: p.detach().clone()
                             for n, p in stage.model.backbone.named_parameters()},
                "method": copy.deepcopy(stage.method.state_dict()),
                "prunable": {n for n, p in stage.model.backbone.named_parameters()
                             if id(p) in prunable_weights(stage.model.backbone)},
            })  # fmt: skip

        result = Curriculum(cfg, root / method, root / "scratch", progress=False,
                            callbacks=[snapshot]).run()  # fmt: skip
        out[method] = SimpleNamespace(cfg=cfg, dir=root / method, result=result, stages=stages)
    return out


@pytest.mark.parametrize("method", METHODS)
def test_curriculum_writes_metrics_and_evaluates_every_seen_task(runs, method):
    run = runs[method]
    metrics = json.loads((run.dir / METRICS_JSON).read_text())
    assert metrics == json.loads(json.dumps(run.result))
    assert (metrics["suite"], metrics["model"], metrics["method"]) == (SUITE, "dreamerv3", method)
    assert metrics["task_ends"] == [STEPS, 2 * STEPS, 3 * STEPS] and metrics["budget"] == STEPS
    assert metrics["fwt"] is not None and np.isfinite(metrics["fwt"])
    recs = _records(run.dir)
    per_task = bwt_by_hand(recs, 3, STEPS, STEPS)
    assert metrics["bwt_per_task"] == pytest.approx(per_task)
    assert set(metrics["bwt_excluded"]) == {"0", "1"} - set(per_task)
    # Each stage: its own task at its start; every task seen at its end.
    expected = sorted(
        [(s, s, s * STEPS) for s in range(3)]
        + [(j, s, (s + 1) * STEPS) for s in range(3) for j in range(s + 1)]
    )
    assert sorted((r["task_index"], r["stage"], r["global_step"]) for r in recs) == expected
    assert all(r["task"] == TASKS[r["task_index"]] for r in recs)
    assert all(np.isfinite(r["normalized_return"]) for r in recs)
    cfg = json.loads((run.dir / "config.json").read_text())
    assert cfg["model"]["type"] == "dreamerv3" and cfg["model"]["deter"] == 32  # smoke
    # The model trained: each task moved the backbone (ft: every parameter may move).
    first, last = run.stages[0]["backbone"], run.stages[-1]["backbone"]
    assert any(not torch.equal(first[n], last[n]) for n in first)


def test_packnet_keeps_task0_weights_of_every_backbone_matrix_bit_identical(runs):
    run = runs["packnet"]
    after0, after1, final = (s["backbone"] for s in run.stages)
    owner0 = run.stages[0]["method"]["owner"]
    prunable = run.stages[0]["prunable"]
    # Every weight matrix of the backbone is pruned, the GRU's and the RSSM's layers included.
    matrices = {n for n, p in after0.items() if p.dim() >= 2}
    assert prunable == matrices == set(owner0)
    for part in ("rssm.gru.weight", "rssm.img_in.0.weight", "rssm.img_out.1.weight",
                 "rssm.obs_out.0.0.weight", "encoder.vector.0.0.weight"):  # fmt: skip
        assert part in prunable, part
    for name in prunable:
        mine = owner0[name] == 0
        n = mine.numel()
        assert int(mine.sum()) == round(0.25 * n), name
        for later in (after1, final):
            assert torch.equal(later[name][mine], after0[name][mine]), name
    # Biases, norms and the learned initial state froze with task 0.
    shared = set(after0) - prunable
    assert "rssm.initial" in shared and "rssm.gru_norm.weight" in shared
    for name in shared:
        assert torch.equal(final[name], after0[name]), name
    # Not vacuous: entries left free after task 0 trained in task 1.
    moved = sum(int((after1[n] != after0[n])[owner0[n] == -1].sum()) for n in prunable)
    assert moved > 0


def _task_config(out: Path) -> TaskRunConfig:
    return resolve(TaskRunConfig, {
        "task": "reach-xy", "preset": "smoke", "seed": 5, "seed_dataset": None, "out": str(out),
        "model": {"type": "dreamerv3"},
        "train": dict(steps=120, seed_steps=40, eval_interval=60, eval_episodes=1,
                      checkpoint_interval=60, buffer_capacity=2_000, device="cpu"),
    })  # fmt: skip


def _checkpoint_params(out: Path) -> dict[str, torch.Tensor]:
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    flat = {f"model.{k}": v for k, v in state["model"].items()}
    flat.update({f"heads.{k}": v for k, v in state["heads"].items()})
    return flat, state


def test_killed_run_resumes_to_the_uninterrupted_parameters(tmp_path, monkeypatch):
    from ccfit.train import train_single

    full, broken = tmp_path / "full", tmp_path / "broken"
    train_single(_task_config(full), progress=False)
    original = DreamerV3.loss
    calls = {"n": 0}

    def dying_loss(self, batch, heads):
        calls["n"] += 1
        # Replay holds the first episode once it is cut at step 60 (evaluation): 2 pretraining
        # updates there, then one every second step; call 25 is step ~106, after the
        # checkpoint of step 60 and before the end.
        if calls["n"] == 25:
            raise KeyboardInterrupt
        return original(self, batch, heads)

    monkeypatch.setattr(DreamerV3, "loss", dying_loss)
    with pytest.raises(KeyboardInterrupt):
        train_single(_task_config(broken), progress=False)
    monkeypatch.setattr(DreamerV3, "loss", original)
    assert torch.load(broken / "checkpoint.pt", weights_only=False)["task_step"] == 60
    train_single(_task_config(broken), progress=False)

    (a, state_a), (b, state_b) = _checkpoint_params(full), _checkpoint_params(broken)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed run diverged"
    # The pretraining burst ran once (not again on resume): 2 + (120 - 60) / 2 updates.
    assert state_a["updates"] == state_b["updates"] == 2 + 30
    assert (full / METRICS).read_text() == (broken / METRICS).read_text()
