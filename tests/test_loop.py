"""The one online loop with a real model: resume, the `ccfit train` CLI, bad input, hooks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ccfit.config import TaskRunConfig, TrainConfig
from ccfit.config_base import ConfigError
from ccfit.config_parse import parse_cli, resolve
from ccfit.models.registry import model_class
from ccfit.replay import ReplayBuffer

try:
    from shipped import shipped_models
    from short_episodes import EPISODE_STEPS, ccfit_command, short, smoke_train_argv
except ImportError:  # tests/ imported as a package
    from tests.shipped import shipped_models
    from tests.short_episodes import EPISODE_STEPS, ccfit_command, short, smoke_train_argv


def _run_config(out: Path, steps=120, checkpoint_interval=60, model="tdmpc2") -> TaskRunConfig:
    return resolve(TaskRunConfig, {
        "task": "reach-xy", "preset": "smoke", "seed": 3, "seed_dataset": None,
        "out": str(out), "model": {"type": model, "batch_size": 8},
        "train": short(dict(steps=steps, seed_steps=40, eval_interval=60, eval_episodes=1,
                            checkpoint_interval=checkpoint_interval, buffer_capacity=2_000,
                            device="cpu")),
    })  # fmt: skip


def _params(out: Path) -> dict[str, torch.Tensor]:
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    flat = {f"model.{k}": v for k, v in state["model"].items()}
    flat.update({f"heads.{k}": v for k, v in state["heads"].items()})
    return flat


def test_resume_after_interruption_matches_uninterrupted_run(tmp_path, monkeypatch):
    from ccfit.models.tdmpc2 import TDMPC2
    from ccfit.train import train_single

    full, broken = tmp_path / "full", tmp_path / "broken"
    train_single(_run_config(full), progress=False)

    # Kill the second run mid-way between its checkpoint (step 60) and the end.
    original = TDMPC2.loss
    calls = {"n": 0}

    def dying_loss(self, batch, heads):
        calls["n"] += 1
        if calls["n"] == 45:  # updates start at step 40: this is step ~85
            raise KeyboardInterrupt
        return original(self, batch, heads)

    monkeypatch.setattr(TDMPC2, "loss", dying_loss)
    with pytest.raises(KeyboardInterrupt):
        train_single(_run_config(broken), progress=False)
    monkeypatch.setattr(TDMPC2, "loss", original)
    assert torch.load(broken / "checkpoint.pt", weights_only=False)["task_step"] == 60
    # Written by other versions: a config.json from before `train.demo_fraction` and
    # `resolved_autocast` existed, a checkpoint that states the former at its legacy value.
    # Both are the same run.
    saved = json.loads((broken / "config.json").read_text())
    del saved["train"]["demo_fraction"], saved["resolved_autocast"]
    (broken / "config.json").write_text(json.dumps(saved))
    state = torch.load(broken / "checkpoint.pt", weights_only=False)
    state["train_config"]["demo_fraction"] = 0.0
    torch.save(state, broken / "checkpoint.pt")
    # A run directory moved elsewhere (off a cluster's scratch disk) resumes where it is.
    moved = tmp_path / "elsewhere" / "broken"
    moved.parent.mkdir()
    broken = broken.rename(moved)
    train_single(_run_config(broken), progress=False)
    assert json.loads((broken / "config.json").read_text())["out"] == str(broken)

    a, b = _params(full), _params(broken)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed run diverged"
    rec_a = (full / "metrics.jsonl").read_text().splitlines()
    rec_b = (broken / "metrics.jsonl").read_text().splitlines()
    assert rec_a == rec_b and [json.loads(x)["task_step"] for x in rec_a] == [0, 60, 120]
    # `ccfit compare` reads it so: the same settings, every record reproduced.
    from ccfit.compare import compare_runs

    comparison = compare_runs(full, broken)
    assert comparison.reproduces and comparison.shared == 3 and comparison.settings == {}
    # A different config must not silently reuse the directory.
    with pytest.raises(ConfigError, match=r"different config \(differs in train\.steps\)"):
        train_single(_run_config(broken, steps=60), progress=False)  # fewer than it ran


def test_load_task_run_reads_a_finished_run_back(tmp_path):
    from ccdata.errors import InputError
    from ccfit.train import load_task_run, train_single

    out = tmp_path / "run"
    cfg = _run_config(out)
    train_single(cfg, progress=False)
    loaded = load_task_run(out, "cpu")
    assert loaded.cfg == cfg and loaded.checkpoint["task_step"] == 120
    params = _params(out)
    for prefix, module in (("model", loaded.model), ("heads", loaded.heads)):
        for name, value in module.state_dict().items():
            assert torch.equal(value, params[f"{prefix}.{name}"]), name
    assert not loaded.model.training and not loaded.heads.training
    with pytest.raises(InputError, match="not a run directory"):
        load_task_run(tmp_path / "nothing")
    (out / "config.json").write_text('{"task": "reach-xy",')  # cut short
    for read in (
        lambda: load_task_run(out),
        lambda: parse_cli(TaskRunConfig, ["--config_path", str(out / "config.json")]),
    ):
        with pytest.raises(ConfigError, match="is not a JSON config"):
            read()
    with pytest.raises(ConfigError, match="config file not found"):
        parse_cli(TaskRunConfig, ["--config_path", str(tmp_path / "none.json")])
    with pytest.raises(ConfigError, match="is a folder: give its config.json"):
        parse_cli(TaskRunConfig, ["--config_path", str(out)])
    # a whole record that is not JSON (a kill cuts only the last line, which is mended)
    from ccfit.train.records import RunLogger

    (out / "metrics.jsonl").write_text('{"global_step": 0}\n{"global_step": x}\n')
    with pytest.raises(InputError, match="metrics.jsonl: missing or corrupt .* delete its folder"):
        RunLogger(out).read_evals()


# With the evaluations in a worker, after `make test` (test_parallel covers that worker).
@pytest.mark.parametrize("parallel", ["off", pytest.param("on", marks=pytest.mark.integration)])
def test_stop_score_ends_a_single_task_run_early_and_resumed_it_stays_ended(parallel, tmp_path):
    from ccfit.analysis.learnability import read_run
    from ccfit.train import train_single

    out = tmp_path / "run"
    cfg = _run_config(out, steps=600)
    cfg = resolve(
        TaskRunConfig,
        {
            **cfg.to_dict(),
            "train": {
                **cfg.to_dict()["train"],
                "stop_score": -1e9,
                "stop_evals": 2,  # every score reaches it
                "parallel": parallel,
            },
        },
    )  # evaluations in a worker: the same step ends the task
    train_single(cfg, progress=False)
    records = (out / "metrics.jsonl").read_text()
    # decided at step 120 on the evaluations at 0 and 60; the task's final evaluation at 120
    assert [json.loads(x)["task_step"] for x in records.splitlines()] == [0, 60, 120]
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    assert (state["task_step"], state["finished"]) == (120, True)
    train_single(cfg, progress=False)  # resumed: nothing more to train
    assert (out / "metrics.jsonl").read_text() == records
    assert torch.load(out / "checkpoint.pt", weights_only=False)["task_step"] == 120
    row = read_run(out)  # finished, not cut short, for `ccfit learnability`
    assert row is not None and (row["budget"], row["trained"]) == (600, 120)
    # the same records without the rule that ended them: an unfinished run
    saved = json.loads((out / "config.json").read_text())
    saved["train"]["stop_score"] = None
    (out / "config.json").write_text(json.dumps(saved))
    assert read_run(out) is None


@pytest.mark.parametrize("model", shipped_models())
def test_a_finished_run_extended_to_more_steps_ends_as_the_longer_run(model, tmp_path):
    """`ccfit train` again with a larger --train.steps goes on from the finished run's end;
    a model whose training reads the step budget (PWM's temperature hold) refuses."""
    from ccfit.train import train_single

    extended, full = tmp_path / "extended", tmp_path / "full"
    train_single(_run_config(extended, steps=60, model=model), progress=False)
    if model_class(model).reads_task_budget:
        with pytest.raises(ConfigError, match="cannot be extended to more"):
            train_single(_run_config(extended, steps=120, model=model), progress=False)
        return
    train_single(_run_config(extended, steps=120, model=model), progress=False)
    train_single(_run_config(full, steps=120, model=model), progress=False)
    a, b = _params(full), _params(extended)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), "extension diverged"
    records = (extended / "metrics.jsonl").read_text()
    assert records == (full / "metrics.jsonl").read_text()
    assert [json.loads(x)["task_step"] for x in records.splitlines()] == [0, 60, 120]
    assert json.loads((extended / "config.json").read_text())["train"]["steps"] == 120


