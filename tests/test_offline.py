"""The offline track (`ccfit fit`) end to end on a tiny Reach dataset made here: the score's
anchors (persistence 0, truth 100), the episode split (held-out rows never reach training,
traced through every batch the backbone is fitted on), the metrics recomputed from the records,
resume after an interruption equal to an uninterrupted run, bad input (one line, exit 2), the
pixel path through the CLI, and the report keeping the offline track apart.

One module-scoped fixture generates the dataset (4 episodes per task, 30 steps at most) and
fits it with three methods at smoke size, tracing what the backbone is fitted on.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ccfit.offline.run as OR
from ccdata.record import GenerateConfig, generate
from ccfit import metrics as M
from ccfit.config_parse import resolve
from ccfit.data import load_episodes
from ccfit.models.base import Batch, OpenLoop
from ccfit.offline import OfflineConfig, OfflineCurriculum
from ccfit.offline.data import SPLIT
from ccfit.offline.fit import TaskFitter
from ccfit.offline.score import normalised_score, score_windows
from ccfit.train.cost import read_cost, running_code, running_machine
from ccfit.train.update import backbone_optimizer_state

SUITE = "Reach"
TASKS = ("reach-xy", "reach-xz", "reach-yz", "reach-xyz")
METHODS = ("er", "ewc", "packnet")
OPTIONS = {"er": {"batch_size": 4}, "ewc": {"fisher_batches": 3}, "packnet": {"retrain_steps": 5}}
UPDATES = 20
STATE_KEY = "observation.environment_state"


# ============================================================================ the score


class FakeModel(torch.nn.Module):
    """Predicts from the windows' own rows: `mix` of the truth and (1 - mix) of persistence."""

    def __init__(self, mix: float) -> None:
        super().__init__()
        self.mix, self.device, self.modes = mix, torch.device("cpu"), []

    def open_loop(self, batch: Batch, context: int, horizon: int) -> OpenLoop:
        self.modes.append(self.training)
        x = batch.obs["state"]
        target, last = x[context : context + horizon], x[context - 1]
        predicted = self.mix * target + (1 - self.mix) * last.unsqueeze(0)
        return OpenLoop({"state": predicted}, {"state": target}, {"state": last})


def _walks(n: int = 7, rows: int = 9, still: bool = False) -> Batch:
    x = torch.randn(rows, n, 6, generator=torch.Generator().manual_seed(1)).double().cumsum(0)
    if still:
        x = x[:1].expand(rows, n, 6).clone()
    zeros = torch.zeros(rows, n, 1)
    return Batch({"state": x}, torch.zeros(rows, n, 4), zeros, zeros, zeros, torch.zeros(rows, n))


@pytest.mark.parametrize("mix, expected", [(0.0, 0.0), (1.0, 100.0), (0.5, 75.0)])
def test_persistence_scores_0_and_the_true_next_observations_100(mix, expected):
    """Persistence (x_{t+k} = x_t) is 0, the truth 100; half-way has a quarter of persistence's
    squared error: 75. Chunking the windows changes nothing; scoring runs in eval mode inside
    the method's view and gives the model back in its mode."""
    model = FakeModel(mix)
    entered = []

    @contextlib.contextmanager
    def view():
        entered.append(True)
        yield

    rec = score_windows(model, _walks(), context=3, horizon=5, chunk=3, view=view())
    assert rec["score"] == pytest.approx(expected, abs=1e-9)
    assert rec["scores"] == {"state": pytest.approx(expected, abs=1e-9)}
    assert rec["score_by_step"] == pytest.approx([expected] * 5, abs=1e-9)
    assert rec["windows"] == 7 and len(model.modes) == 3 and not any(model.modes)
    assert entered == [True] and model.training
    whole = score_windows(model, _walks(), context=3, horizon=5, chunk=100)
    assert whole["score"] == pytest.approx(rec["score"], abs=1e-9)
    assert rec["mse"]["state"] == pytest.approx((1 - mix) ** 2 * rec["mse_persistence"]["state"])


