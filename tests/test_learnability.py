"""`ccfit learnability`: steps to 50 and 80 per task from single-task runs, and per-suite
budgets, on a real smoke run and on records whose answers are known."""

from __future__ import annotations

import json
from pathlib import Path

from ccfit.analysis.learnability import (
    budgets,
    first_steady_at,
    first_step_at,
    read_run,
    write_learnability,
)

try:
    from short_episodes import smoke_train_argv
except ImportError:  # tests/ imported as a package
    from tests.short_episodes import smoke_train_argv


def _fake_run(root: Path, task: str, model: str, scores: list[float], interval: int = 1000,
              seed: int = 0, demo_fraction: float = 0.0,
              capacity: int = 50_000) -> Path:  # fmt: skip
    """A run directory as `ccfit train` leaves it (config.json, metrics.jsonl, cost.json)."""
    run = root / f"{model}-{task}-s{seed}-demo{demo_fraction}-cap{capacity}"
    run.mkdir(parents=True)
    steps = interval * (len(scores) - 1)
    (run / "config.json").write_text(json.dumps({
        "task": task, "seed": seed, "preset": "cpu", "obs": "state", "model": {"type": model},
        "train": {"steps": steps, "eval_interval": interval, "demo_fraction": demo_fraction,
                  "buffer_capacity": capacity},
    }))  # fmt: skip
    (run / "metrics.jsonl").write_text("".join(
        json.dumps({"task_step": i * interval, "normalized_return": s}) + "\n"
        for i, s in enumerate(scores)))  # fmt: skip
    (run / "cost.json").write_text(json.dumps({"wall_s": 10.0, "cpu_s": 7200.0, "segments": 1}))
    return run


def test_first_steps_and_budgets_by_hand(tmp_path):
    records = [{"task_step": t, "normalized_return": s} for t, s in
               [(0, 10.0), (1000, 55.0), (2000, 40.0), (3000, 85.0)]]  # fmt: skip
    assert first_step_at(records, 50) == 1000 and first_step_at(records, 80) == 3000
    assert first_step_at(records, 90) is None
    # three evaluations in a row at 80 or more (the stop rule), in any record order
    later = [(4000, 90.0), (5000, 20.0), (6000, 81.0), (7000, 80.0), (8000, 99.0)]
    swings = records + [{"task_step": t, "normalized_return": s} for t, s in later]
    assert first_steady_at(swings[::-1], 80) == 6000 and first_steady_at(records, 80) is None
    assert first_steady_at(swings, 80, evals=2) == 3000
    # Grasp: pick-cube reaches 50 at 2000, place-cube at 1000, pnp-cube at 4000: the suite
    # needs 4000 steps per task. Reach lacks a task: no budget.
    for task, scores in [("pick-cube", [0, 20, 60, 90]), ("place-cube", [0, 70, 90, 95, 96]),
                         ("pnp-cube", [0, 10, 20, 30, 55])]:  # fmt: skip
        _fake_run(tmp_path, task, "m", scores)
    _fake_run(tmp_path, "reach-xy", "m", [0, 90])
    _fake_run(tmp_path, "reach-xz", "m", [0, 10, 20, 30, 40, 50, 60, 70])
    rows = [read_run(p) for p in sorted(tmp_path.iterdir())]
    assert budgets(rows)["Grasp"] == {"m": 4000} and "Reach" not in budgets(rows)
    pnp = next(r for r in rows if r["task"] == "pnp-cube")
    assert pnp["suites"] == ["Grasp", "DrawerPnP", "PnPBoxClose"] and pnp["cpu_hours"] == 2.0
    assert (pnp["steps_to_50"], pnp["steps_to_80"], pnp["best"]) == (4000, None, 55)
    assert pnp["last"] == 55 and pnp["last_5"] == 23.0  # (0 + 10 + 20 + 30 + 55) / 5
    assert pnp["steady_80"] is None
    assert next(r for r in rows if r["task"] == "place-cube")["steady_80"] == 2000
    assert next(r for r in rows if r["task"] == "reach-xz")["last_5"] == 50.0  # 30 .. 70
    # runs oversampling demonstrations are rows (and budgets) of their own
    for task in ("pick-cube", "place-cube", "pnp-cube"):
        _fake_run(tmp_path, task, "m", [0, 60], demo_fraction=0.25)
    rows = [read_run(p) for p in sorted(tmp_path.iterdir())]
    assert budgets(rows)["Grasp"] == {"m": 4000, "m [demo_fraction=0.25]": 1000}
    # a task that never reaches 50: the suite has no budget within the runs
    _fake_run(tmp_path, "pick-cube", "m", [0, 10, 20, 30], seed=1)
    rows = [read_run(p) for p in sorted(tmp_path.iterdir())]
    assert budgets(rows)["Grasp"] == {"m": None, "m [demo_fraction=0.25]": 1000}
    # so are runs with another replay capacity than the preset's (cpu: 50 000 rows)
    _fake_run(tmp_path, "pnp-cube", "m", [0, 60], capacity=100_000, demo_fraction=0.25)
    row = read_run(sorted(tmp_path.glob("*cap100000"))[0])
    assert row["model"] == "m [demo_fraction=0.25, buffer_capacity=100000]"
    # and runs cloning the demonstrations (a model setting, off in the preset's model)
    run = Path(row["run"])
    cfg = json.loads((run / "config.json").read_text())
    cfg["model"] = {"type": "tdmpc2", "demo_bc_coef": 0.5}
    (run / "config.json").write_text(json.dumps(cfg))
    assert read_run(run)["model"] == (
        "tdmpc2 [demo_fraction=0.25, buffer_capacity=100000, demo_bc_coef=0.5]"
    )
    # and runs from pixels, through a frozen encoder or not (the state budget is not theirs)
    for obs, encoder in (("pixels", "frozen:enc.safetensors"), ("pixels", None)):
        run = _fake_run(tmp_path / obs / str(encoder), "reach-xy", "m", [0, 60])
        cfg = json.loads((run / "config.json").read_text())
        (run / "config.json").write_text(json.dumps({**cfg, "obs": obs, "encoder": encoder}))
        assert read_run(run)["model"] == ("m [pixels, frozen encoder]" if encoder else "m [pixels]")