def test_an_extended_run_stops_where_the_longer_run_stops(tmp_path):
    """A run that met stop_score only at its last step (where the rule is not tested) ends
    there when extended, as the longer run does."""
    from ccfit.train import train_single

    def config(steps: int) -> TaskRunConfig:
        cfg = _run_config(tmp_path / "run", steps=steps).to_dict()
        train = {**cfg["train"], "stop_score": -1e9, "stop_evals": 2}  # every score meets it
        return resolve(TaskRunConfig, {**cfg, "train": train})

    train_single(config(120), progress=False)  # evaluated at 0 and 60, tested at 60 on one
    records = (tmp_path / "run" / "metrics.jsonl").read_text()
    train_single(config(600), progress=False)  # the 600-step run stops at 120 on 0 and 60
    assert (tmp_path / "run" / "metrics.jsonl").read_text() == records
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert (state["task_step"], state["finished"]) == (120, True)


def test_a_run_killed_after_an_evaluation_resumes_without_logging_it_twice(tmp_path, monkeypatch):
    """Wall-clock checkpoints due at every episode end (25-step episodes end at 25, 50, ...;
    evaluations every 100 steps) and a kill right after the evaluation at step 100 was logged:
    the resumed run logs no evaluation twice and ends as the uninterrupted one (a checkpoint
    at step 100, before its evaluation, made the resumed run log it again). It resumes with
    `--train.parallel` changed (a setting a resumed run may change) and past what the killed
    process left half-written: a checkpoint and a replay file mid-write, a torn last line of
    metrics.jsonl."""
    from ccfit.train import train_single
    from ccfit.train.loop import Trainer

    def config(out: Path, parallel: str = "off") -> TaskRunConfig:
        cfg = _run_config(out, steps=200, checkpoint_interval=1000).to_dict()
        train = {**cfg["train"], "eval_interval": 100, "checkpoint_minutes": 1e-9,
                 "parallel": parallel}  # fmt: skip
        return resolve(TaskRunConfig, {**cfg, "train": train})

    full, broken = tmp_path / "full", tmp_path / "broken"
    train_single(config(full), progress=False)
    original = Trainer._env_step

    def dying(self):
        if self.task_step == 110:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(Trainer, "_env_step", dying)
    with pytest.raises(KeyboardInterrupt):
        train_single(config(broken), progress=False)
    monkeypatch.setattr(Trainer, "_env_step", original)
    records = broken / "metrics.jsonl"
    assert [json.loads(x)["task_step"] for x in records.read_text().splitlines()][-1] == 100
    with records.open("a") as f:
        f.write('{"discounted_return": -1')
    half = [broken / ".checkpoint.pt.x1.tmp", broken / "replay" / ".rows-x.pt.x2.tmp"]
    for path in half:
        path.write_bytes(b"half")
    train_single(config(broken, parallel="on"), progress=False)
    assert records.read_text() == (full / "metrics.jsonl").read_text()
    a, b = _params(full), _params(broken)
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed run diverged"
    assert not any(path.exists() for path in half)