def test_worse_than_persistence_is_bounded_and_a_still_task_has_no_score():
    """Twice persistence's error scores -50 and no error can go below -100 (the mirror of
    100 (1 - M/P)), so an untrained model's huge error cannot dominate an integral."""
    assert normalised_score(2.0, 1.0) == -50.0 and normalised_score(1e12, 1.0) > -100.0
    assert normalised_score(0.25, 1.0) == 75.0 and normalised_score(1.0, 1.0) == 0.0
    assert score_windows(FakeModel(-1.0), _walks(), 3, 5, 4)["score"] == pytest.approx(-75.0)
    assert score_windows(FakeModel(0.5), _walks(still=True), 3, 5, 4)["score"] is None
    assert normalised_score(1.0, 0.0) is None


# ============================================================================ the runs


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("offline") / "Reach"
    root, _ = generate(GenerateConfig(SUITE, episodes=2, explore_episodes=1, image_size=32,
                                      max_steps=30, root=root), progress=False)  # fmt: skip
    return root


def _config(dataset: Path, method: str, **top) -> OfflineConfig:
    return resolve(OfflineConfig, {
        "suite": SUITE, "preset": "smoke", "dataset": str(dataset), "model": {"type": "dreamerv3"},
        "method": {"type": method, **OPTIONS.get(method, {})}, **top,
    })  # fmt: skip


def _rows(states) -> set[bytes]:
    return {np.asarray(r, dtype=np.float32).tobytes() for r in np.asarray(states).reshape(-1, 39)}


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    """Each method's run, with every state row the backbone was fitted on (a spy wraps the
    model's `backbone_loss`: the fitting updates, ER's replay, EWC's Fisher batches)."""
    root = tmp_path_factory.mktemp("runs")
    seen: dict[str, set[bytes]] = {}
    updates: dict[str, list[set[int]]] = {}
    real = OR.load_model

    def traced_model(cfg, device):
        model = real(cfg, device)
        loss = model.backbone_loss

        def traced(batch):
            seen[current].update(_rows(batch.obs["state"].detach().cpu().numpy()))
            return loss(batch)

        model.backbone_loss = traced
        after = model.after_backbone_update

        def counted(batch):  # the fitted task's own batches only, one call per update
            updates[current].append(set(batch.task.flatten().tolist()))
            after(batch)

        model.after_backbone_update = counted
        return model

    out = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(OR, "load_model", traced_model)
        for current in METHODS:
            seen[current], updates[current] = set(), []
            cfg = _config(dataset, current)
            result = OfflineCurriculum(cfg, root / current, root / "scratch", progress=False).run()
            out[current] = SimpleNamespace(cfg=cfg, dir=root / current, result=result)
    return SimpleNamespace(root=root, runs=out, seen=seen, updates=updates)


def _split_rows(dataset: Path, split: dict) -> tuple[set[bytes], set[bytes]]:
    """(rows of every training episode, rows of every held-out episode) over all tasks."""
    train, held = set(), set()
    for task, s in split["tasks"].items():
        for ep in load_episodes(dataset, task=task, images=False):
            rows = _rows(ep[STATE_KEY])
            (train if int(ep["episode_index"]) in s["train"] else held).update(rows)
            assert int(ep["episode_index"]) in s["train"] + s["heldout"]
    return train, held


@pytest.mark.parametrize("method", METHODS)
def test_held_out_episodes_never_reach_training(runs, dataset, method):
    """Every state row any backbone loss saw (fitting, ER replay, EWC Fisher, PackNet
    retraining) is a training episode's; none is a held-out episode's."""
    run = runs.runs[method]
    split = json.loads((run.dir / SPLIT).read_text())
    train, held = _split_rows(dataset, split)
    only_held = held - train  # rows a held-out episode shares with none of the training ones
    seen = runs.seen[method]
    assert only_held and seen, "the check could not tell"
    assert not seen & only_held, f"{len(seen & only_held)} held-out rows reached training"
    assert seen <= train
    # The tracer does see held-out rows when they are fed to the backbone loss.
    leak = next(iter(only_held))
    assert leak in _rows(np.frombuffer(leak, dtype=np.float32)[None])


