"""Routing records, Fig. 5 numbers and the expert ablation (Fig. 6) on a real smoke PWM
curriculum (Reach, progressive experts), driven through `Curriculum.run` and the CLI."""

import json
import math

import numpy as np
import pytest
import torch

from ccfit.analysis import (
    ABLATION_JSON,
    ABLATION_PNG,
    ROUTING,
    append_routing,
    figure_data,
    load_routed_run,
    read_routing,
    routing_callback,
    routing_record,
)
from ccfit.cli import main
from ccfit.config import CurriculumConfig
from ccfit.config_parse import resolve
from ccfit.curriculum import Curriculum
from ccfit.train import CONFIG

try:
    from short_episodes import short
except ImportError:  # tests/ imported as a package
    from tests.short_episodes import short

K, TASKS, MAX_EXPERTS = 3, 4, 24  # PWM defaults: 3 experts per task, 8 groups allocated


def smoke_config(model: str = "pwm", method: str = "experts") -> CurriculumConfig:
    return resolve(CurriculumConfig, {
        "suite": "Reach", "preset": "smoke", "seed": 0, "seed_dataset": None,
        "model": {"type": model}, "method": {"type": method},
        "train": short(dict(steps=100, seed_steps=50, eval_interval=100, checkpoint_interval=100)),
    })  # fmt: skip


@pytest.fixture(scope="module")
def pwm_run(tmp_path_factory):
    """A finished 4-task PWM + experts curriculum (about a minute on a loaded machine)."""
    root = tmp_path_factory.mktemp("analysis")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        # Short episodes also end inside a 100-step task, so replay holds data and the heads
        # do get trained.
        Curriculum(
            smoke_config(),
            root / "run",
            root / "scratch",
            progress=False,
            callbacks=[routing_callback],
        ).run()
    finally:
        torch.set_num_threads(threads)
    return root / "run"


# ----------------------------------------------------------------------- routing record


@pytest.mark.integration
def test_routing_record_per_stage(pwm_run):
    records = read_routing(pwm_run)
    assert [r["stage"] for r in records] == list(range(TASKS))
    for s, r in enumerate(records):
        assert r["num_active"] == K * (s + 1)  # one new group per task
        assert [t["task_index"] for t in r["tasks"]] == list(range(s + 1))
        for t in r["tasks"]:
            w = np.array(t["weights"])
            assert w.shape == (MAX_EXPERTS,)
            assert t["routed_as"] == t["task_index"]
            assert t["samples"] > 0 and t["normalized_return"] is not None
            assert np.all(w[r["num_active"] :] == 0.0)  # inactive experts: exactly 0
            scope = K * (t["task_index"] + 1)  # a task routes over its own and earlier groups
            assert np.all(w[:scope] > 0.0) and np.all(w[scope:] == 0.0)
            assert w.sum() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.integration
def test_routing_record_reproduces_from_saved_run(pwm_run):
    """Replaying the last stage from curriculum.pt gives the record written during the run:
    the record depends only on the model state and the run's seed."""
    cfg, model, stored, method = load_routed_run(pwm_run)
    again = routing_record(
        model, stored, cfg.tasks, stage=TASKS - 1, seed=cfg.seed, episodes=1,
        episode_steps=cfg.train.episode_steps, obs_mode="state",
        device=model.device, view=lambda i: method.evaluating(i, model.backbone),
    )  # fmt: skip
    assert json.loads(json.dumps(again)) == read_routing(pwm_run)[-1]


@pytest.mark.integration
def test_resume_of_finished_run_keeps_routing(pwm_run):
    before = (pwm_run / ROUTING).read_bytes()
    Curriculum(
        smoke_config(),
        pwm_run,
        pwm_run.parent / "scratch",
        progress=False,
        callbacks=[routing_callback],
    ).run()
    assert (pwm_run / ROUTING).read_bytes() == before


def test_append_routing_replaces_redone_stages(tmp_path):
    for stage in (0, 1, 2):
        append_routing(tmp_path, {"stage": stage, "mark": "first"})
    append_routing(tmp_path, {"stage": 1, "mark": "redone"})  # a resumed run redoing stage 1
    lines = [json.loads(x) for x in (tmp_path / ROUTING).read_text().splitlines()]
    assert lines == [{"stage": 0, "mark": "first"}, {"stage": 1, "mark": "redone"}]


# ------------------------------------------------------------------------ Fig. 5 numbers


def _record(stage: int, k: int, current: list[float], width: int = 8) -> dict:
    """A routing record whose current-task weights are `current` (padded with zeros)."""
    w = list(current) + [0.0] * (width - len(current))
    filler = {"weights": [0.0] * width}
    return {"stage": stage, "task": f"t{stage}", "num_active": len(current),
            "experts_per_task": k, "tasks": [filler] * stage + [{"weights": w}]}  # fmt: skip