def test_a_run_whose_last_step_was_not_an_evaluation_step_is_not_extended(tmp_path, capsys):
    """A 90-step run evaluated and cut its episode at 90, where a 120-step run (evaluations
    every 60) does not: extending it would not give the longer run, so it is refused."""
    from ccfit.cli import main

    argv = smoke_train_argv(tmp_path / "run", "--train.eval_interval=60", "--train.seed_steps=40",
                            "--train.eval_episodes=1", "--train.buffer_capacity=2000")  # fmt: skip
    assert main([*argv, "--train.steps=90"]) == 0
    saved = (tmp_path / "run" / "config.json").read_text()
    assert main([*argv, "--train.steps=120"]) == 2
    err = capsys.readouterr().err
    assert "holds a run of 90 steps" in err and "cannot be extended" in err and err.count("\n") == 1
    assert (tmp_path / "run" / "config.json").read_text() == saved


@pytest.mark.slow  # two 300-step runs (~60 s); resume equality is covered by the tests below
def test_wall_clock_checkpoints_do_not_change_the_run(tmp_path):
    """A checkpoint written at an episode end (checkpoint_minutes) cuts nothing: the run's
    parameters equal those of a run without it."""
    from ccfit.train import train_single

    plain = _run_config(tmp_path / "plain", steps=300, checkpoint_interval=300)
    timed = _run_config(tmp_path / "timed", steps=300, checkpoint_interval=300)
    timed.train.checkpoint_minutes = 1e-9  # due at every episode end
    train_single(plain, progress=False)
    train_single(timed, progress=False)
    a, b = _params(tmp_path / "plain"), _params(tmp_path / "timed")
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.integration  # the whole smoke preset in two processes (~35 s); in-process CLI runs
# of `ccfit train` are in make test (test_data_loading, test_loop's resume tests)
def test_cli_smoke_run_writes_config_metrics_checkpoint(tmp_path):
    out = tmp_path / "run"
    cmd = ccfit_command(smoke_train_argv(out, "--obs", "state"))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["task"] == "reach-xy" and cfg["model"]["type"] == "tdmpc2"
    assert cfg["model"]["seq_len"] == cfg["model"]["horizon"] + 1 == 4
    assert cfg["model"]["obs_mode"] == cfg["obs"] == "state"
    assert cfg["train"] == {**cfg["train"], **TrainConfig.PRESETS["smoke"]}
    records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    steps = TrainConfig.preset("smoke").steps
    interval = TrainConfig.preset("smoke").eval_interval
    assert [r["global_step"] for r in records] == list(range(0, steps + 1, interval))
    from ccdata.scoring import floor_return

    for r in records:
        assert r["task"] == "reach-xy" and 0.0 <= r["success_rate"] <= 1.0
        assert floor_return() - 1e-6 <= r["discounted_return"] <= 0.0
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ckpt["task_step"] == steps and ckpt["buffer"]["episodes"].shape[0] >= 2
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert "reach-xy step 600" in proc.stdout
    # The saved config runs again as it is: same directory, nothing to redo.
    again = subprocess.run([sys.executable, "-m", "ccfit.cli", "train", "--config_path",
                            str(out / "config.json"), "--quiet"],
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert "reach-xy step 600" in again.stdout


def test_preset_fills_defaults_and_flags_override_them():
    cfg = parse_cli(TaskRunConfig, ["--task", "reach-xz", "--preset", "smoke",
                                    "--model.type=pwm", "--model.router=state",
                                    "--train.steps=900", "--obs", "pixels", "--image-size",
                                    "32"])  # fmt: skip
    assert cfg.model.type == "pwm" and cfg.model.router == "state"
    assert cfg.model.obs_mode == "pixels" and cfg.model.image_size == 32
    assert (
        cfg.train.steps == 900
        and cfg.train.seed_steps == TrainConfig.PRESETS["smoke"]["seed_steps"]
    )
    assert cfg.model.batch_size == 16  # the smoke preset's, not the class default
    back = resolve(TaskRunConfig, json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["train", "--task", "reach-nowhere"], "reach-xy"),
        (["train", "--task", "reach-xy", "--model.type=dreamer9"], "dreamer9"),
        (["train", "--task", "reach-xy", "--preset", "huge"], "valid: smoke, cpu, paper"),
        (["train", "--task", "reach-xy", "--obs", "rgb"], "state"),
        (["train", "--task", "reach-xy", "--train.steps=0"], "train.steps must be >= 1"),
        (
            ["train", "--task", "reach-xy", "--train.episode_steps=0"],
            "train.episode_steps must be >= 1",
        ),
        (
            ["run", "--suite", "Reach", "--train.episode_steps=-5"],
            "train.episode_steps must be >= 1",
        ),
        (["train", "--task", "reach-xy", "--train.steps=many"], "train.steps"),
        (["train", "--task", "reach-xy", "--model.obs_mode=pixels"], "--obs"),
        (["train", "--task", "reach-xy", "--seed-dataset", "/no/such/dir"], "cannot read"),
        (["run", "--suite", "Reach", "--method.type=experts"], "pwm"),
        (["run", "--suite", "Nowhere"], "Reach"),
        (["run", "--suite", "Reach", "--method.type=ewc", "--method.lam=-1"], "lam"),
        (
            ["train", "--task", "reach-xy", "--train.autocast=fp16"],
            "train.autocast must be one of ('off', 'bf16', 'auto')",
        ),
        (["run", "--suite", "Reach", "--train.stop_score=80"], "single-task runs"),
        (["train", "--task", "reach-xy", "--train.stop_evals=0"], "train.stop_evals"),
        (["fly"], "invalid choice"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(argv, needle, capsys, tmp_path):
    from ccfit.cli import main

    try:
        code = main([*argv, "--out", str(tmp_path / "x")] if argv[0] != "fly" else argv)
    except SystemExit as e:  # argparse errors
        code = e.code
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "x").exists(), "bad input must not leave a run directory"


def _evaluator(model):
    from ccfit.train import Evaluator

    return Evaluator(model, {0: "reach-xy"}, seed=0, obs_mode="state", image_size=64,
                     episodes=1, episode_steps=EPISODE_STEPS)  # fmt: skip


class _CountingMethod:
    """A continual method that only counts the hooks the loop calls."""

    wants_retrain_steps = 0

    def __init__(self) -> None:
        self.penalties = self.after_steps = 0
        self.after_tasks: list[int] = []

    def after_task(self, task_index, backbone, task_data) -> None:
        self.after_tasks.append(task_index)

    def penalty(self, backbone, backbone_loss):
        self.penalties += 1
        return 0.0 * sum(p.sum() for p in backbone.parameters())

    def after_step(self, backbone) -> None:
        self.after_steps += 1

    def state_dict(self) -> dict:
        return {}


def test_trainer_calls_continual_hooks_once_per_update():
    from ccdata import make_env
    from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
    from ccfit.train import Trainer

    torch.manual_seed(0)
    cfg = TrainConfig(steps=50, seed_steps=20, eval_interval=50, eval_episodes=1,
                      checkpoint_interval=50, buffer_capacity=1000, device="cpu",
                      episode_steps=EPISODE_STEPS)  # fmt: skip
    model = TDMPC2(
        TDMPC2Config.preset("smoke", batch_size=4, train_ratio=2.0, episode_length=EPISODE_STEPS),
        device="cpu",
    )
    env = make_env("reach-xy", render=False, episode_steps=EPISODE_STEPS)
    method = _CountingMethod()
    buffer = ReplayBuffer(1000)
    state = np.zeros((31, 39), np.float32)
    buffer.add_episode({"state": state}, np.zeros((30, 4), np.float32),
                       np.zeros(30, np.float32), np.zeros(30, np.float32))  # fmt: skip
    before = [p.detach().clone() for p in model.backbone.parameters()]
    trainer = Trainer(env=env, model=model, heads=model.new_heads(), buffer=buffer, config=cfg,
                      seed=0, obs_mode="state", task_id="reach-xy", method=method,
                      evaluator=_evaluator(model), progress=False)  # fmt: skip
    last = trainer.run()
    env.close()
    assert last["task_step"] == 50 and [r["task_step"] for r in trainer.evals] == [0, 50]
    assert trainer.updates == (50 - 20) * 2
    assert method.penalties == method.after_steps == trainer.updates
    assert method.after_tasks == [0]  # the trainer closes its task once
    assert buffer.num_transitions == 30 + 50  # the episode in progress is stored at the end
    after = list(model.backbone.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, after, strict=True))