def test_the_split_is_by_episode_seeded_recorded_and_scored_inside_held_out_episodes(runs, dataset):
    splits = [json.loads((r.dir / SPLIT).read_text()) for r in runs.runs.values()]
    assert all(s == splits[0] for s in splits)  # a function of the seed and the dataset
    rows = splits[0]["tasks"]
    assert sorted(rows) == sorted(TASKS)
    for task, s in rows.items():
        episodes = {int(ep["episode_index"]): len(ep["action"])
                    for ep in load_episodes(dataset, task=task, images=False)}  # fmt: skip
        assert not set(s["train"]) & set(s["heldout"])
        assert sorted(s["train"] + s["heldout"]) == sorted(episodes)
        assert len(s["heldout"]) == 1 and s["windows"]
        for episode, start in s["windows"]:
            assert episode in s["heldout"] and start + 7 <= episodes[episode]
    other = OR.make_splits(_config(dataset, "ft", seed=1), str(dataset))
    assert any(other[t].heldout != rows[t]["heldout"] for t in TASKS)
    run = next(iter(runs.runs.values()))
    for where in (run.dir, Path(run.result["scratch_dir"])):  # the reference records it too
        config = json.loads((where / "config.json").read_text())
        assert config["resolved_dataset_meta"]["total_episodes"] == len(
            load_episodes(dataset, images=False)
        )


@pytest.mark.parametrize("method", METHODS)
def test_every_seen_task_is_scored_and_the_metrics_come_from_the_records(runs, method):
    run = runs.runs[method]
    metrics = json.loads((run.dir / "metrics.json").read_text())
    assert metrics == json.loads(json.dumps(run.result))
    assert metrics["track"] == "offline" and metrics["measurement_space"] == "state"
    assert metrics["task_ends"] == [UPDATES * (i + 1) for i in range(4)]
    assert metrics["budget"] == UPDATES
    records = _records(run.dir)
    for rec in records:
        assert rec["track"] == "offline" and rec["windows"] > 0
        assert len(rec["score_by_step"]) == run.cfg.fit.horizon
    scored: dict[tuple[int, int], list[int]] = {}
    for rec in records:
        scored.setdefault((rec["stage"], rec["global_step"]), []).append(rec["task_index"])
    assert len(scored) == 4 * 3  # each stage: its start, its middle, its end
    for (stage, step), tasks in scored.items():
        first = step == stage * UPDATES
        assert tasks == ([stage] if first else list(range(stage + 1))), (stage, step)
    scratch = json.loads((Path(metrics["scratch_dir"]) / "done.json").read_text())
    assert {r["task_index"] for r in scratch} == {3}
    # What it cost, as online: the run's own cost.json, the reference it trained included
    # (a reference has a cost.json of its own only when it was a job of its own: the sweep's).
    cost = json.loads((run.dir / "cost.json").read_text())
    assert cost["segments"] == 1 and 0 < cost["cpu_s"] and 0 < cost["wall_s"]
    assert cost["code"] == [running_code()] and cost["code"][0]["torch"] == torch.__version__
    assert not (Path(metrics["scratch_dir"]) / "cost.json").exists()
    again = M.compute_metrics(records, scratch, 4, UPDATES, key="score")
    for key in ("bwt", "fwt", "end_of_task", "final_per_task", "lopez_paz_bwt"):
        assert again[key] == metrics[key], key