def test_a_from_scratch_reference_is_a_row_of_its_task(tmp_path):
    """A curriculum's from-scratch reference (config of the suite, done.json, records of the
    suite's last task, no cost recorded) is the same single-task run: a row of that task; an
    unfinished one (no done.json) is not."""
    run = _fake_run(tmp_path, "reach-xyz", "m", [0, 40, 90])
    cfg = json.loads((run / "config.json").read_text())
    del cfg["task"]
    (run / "config.json").write_text(json.dumps({**cfg, "suite": "Reach"}))
    records = [{**json.loads(x), "task": "reach-xyz"}
               for x in (run / "metrics.jsonl").read_text().splitlines()]  # fmt: skip
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    (run / "cost.json").unlink()
    assert read_run(run) is None
    (run / "done.json").write_text(json.dumps(records))
    row = read_run(run)
    assert (row["task"], row["suites"], row["steps_to_50"], row["steps_to_80"]) == (
        "reach-xyz",
        ["Reach"],
        2000,
        2000,
    )
    assert row["cpu_hours"] is None  # not 0: no cost was recorded


def test_cli_on_a_real_smoke_run(tmp_path, capsys):
    from ccfit.cli import main

    run = tmp_path / "runs" / "reach"
    schedule = ["--train.steps=100", "--train.seed_steps=50", "--train.eval_interval=50",
                "--train.checkpoint_interval=50"]  # fmt: skip
    train = smoke_train_argv(run, *schedule)
    assert main(train) == 0
    capsys.readouterr()
    assert main(["learnability", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out.split()
    assert [Path(p).name for p in printed] == ["learnability.md", "learnability.csv",
                                               "budgets.json"]  # fmt: skip
    (row,) = [read_run(run)]
    assert row["task"] == "reach-xy" and row["budget"] == 100 and row["cpu_hours"] > 0
    md = (tmp_path / "out" / "learnability.md").read_text()
    # budget, trained; its short episodes make it another way of learning the task
    assert "| Reach | reach-xy | tdmpc2 [episode_steps=25] | 0 | 100 | 100 |" in md
    assert main(["learnability", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    # Published: the run's small files, and the same tables rebuilt from them alone.
    published = tmp_path / "results" / "learnability"
    assert main(["publish", str(tmp_path / "runs"), "--out", str(published)]) == 0
    files = sorted(str(p.relative_to(published)) for p in published.rglob("*") if p.is_file())
    assert files == ["learnability/budgets.json", "learnability/learnability.csv",
                     "learnability/learnability.md", "reach/config.json", "reach/cost.json",
                     "reach/metrics.jsonl"]  # fmt: skip
    for name in ("learnability.md", "learnability.csv", "budgets.json"):
        assert (published / "learnability" / name).read_text() == (
            tmp_path / "out" / name).read_text(), name  # fmt: skip
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert main(["publish", str(tmp_path / "empty"), "--out", str(tmp_path / "p")]) == 2
    assert "no finished runs under" in capsys.readouterr().err


def test_a_run_off_its_presets_model_is_a_row_of_its_own(tmp_path):
    # Another model size (or planner) learns another way: its row names the settings, as
    # demonstrations oversampled do; a run at the preset's model is the plain row.
    from ccfit.config import TaskRunConfig
    from ccfit.config_parse import resolve

    preset = resolve(TaskRunConfig, {"preset": "cpu", "obs": "state", "task": "reach-xy",
                                     "model": {"type": "tdmpc2"}}).to_dict()  # fmt: skip
    rows = {}
    for name, change in [("plain", {}), ("wide", {"mlp_dim": 384, "num_samples": 512})]:
        run = _fake_run(tmp_path / name, "reach-xy", "tdmpc2", [0, 90])
        cfg = json.loads((run / "config.json").read_text())
        cfg["model"] = {**preset["model"], **change}
        (run / "config.json").write_text(json.dumps(cfg))
        rows[name] = read_run(run)["model"]
    assert rows == {"plain": "tdmpc2", "wide": "tdmpc2 [mlp_dim=384, num_samples=512]"}


def test_a_run_made_before_its_preset_changed_a_legacy_setting_is_a_row_of_its_own(tmp_path):
    # config.json leaves out a `LEGACY_VALUES` setting at its legacy value; DreamerV3's `cpu`
    # preset has since weighted the state's reconstruction 1000: a run that recorded no weight
    # ran at 1 and learnt another way than one at the preset.
    from ccfit.config import TaskRunConfig
    from ccfit.config_base import LEGACY_VALUES
    from ccfit.config_parse import resolve

    preset = resolve(TaskRunConfig, {"preset": "cpu", "obs": "state", "task": "pick-cube",
                                     "model": {"type": "dreamerv3"}}).to_dict()  # fmt: skip
    assert preset["model"]["state_recon_scale"] != LEGACY_VALUES["model.state_recon_scale"]
    rows = {}
    for name, model in [("now", preset["model"]),
                        ("before", {k: v for k, v in preset["model"].items()
                                    if k != "state_recon_scale"})]:  # fmt: skip
        run = _fake_run(tmp_path / name, "pick-cube", "dreamerv3", [0, 90])
        cfg = json.loads((run / "config.json").read_text())
        (run / "config.json").write_text(json.dumps({**cfg, "model": model}))
        rows[name] = read_run(run)["model"]
    assert rows == {"now": "dreamerv3", "before": "dreamerv3 [state_recon_scale=1.0]"}


def test_a_damaged_run_is_one_line_and_exit_2(tmp_path, capsys):
    from ccfit.cli import main

    run = _fake_run(tmp_path / "runs", "pick-cube", "m", [0, 60, 90])
    with (run / "metrics.jsonl").open("a") as f:
        f.write('{"task_step": 3000, "normalized_ret')  # a copy cut short
    assert main(["learnability", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "metrics.jsonl: missing or corrupt" in line and "leave it out of the table" in line


def test_an_offline_reference_is_no_row(tmp_path):
    # `ccfit learnability results/` meets the offline track's references too: they score
    # predictions, not returns, so they are left out rather than read as online runs.
    ref = tmp_path / "runs" / "scratch" / "offline-Reach-dreamerv3-state-cpu-s0"
    ref.mkdir(parents=True)
    (ref / "config.json").write_text(json.dumps({"track": "offline", "suite": "Reach",
                                                 "seed": 0, "fit": {"updates": 100}}))  # fmt: skip
    (ref / "done.json").write_text("[]")
    (ref / "metrics.jsonl").write_text(json.dumps({"task": "reach-xyz", "global_step": 0,
                                                   "score": -90.0}) + "\n")  # fmt: skip
    _fake_run(tmp_path / "runs", "reach-xy", "m", [0, 90])
    assert read_run(ref) is None
    (path, *_) = write_learnability([tmp_path / "runs"], tmp_path / "out")
    assert len(path.read_text().splitlines()) == 3  # header, rule, the online run's row