class _HeldEvaluator:
    """The in-line evaluator with the records of its step-0 evaluation held back until the
    trainer reaches task step `release_at`, as a worker that is still starting holds them;
    `waits`: the task steps at which the loop waited for held records."""

    def __init__(self, inner, release_at: int) -> None:
        self.inner, self.heads, self.release_at = inner, inner.heads, release_at
        self.trainer, self.queue, self.waits = None, [], []

    def submit(self, tasks, *, stage, global_step, task_step) -> None:
        self.inner.submit(tasks, stage=stage, global_step=global_step, task_step=task_step)
        request = {"tasks": list(tasks), "stage": stage, "global_step": global_step,
                   "task_step": task_step}  # fmt: skip
        self.queue.append((request, self.inner.results()))

    def results(self, until=-1) -> list[dict]:
        out = []
        while self.queue:
            request, records = self.queue[0]
            ready = request["global_step"] > 0 or self.trainer.task_step >= self.release_at
            must = until is None or (until >= 0 and request["global_step"] < until)
            if not (ready or must):
                break
            if not ready:
                self.waits.append(self.trainer.task_step)
            out += records
            self.queue.pop(0)
        return out

    @property
    def pending(self) -> list[dict]:
        return [request for request, _ in self.queue]


def _seed_phase_run(out: Path, release_at: int | None):
    """A 180-step run (seed phase 60, evaluations and checkpoints every 60) into `out`, its
    step-0 records held back until `release_at` (None: the in-line evaluator); returns the
    steps its checkpoints were written at, its evaluator and its trainer."""
    from ccdata import make_env
    from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
    from ccfit.train import Trainer

    cfg = TrainConfig(steps=180, seed_steps=60, eval_interval=60, eval_episodes=1,
                      checkpoint_interval=60, buffer_capacity=1000, device="cpu",
                      episode_steps=EPISODE_STEPS)  # fmt: skip
    torch.manual_seed(0)
    model = TDMPC2(TDMPC2Config.preset("smoke", batch_size=4, episode_length=EPISODE_STEPS),
                   device="cpu")  # fmt: skip
    evaluator = _evaluator(model)
    evaluator = evaluator if release_at is None else _HeldEvaluator(evaluator, release_at)
    env = make_env("reach-xy", render=False, episode_steps=EPISODE_STEPS)
    trainer = Trainer(env=env, model=model, heads=model.new_heads(), buffer=ReplayBuffer(1000),
                      config=cfg, seed=0, obs_mode="state", task_id="reach-xy",
                      evaluator=evaluator, run_dir=out, progress=False)  # fmt: skip
    written, real_checkpoint = [], trainer._checkpoint

    def checkpoint() -> None:
        written.append(trainer.task_step)
        real_checkpoint()

    trainer._checkpoint, evaluator.trainer = checkpoint, trainer
    trainer.run()
    env.close()
    return written, evaluator, trainer