def test_methods_act_through_their_hooks(runs):
    state = {m: torch.load(r.dir / OR.STATE, weights_only=True) for m, r in runs.runs.items()}
    assert all(s["completed"] == 4 for s in state.values())
    er = state["er"]["method"]
    assert sorted(er["kept"]) == [0, 1, 2, 3] and er["memory"]["written"] > 0
    assert state["ewc"]["method"]["fisher"]
    pack = state["packnet"]["method"]
    assert {int(v.max()) for v in pack["owner"].values()} == {3}
    # The model's per-update hook sees each fitting update's batch (PackNet's retraining of
    # every task but the last, which it does not prune, included), of the task being fitted
    # alone; the from-scratch reference fits once, in the first run.
    updates = runs.runs["er"].cfg.fit.updates
    scratch = {"er": updates}
    for name, calls in runs.updates.items():
        retrain = 3 * OPTIONS[name].get("retrain_steps", 0)
        assert len(calls) == 4 * updates + retrain + scratch.get(name, 0), name
        assert all(len(tasks) == 1 for tasks in calls)
    # The runs differ only by the method, and share one from-scratch reference.
    dirs = {r.result["scratch_dir"] for r in runs.runs.values()}
    assert len(dirs) == 1 and len(list((runs.root / "scratch").glob("offline-*"))) == 1


# ============================================================================ resume


@pytest.mark.parametrize("minutes, killed_at", [(None, 15), (1e-9, 10)])
def test_a_resumed_run_equals_an_uninterrupted_one(runs, dataset, tmp_path, monkeypatch, minutes,
                                                   killed_at):  # fmt: skip
    """Interrupted in task 2 five updates after a checkpoint, run again: the same records and
    the same parameters as the fixture's uninterrupted run (PackNet: retraining included).
    With wall-clock checkpoints after every update, interrupted right after the score at update
    10: that score is logged once (a checkpoint before it made the resumed run log it again)."""
    fit = {} if minutes is None else {"fit": {"checkpoint_minutes": minutes}}
    cfg, out = _config(dataset, "packnet", **fit), tmp_path / "run"
    real_step, calls = TaskFitter._step, [0]

    def step(self):
        calls[0] += 1
        if self.task_index == 2 and self.update == killed_at:
            raise KeyboardInterrupt
        real_step(self)

    monkeypatch.setattr(TaskFitter, "_step", step)
    with pytest.raises(KeyboardInterrupt):
        OfflineCurriculum(cfg, out, runs.root / "scratch", progress=False).run()
    ckpt = torch.load(out / "tasks" / "2-reach-yz" / "checkpoint.pt", weights_only=True)
    assert ckpt["update"] == 10 and not (out / "metrics.json").exists()
    monkeypatch.setattr(TaskFitter, "_step", real_step)
    result = OfflineCurriculum(cfg, out, runs.root / "scratch", progress=False).run()
    ref = runs.runs["packnet"]
    # Its own reference where the config differs (checkpoint_minutes): the same records.
    assert {**result, "scratch_dir": None} == {**ref.result, "scratch_dir": None}
    assert _records(out) == _records(ref.dir)
    ours, theirs = (torch.load(d / OR.STATE, weights_only=True) for d in (out, ref.dir))
    for name, value in theirs["model"].items():
        assert torch.equal(ours["model"][name], value), name
    assert not list((out / "tasks").glob("*/checkpoint.pt"))
    # TensorBoard holds each score once, as metrics.jsonl does (re-logging the checkpoint's
    # records at resume wrote them twice).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(out / "tb"))
    events.Reload()
    for task in TASKS:
        steps = [e.step for e in events.Scalars(f"offline/{task}/score")]
        expected = [r["global_step"] for r in _records(out)
                    if r["task"] == task and r["score"] is not None]  # fmt: skip
        assert sorted(steps) == sorted(expected), task


class _Stopped(Exception):
    """Raised by the test's `_save` spy to stop a run between tasks."""