def test_figure_data_known_answer():
    k = 2
    records = [
        _record(0, k, [0.7, 0.3]),
        _record(1, k, [0.1, 0.3, 0.4, 0.2]),
        _record(2, k, [0.05, 0.15, 0.1, 0.3, 0.2, 0.2]),
    ]
    data = figure_data(records, num_tasks=3)
    rel = data["relative_change"]
    assert rel[0] == [1.0, None, None]
    assert rel[1][0] == pytest.approx(0.2 / 0.5) and rel[1][1] == 1.0 and rel[1][2] is None
    assert rel[2][0] == pytest.approx(0.1 / 0.5)
    assert rel[2][1] == pytest.approx(0.2 / 0.3)
    assert rel[2][2] == 1.0
    norm = data["normalized_weights"]
    assert norm[0][:2] == pytest.approx([1.4, 0.6]) and norm[0][2:] == [None] * 4
    assert norm[2] == pytest.approx([0.3, 0.9, 0.6, 1.8, 1.2, 1.2])
    top = data["top_expert"]
    # Task 0's top expert is 0 (0.7 vs 0.3), after composition 1 (0.05 vs 0.15); task 1's is
    # expert 2 (0.4 vs 0.2), after composition 3 (0.1 vs 0.3).
    assert [(p["top_before"], p["top_after"]) for p in top["primitives"]] == [(0, 1), (2, 3)]
    assert (top["k"], top["n"]) == (0, 2)
    records[2]["tasks"][2]["weights"][:4] = [0.3, 0.1, 0.2, 0.1]
    top = figure_data(records, num_tasks=3)["top_expert"]
    assert (top["k"], top["n"]) == (2, 2)
    assert figure_data(records[:2], num_tasks=3)["top_expert"]["k"] is None  # not finished


@pytest.mark.integration
def test_figure_data_of_run(pwm_run):
    records = read_routing(pwm_run)
    data = figure_data(records, TASKS)
    rel = data["relative_change"]
    for s in range(TASKS):
        assert rel[s][s] == 1.0  # exactly: a ratio to itself
        assert all(v is None for v in rel[s][s + 1 :])
        assert all(v is not None and 0 < v < math.inf for v in rel[s][: s + 1])
    w = [np.array(r["tasks"][s]["weights"]) for s, r in enumerate(records)]
    assert rel[3][1] == pytest.approx(w[3][3:6].mean() / w[1][3:6].mean(), rel=1e-12)
    for s, row in enumerate(data["normalized_weights"]):
        active = [v for v in row if v is not None]
        assert len(active) == K * (s + 1) and len(row) == K * TASKS
        assert np.mean(active) == pytest.approx(1.0, abs=1e-5)
    top = data["top_expert"]
    assert top["n"] == TASKS - 1 and 0 <= top["k"] <= top["n"]
    for p in top["primitives"]:
        j = p["task_index"]
        assert p["top_before"] == K * j + int(np.argmax(w[j][K * j : K * (j + 1)]))
        assert p["top_after"] == K * j + int(np.argmax(w[-1][K * j : K * (j + 1)]))


@pytest.mark.integration
def test_report_draws_routing_figure(pwm_run, tmp_path):
    import matplotlib.image

    out = tmp_path / "report"
    assert main(["report", str(pwm_run), "--out", str(out)]) == 0
    png = out / "routing_pwm_Reach_experts_s0.png"
    image = matplotlib.image.imread(png)
    assert image.shape[0] > 200 and image.shape[1] > 600
    summary = json.loads((out / "summary.json").read_text())
    routing = summary["pwm/Reach/experts"]["routing"]["s0"]
    k = figure_data(read_routing(pwm_run), TASKS)["top_expert"]["k"]
    assert (routing["top_expert_stays_top"], routing["of"]) == (k, TASKS - 1)
    assert routing["statement"].endswith(f"in {k}/{TASKS - 1} cases")


# ---------------------------------------------------------------------------- ablation


@pytest.mark.integration
def test_ablate_command(pwm_run, capsys):
    assert main(["ablate", str(pwm_run), "--episodes", "1"]) == 0
    assert "uniform" in capsys.readouterr().out
    result = json.loads((pwm_run / ABLATION_JSON).read_text())
    assert (pwm_run / ABLATION_PNG).stat().st_size > 1000
    modes = result["modes"]
    assert list(modes) == ["full", "prior", "new", "uniform"]
    assert result["task"] == "reach-xyz" and result["num_active"] == K * TASKS
    for m in modes.values():
        for key in ("normalized_return", "latent_error", "return_ratio", "latent_error_ratio",
                    "fidelity_ratio"):  # fmt: skip
            assert math.isfinite(m[key]), key
        assert m["latent_error"] > 0
    full = modes["full"]
    assert full["return_ratio"] == full["latent_error_ratio"] == full["fidelity_ratio"] == 1.0
    # The routing each mode planned with, read through routing_weights inside the override.
    n, prior = K * TASKS, K * (TASKS - 1)
    w = {name: np.array(m["routing_weights"]) for name, m in modes.items()}
    assert np.all(w["new"][:prior] == 0.0) and w["new"][prior:n].sum() == pytest.approx(1.0)
    assert np.all(w["prior"][prior:] == 0.0) and w["prior"][:prior].sum() == pytest.approx(1.0)
    assert w["uniform"][:n] == pytest.approx(np.full(n, 1.0 / n))
    for name in w:
        assert np.all(w[name][n:] == 0.0)
    learnt = np.array(read_routing(pwm_run)[-1]["tasks"][-1]["weights"])
    assert w["full"] == pytest.approx(learnt, abs=1e-6)  # task routing: input-independent
    # Different experts, different dynamics: the open-loop errors must differ.
    assert modes["new"]["latent_error"] != full["latent_error"]
    assert modes["prior"]["latent_error"] != full["latent_error"]


@pytest.mark.integration
def test_ablate_errors(pwm_run, tmp_path, capsys):
    tdmpc2 = tmp_path / "tdmpc2"
    tdmpc2.mkdir()
    cfg = smoke_config(model="tdmpc2", method="ft").to_dict()
    (tdmpc2 / CONFIG).write_text(json.dumps(cfg))
    assert main(["ablate", str(tdmpc2)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "tdmpc2" in err
    assert "needs a model offering 'routing'" in err

    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / CONFIG).write_text((pwm_run / CONFIG).read_text())
    assert main(["ablate", str(unfinished)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not finished" in err

    assert main(["ablate", str(tmp_path / "missing")]) == 2
    assert "not a run directory" in capsys.readouterr().err