@pytest.fixture(scope="module")
def in_line_run(tmp_path_factory):
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # as the tests' own fixture sets it: the same reduction order
    out = tmp_path_factory.mktemp("in-line")
    written, _, trainer = _seed_phase_run(out, None)
    torch.set_num_threads(before)
    return out, written, trainer.evals


@pytest.mark.parametrize("release_at, checkpoints, waits", [(70, [85, 120, 180], []),
                                                            (150, [120, 180], [120])])  # fmt: skip
def test_the_seed_phase_checkpoint_does_not_wait_for_a_starting_evaluator(
        release_at, checkpoints, waits, in_line_run, tmp_path):  # fmt: skip
    """At the end of the run's seed phase (step 60), where the step-0 evaluation may still run
    in a worker that is starting, the checkpoint is put off to the first episode end after its
    records came (85; episodes of 25 steps, cut at 60 and 120), or waits at the next checkpoint
    step (120) when they come later; the run computes what it computes with them in line."""
    written, held, trainer = _seed_phase_run(tmp_path, release_at)
    assert written == checkpoints and held.waits == waits
    plain, plain_written, plain_evals = in_line_run
    assert plain_written == [60, 120, 180] and trainer.evals == plain_evals
    a, b = _params(tmp_path), _params(plain)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("global_offset, burst", [(0, 5), (100, 0)])