def test_kept_optimiser_state_crosses_tasks_and_a_stop_between_them(runs, dataset, tmp_path,
                                                                    monkeypatch):  # fmt: skip
    """`--fit.keep_backbone_optimizer`: each task's optimiser starts from the state where the
    last task left it, and a run stopped between tasks resumes to the uninterrupted result
    (the state is saved with the curriculum's); the from-scratch reference is unaffected."""
    cfg = _config(dataset, "ewc", fit={"keep_backbone_optimizer": True})
    started, ended = [], []
    real_run, real_save = TaskFitter.run, OR.OfflineCurriculum._save

    def run(self):
        started.append(backbone_optimizer_state(self.optim, self.model.backbone))
        records = real_run(self)
        ended.append(backbone_optimizer_state(self.optim, self.model.backbone))
        return records

    def save_then_stop(self, completed, *args):
        real_save(self, completed, *args)
        if completed == 2:
            raise _Stopped

    monkeypatch.setattr(TaskFitter, "run", run)
    scratch = runs.root / "scratch"
    whole = OfflineCurriculum(cfg, tmp_path / "whole", scratch, progress=False).run()
    assert len(started) == len(TASKS) and started[0] == {} and ended[0]
    for before, after in zip(started[1:], ended[:-1], strict=True):
        assert before.keys() == after.keys()
        assert all(torch.equal(before[n][k], v) for n in after for k, v in after[n].items())
    # What it changes: the run without it (the fixture's) differs from the first update of
    # the second task on.
    assert _records(tmp_path / "whole") != _records(runs.runs["ewc"].dir)
    assert whole["scratch_dir"] == runs.runs["ewc"].result["scratch_dir"]
    monkeypatch.setattr(OR.OfflineCurriculum, "_save", save_then_stop)
    with pytest.raises(_Stopped):
        OfflineCurriculum(cfg, tmp_path / "stopped", scratch, progress=False).run()
    monkeypatch.setattr(OR.OfflineCurriculum, "_save", real_save)
    assert OfflineCurriculum(cfg, tmp_path / "stopped", scratch, progress=False).run() == whole
    assert _records(tmp_path / "stopped") == _records(tmp_path / "whole")


# ============================================================================ bad input


@pytest.mark.parametrize("argv, needle", [
    (["--dataset", "{empty}"], "cannot read LeRobot dataset"),
    (["--model.type=tdmpc2"], "own latent space"),
    (["--model.type=pwm", "--method.type=experts"], "own latent space"),
    (["--fit.updates=15"], "multiple of fit.score_interval"),
    (["--fit.holdout=1"], "fit.holdout"),
    (["--fit.horizon=500"], "no held-out episode has"),
    (["--suite", "Nope"], "valid suites"),
    (["--obs", "pixels", "--encoder", "frozen:/missing"], "not found"),
    (["--method.type=experts"], "needs a model offering experts"),
])  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(argv, needle, dataset, tmp_path, capsys):
    from ccfit.cli import main

    (tmp_path / "empty").mkdir()
    argv = [a.format(empty=tmp_path / "empty") for a in argv]
    if "--dataset" not in argv:
        argv += ["--dataset", str(dataset)]
    code = main(["fit", "--suite", SUITE, "--preset", "smoke", "--out", str(tmp_path / "x"),
                 *argv])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err and not (tmp_path / "x").exists()