def test_pretrain_updates_run_once_on_the_runs_first_task_only(global_offset, burst):
    """`pretrain_updates` run at once when updates first become possible on a fresh model (the
    run's first task, global offset 0); a later task of a curriculum does not repeat them."""
    from ccdata import make_env
    from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
    from ccfit.train import Trainer

    torch.manual_seed(0)
    cfg = TrainConfig(steps=50, seed_steps=20, eval_interval=50, eval_episodes=1,
                      checkpoint_interval=50, buffer_capacity=1000, device="cpu",
                      episode_steps=EPISODE_STEPS)  # fmt: skip
    model = TDMPC2(TDMPC2Config.preset("smoke", batch_size=4, train_ratio=0.5, pretrain_updates=5,
                                       episode_length=EPISODE_STEPS), device="cpu")  # fmt: skip
    env = make_env("reach-xy", render=False, episode_steps=EPISODE_STEPS)
    buffer = ReplayBuffer(1000)
    buffer.add_episode({"state": np.zeros((31, 39), np.float32)}, np.zeros((30, 4), np.float32),
                       np.zeros(30, np.float32), np.zeros(30, np.float32))  # fmt: skip
    method = _CountingMethod()
    trainer = Trainer(env=env, model=model, heads=model.new_heads(), buffer=buffer, config=cfg,
                      seed=0, obs_mode="state", task_id="reach-xy", method=method,
                      evaluator=_evaluator(model), global_offset=global_offset,
                      progress=False)  # fmt: skip
    updates_at: dict[int, int] = {}
    real_update = trainer._update

    def counting_update() -> None:
        updates_at[trainer.task_step] = updates_at.get(trainer.task_step, 0) + 1
        real_update()

    trainer._update = counting_update
    trainer.run()
    env.close()
    # Steps 20..49 add 0.5 each: 15 regular updates, the first at step 21; the burst runs at
    # step 20, where updates first become possible.
    assert trainer.updates == burst + 15 == method.after_steps == sum(updates_at.values())
    assert updates_at.get(20, 0) == burst and updates_at[21] == 1
    assert min(updates_at) == (20 if burst else 21)