def test_no_local_dataset_is_one_line_naming_the_command(tmp_path, capsys, monkeypatch):
    import ccdata.settings
    from ccfit.cli import main

    monkeypatch.setattr(ccdata.settings, "suite_dataset_root", lambda suite: tmp_path / "none")
    code = main(["fit", "--suite", SUITE, "--preset", "smoke", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "ccdata generate --suite Reach" in err and not (tmp_path / "x").exists()


# ============================================================================ CLI, report


def test_cli_fits_pixels_and_the_report_keeps_the_track_apart(runs, dataset, tmp_path, capsys):
    from ccfit.cli import main
    from ccfit.report.runs import find_runs

    out = tmp_path / "pixels"
    code = main(["fit", "--suite", SUITE, "--preset", "smoke", "--obs", "pixels",
                 "--image_size", "32", "--dataset", str(dataset), "--out", str(out),
                 "--scratch-root", str(tmp_path / "scratch"), "--quiet"])  # fmt: skip
    printed = capsys.readouterr().out
    assert code == 0 and "offline (pixels+proprio)" in printed and str(out) in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["measurement_space"] == "pixels+proprio"
    assert set(_records(out)[0]["scores"]) == {"pixels", "proprio"}

    report = tmp_path / "report"
    assert main(["report", str(runs.root), str(out), "--out", str(report)]) == 0
    table = (report / "table_dreamerv3-offline.md").read_text()
    assert "Offline track" in table and "persistence" in table and "| er BWT |" in table
    assert list(report.glob("curves_dreamerv3-offline_Reach_er*.png"))
    summary = json.loads((report / "summary.json").read_text())
    assert all(v["track"] == "offline" for v in summary.values())
    found = {r.path: r for r in find_runs([runs.root])}
    assert {r.track for r in found.values()} == {"offline"}
    assert {r.backbone for r in found.values()} == {"dreamerv3-offline"}


def test_fit_autocast_runs_the_updates_in_bf16_and_is_recorded(dataset, tmp_path, capsys):
    """`--fit.autocast`, as `--train.autocast` online: resolved once, recorded as
    `resolved_autocast`, the updates under bf16 autocast (the scores stay finite)."""
    from ccfit.cli import main

    out = tmp_path / "bf16"
    code = main(["fit", "--suite", SUITE, "--preset", "smoke", "--fit.autocast=bf16",
                 "--fit.device=cpu", "--dataset", str(dataset), "--out", str(out),
                 "--scratch-root", str(tmp_path / "scratch"), "--quiet"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    saved = json.loads((out / "config.json").read_text())
    assert saved["fit"]["autocast"] == "bf16" and saved["resolved_autocast"] == "bf16"
    assert saved["resolved_device"] == "cpu"
    assert all(r["score"] is None or np.isfinite(r["score"]) for r in _records(out))


# ============================================================================ sweep


def test_sweep_track_offline_expands_fit_runs_and_runs_their_jobs(dataset, tmp_path, capsys):
    """`ccfit sweep --track offline` plans `ccfit fit` runs sharing one offline from-scratch
    reference; its jobs (called here in-process, as the local pool and SLURM call them) train
    them and the report job reports them on the offline track."""
    from ccfit.cli import main
    from ccfit.sweep import Grid, ReportJob, RunJob, ScratchJob, expand
    from ccfit.sweep.grid import write_record
    from ccfit.tracks import track_of

    root = tmp_path / "sweep"
    common = ["--suites", SUITE, "--methods", "ft,ewc", "--preset", "smoke", "--out", str(root),
              "--dataset", str(dataset)]  # fmt: skip
    assert main(["sweep", "--track", "offline", *common, "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "Reach-dreamerv3-ewc-state-smoke-s0-offline" in printed
    assert "scratch/offline-Reach-dreamerv3-state-smoke-s0-" in printed
    assert main(["sweep", "--track", "offline", "--models", "tdmpc2", *common]) == 2
    assert "own latent space" in capsys.readouterr().err and not root.exists()

    grid = Grid((SUITE,), ("dreamerv3",), ("ft", "ewc"), (0,), "smoke",
                ("--dataset", str(dataset)), (), "offline")  # fmt: skip
    sweep = expand(grid, root)
    assert all(track_of(r.config).name == "offline" and r.name.endswith("-offline")
               for r in sweep.runs)  # fmt: skip
    (key,) = {r.scratch_key for r in sweep.runs}
    write_record(sweep, [])
    ScratchJob()(sweep.scratch_configs()[key], str(sweep.scratch_dir(key)), [], sweep.code)
    for run in sweep.runs:
        summary = RunJob()(run.config, str(sweep.run_dir(run)), str(root / "scratch"), key, [],
                           sweep.code)  # fmt: skip
        assert summary["method"] == run.config["method"]["type"]
    status = ReportJob()(str(root), [], sweep.code)
    assert not status["missing"] and "table_dreamerv3-offline.md" in status["report"]
    # The reference's job recorded its cost, which the report's cost.md counts once, beside
    # the runs' (each of which trained no reference).
    reference = read_cost(sweep.scratch_dir(key))
    assert reference["segments"] == 1 and reference["machines"] == [running_machine()]
    cost_md = (root / "report" / "cost.md").read_text()
    assert "| dreamerv3-offline | Reach | ft | 1 |" in cost_md
    assert f"| dreamerv3-offline | Reach | 1 | {reference['cpu_s'] / 3600:.2f} |" in cost_md