@pytest.mark.integration
def test_wandb_offline_logs_the_evaluations_and_resumes_the_same_run(tmp_path):
    """`--log.wandb=true --log.wandb_mode=offline`: every evaluation reaches W&B at its global
    step, the resolved config is the W&B run's config, and running the command again (the
    finished run is resumed) continues the same W&B run; logging settings are not part of the
    run's identity."""
    pytest.importorskip("wandb")
    try:
        from wandb_records import config, history
    except ImportError:  # tests/ imported as a package
        from tests.wandb_records import config, history

    out = tmp_path / "run"
    argv = smoke_train_argv(
        out,
        "--train.steps=100",
        "--train.seed_steps=50",
        "--train.eval_interval=50",
        "--train.checkpoint_interval=50",
        "--log.wandb=true",
        "--log.wandb_mode=offline",
        "--log.tensorboard=false",
    )
    env = {**__import__("os").environ, "WANDB_SILENT": "true"}
    proc = subprocess.run(ccfit_command(argv), capture_output=True, text=True, timeout=300,
                          env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not (out / "tb").exists()
    (log,) = (out / "wandb").glob("offline-run-*/run-*.wandb")
    run_id = (out / "wandb_id").read_text().strip()
    assert log.name == f"run-{run_id}.wandb"
    records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in history(log) if "eval/reach-xy/discounted_return" in r]
    assert [r["_step"] for r in rows] == [r["global_step"] for r in records] == [0, 50, 100]
    assert [r["eval/reach-xy/discounted_return"] for r in rows] == pytest.approx(
        [r["discounted_return"] for r in records]
    )
    logged = config(log)
    assert logged["task"] == "reach-xy" and logged["train"]["steps"] == 100
    # Again, with W&B on or off: the same run (nothing left to train), no config error.
    again = subprocess.run(ccfit_command(argv), capture_output=True, text=True, timeout=300,
                           env=env)  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert (out / "wandb_id").read_text().strip() == run_id
    plain = [a for a in argv if not a.startswith("--log.")]
    assert subprocess.run(ccfit_command(plain), capture_output=True, timeout=300).returncode == 0


def test_wandb_without_credentials_stops_the_run_before_it_trains(tmp_path):
    """`--log.wandb=true` online with no W&B API key: one line naming the way out, exit 2,
    before the first update (it ended in a traceback at the first evaluation)."""
    pytest.importorskip("wandb")
    out = tmp_path / "run"
    argv = smoke_train_argv(out, "--train.steps=100", "--train.seed_steps=50",
                            "--train.eval_interval=50", "--log.wandb=true")  # fmt: skip
    env = {k: v for k, v in __import__("os").environ.items() if not k.startswith("WANDB_")}
    env["HOME"] = str(tmp_path)  # no ~/.netrc
    proc = subprocess.run(ccfit_command(argv), capture_output=True, text=True, timeout=300,
                          env=env)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert "log.wandb: W&B could not start a run: UsageError: No API key" in proc.stderr
    assert "--log.wandb_mode=offline" in proc.stderr
    assert not (out / "metrics.jsonl").exists() and not (out / "checkpoint.pt").exists()


def test_the_memory_check_counts_the_kept_demonstrations():
    """Demonstrations kept beside the ring (`--train.demo_fraction`) count in the memory
    check; the message names what to lower, the demonstrations themselves when they alone
    do not fit."""
    from ccfit.train import build_model
    from ccfit.train.resources import HOST_SHARE, available_host_memory, plan_replay, row_bytes

    def config(capacity: int) -> TaskRunConfig:
        return resolve(TaskRunConfig, {"task": "reach-xy", "preset": "smoke",
                                       "seed_dataset": None,
                                       "train": {"buffer_capacity": capacity}})  # fmt: skip

    model = build_model(config(1000), torch.device("cpu"))
    row = row_bytes(config(1000), model)
    assert plan_replay(config(1000), model, 500).bytes == row * 1500
    # Rows the machine holds; the margins (a fifth of it) outlast what other processes'
    # allocations move free memory by between this read and the check's own.
    fits = int(HOST_SHARE * available_host_memory() // row)
    big = config(int(0.6 * fits))
    with pytest.raises(ConfigError, match=r"\d+ rows and \d+ rows of demonstrations") as e:
        plan_replay(big, model, int(0.6 * fits))  # neither alone is too much: the ring
    assert "lower --train.buffer_capacity to at most" in str(e.value)
    with pytest.raises(ConfigError, match="set --train.demo_fraction=0"):
        plan_replay(config(1000), model, int(1.2 * fits))


def test_a_replay_that_fits_nowhere_is_refused_before_the_run(tmp_path, capsys):
    """`--preset paper --obs pixels` asks for a million 64 px rows (37 GB): on a machine
    without that memory the run stops at once, naming the setting to lower, and leaves no run
    directory."""
    import shutil

    from ccfit.cli import main
    from ccfit.replay_store import disk_rows
    from ccfit.train.resources import ReplayPlan, available_host_memory, check_disk

    out = tmp_path / "x"
    code = main(
        [
            "train",
            "--task",
            "reach-xy",
            "--preset",
            "paper",
            "--obs",
            "pixels",
            "--seed_dataset",
            "null",
            "--train.device=cpu",
            "--out",
            str(out),
        ]
    )
    err = capsys.readouterr().err
    if 36.9e9 < 0.8 * available_host_memory():
        pytest.skip("this machine holds a paper-scale pixel replay")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "lower --train.buffer_capacity to at most" in err and not out.exists()
    free = shutil.disk_usage(tmp_path).free
    row = 10**6
    capacity = free // row  # the ring alone fits; with the file it partly overwrote it does not
    plan = ReplayPlan(row, capacity, 0, torch.device("cpu"))
    with pytest.raises(ConfigError, match="lower --train.buffer_capacity to at most") as err:
        check_disk(plan, tmp_path / "y")
    most = int(str(err.value).split("at most ")[1].split()[0])
    assert disk_rows(most) * row <= free < disk_rows(most + 1) * row
    check_disk(ReplayPlan(row, most, 0, torch.device("cpu")), tmp_path / "y")


def test_a_second_process_on_the_same_run_directory_stops_in_one_line(tmp_path, capsys):
    # Two `ccfit train` processes given one --out would write checkpoints and records over
    # each other; the second stops at once instead, and the first goes on.
    import time

    from ccfit.cli import main

    out = tmp_path / "run"
    argv = smoke_train_argv(out, "--train.steps=3000", "--train.device=cpu")
    first = subprocess.Popen(ccfit_command(argv), stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while not (out / "config.json").exists() and time.monotonic() < deadline:
            assert first.poll() is None, first.stderr.read()
            time.sleep(0.05)
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "is being trained by another process" in err, err
        assert first.poll() is None
    finally:
        first.kill()
        first.communicate()


def test_the_task_end_evaluation_plays_end_eval_episodes_and_changes_nothing_else(tmp_path):
    """`--train.end_eval_episodes 3` with `--train.eval_episodes 1`: the evaluation after the
    task's close plays 3 layouts (3 returns kept), in line as in the evaluation worker; every
    other evaluation and the trained weights are those of the run without it, and config.json
    records the setting."""
    from ccfit.cli import main

    runs = {}
    end3 = ["--train.end_eval_episodes=3"]
    for name, extra in (("plain", []), ("end3", end3),
                        ("worker", [*end3, "--train.parallel=on"])):  # fmt: skip
        out = tmp_path / name
        argv = smoke_train_argv(out, "--train.steps=120", "--train.seed_steps=60",
                                "--train.eval_interval=60", "--train.eval_episodes=1",
                                "--train.buffer_capacity=2000", *extra)  # fmt: skip
        assert main(argv) == 0
        records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
        weights = torch.load(out / "checkpoint.pt", weights_only=False)["model"]
        runs[name] = records, weights, json.loads((out / "config.json").read_text())
    (plain, plain_weights, _), (end3, end3_weights, config) = runs["plain"], runs["end3"]
    assert [r["global_step"] for r in end3] == [0, 60, 120]
    assert [(r["episodes"], len(r["returns"])) for r in end3] == [(1, 1), (1, 1), (3, 3)]
    assert end3[:2] == plain[:2]
    assert all(torch.equal(plain_weights[k], end3_weights[k]) for k in plain_weights)
    assert config["train"]["end_eval_episodes"] == 3
    assert runs["worker"][0] == end3
    assert main(["train", "--task", "reach-xy", "--preset", "smoke",
                 "--train.end_eval_episodes=0"]) == 2  # fmt: skip
