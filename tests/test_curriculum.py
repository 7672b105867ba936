"""Algorithm 1 end to end on a real suite (Grasp, 3 tasks) at smoke size, for ft, er, ewc and
packnet: metrics, evaluation records, stored heads, the shared from-scratch reference, PackNet's
frozen weights, ER's kept fraction, EWC's anchor, no data leakage between tasks, resume after
SIGKILL, CLI errors, `ccfit report` and the results notebook.

One module-scoped fixture runs the four curricula once (about 100 s on a loaded 2-core machine;
evaluation episodes dominate). Spies wrap the real classes and functions (they record what they
see and call through); nothing is mocked.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ccfit.curriculum as C
import ccfit.train.evaluate as E
import ccfit.train.run as R
from ccdata.suites import get_suite
from ccfit.config import CurriculumConfig
from ccfit.config_parse import parse_cli, resolve
from ccfit.curriculum import Curriculum
from ccfit.io import derived_seed
from ccfit.train import CONFIG, METRICS, build_model, resolved_config
from ccfit.train.update import backbone_optimizer_state

try:
    from metrics_by_hand import bwt_by_hand
    from shipped import shipped_models
    from short_episodes import ccfit_command
    from stage_ends import assert_stage_ends_are_the_metrics
except ImportError:  # tests/ imported as a package
    from tests.metrics_by_hand import bwt_by_hand
    from tests.shipped import shipped_models
    from tests.short_episodes import ccfit_command
    from tests.stage_ends import assert_stage_ends_are_the_metrics

SUITE = "Grasp"
TASKS = ("pick-cube", "place-cube", "pnp-cube")
METHODS = ("ft", "er", "ewc", "packnet")
STEPS, EVAL = 100, 100
EPISODE_STEPS = 50
"""Longer than the other tests' short episodes: at 25 steps no Grasp task scores above 0 by
the end of its 100-step stage, and BWT (which counts the tasks learnt) would be vacuous."""
TRAIN = {"steps": STEPS, "seed_steps": 50, "eval_interval": EVAL, "checkpoint_interval": 50,
         "episode_steps": EPISODE_STEPS}  # fmt: skip
OPTIONS = {
    "ft": {},
    "er": {"batch_size": 16},
    "ewc": {"fisher_batches": 4},
    "packnet": {"retrain_steps": 20},
}
NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "results.ipynb"


def _config(method: str) -> CurriculumConfig:
    return resolve(CurriculumConfig, {
        "suite": SUITE, "preset": "smoke", "seed_dataset": None, "train": dict(TRAIN),
        "method": {"type": method, **OPTIONS[method]},
    })  # fmt: skip


def _cli_argv(method: str, out: Path, scratch_root: Path) -> list[str]:
    argv = ["run", "--suite", SUITE, f"--method.type={method}", "--preset", "smoke",
            "--seed_dataset", "null", "--out", str(out), "--scratch-root", str(scratch_root),
            "--quiet"]  # fmt: skip
    argv += [f"--train.{k}={v}" for k, v in TRAIN.items()]
    argv += [f"--method.{k}={v}" for k, v in OPTIONS[method].items()]
    return argv


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / METRICS).read_text().splitlines() if x.strip()]


@dataclass
class Seen:
    """What the spies saw during one method's curriculum."""

    trainers: list = field(default_factory=list)
    """Every Trainer built (the curriculum's tasks, then the scratch reference if trained)."""
    buffers: list = field(default_factory=list)
    """Every replay buffer built."""
    evals: list = field(default_factory=list)
    """(env task id, heads, heads trainable?, heads in train mode?) per task evaluation."""
    saves: list = field(default_factory=list)
    """Per `curriculum.pt` write: completed tasks, backbone parameters, method and heads states."""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("curriculum")
    current: list[Seen] = []

    class SpyBuffer(R.ReplayBuffer):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.added: list[tuple[int, np.ndarray]] = []
            current[-1].buffers.append(self)

        def add_episode(self, obs, action, reward, terminated, task=0) -> None:
            self.added.append((int(task), np.array(obs["state"][0])))
            super().add_episode(obs, action, reward, terminated, task=task)

    class SpyTrainer(C.Trainer):
        def __init__(self, **kwargs) -> None:
            super().__init__(**kwargs)
            current[-1].trainers.append(self)

        def run(self, wait: bool = True) -> dict | None:
            self.returned = super().run(wait)
            return self.returned

    real_play, real_save = E.play_episodes, Curriculum._save

    def spy_play(envs, model, heads, **kwargs):
        trainable = any(p.requires_grad for p in heads.parameters())
        current[-1].evals.append((envs[0].task_id, heads, trainable, heads.training))
        return real_play(envs, model, heads, **kwargs)

    def spy_save(self, completed, model, method, backbone_optim, extra):
        current[-1].saves.append({
            "completed": completed,
            "backbone": {n: p.detach().clone() for n, p in model.backbone.named_parameters()},
            "method": copy.deepcopy(method.state_dict()),
            "heads": copy.deepcopy(extra["heads"]),
        })  # fmt: skip
        real_save(self, completed, model, method, backbone_optim, extra)

    out = {}
    done_mtimes = []
    start = time.monotonic()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(R, "ReplayBuffer", SpyBuffer)
        mp.setattr(C, "Trainer", SpyTrainer)
        mp.setattr(R, "Trainer", SpyTrainer)  # the scratch reference's
        mp.setattr(E, "play_episodes", spy_play)
        mp.setattr(Curriculum, "_save", spy_save)
        for method in METHODS:
            current.append(Seen())
            cfg = _config(method)
            result = Curriculum(cfg, root / method, root / "scratch", progress=False).run()
            done_mtimes.append((Path(result["scratch_dir"]) / "done.json").stat().st_mtime_ns)
            out[method] = SimpleNamespace(cfg=cfg, dir=root / method, result=result,
                                          seen=current[-1])  # fmt: skip
    wall = time.monotonic() - start
    print(f"\ncurriculum fixture: {len(METHODS)} methods in {wall:.0f} s")
    return SimpleNamespace(root=root, scratch_root=root / "scratch", runs=out,
                           done_mtimes=done_mtimes, wall=wall)  # fmt: skip


def _final_model(run):
    """The model and method state of a finished run, rebuilt from its curriculum.pt."""
    state = torch.load(run.dir / C.STATE, map_location="cpu", weights_only=False)
    model = build_model(run.cfg, torch.device("cpu"))
    model.load_state_dict(state["model"])
    return model, state


# ============================================================================ metrics


@pytest.mark.parametrize("method", METHODS)
def test_each_method_writes_metrics_and_resolved_config(runs, method):
    run = runs.runs[method]
    metrics = json.loads((run.dir / C.METRICS_JSON).read_text())
    assert metrics == json.loads(json.dumps(run.result))
    assert (metrics["suite"], metrics["method"], metrics["model"]) == (SUITE, method, "tdmpc2")
    assert metrics["task_ends"] == [STEPS, 2 * STEPS, 3 * STEPS] and metrics["budget"] == STEPS

    # Every metric, recomputed from the evaluation records it comes from.
    recs = _records(run.dir)

    def score(task, stage, step):
        (r,) = [r for r in recs if (r["task_index"], r["stage"], r["global_step"])
                == (task, stage, step)]  # fmt: skip
        return r["normalized_return"]

    final = [score(i, 2, 3 * STEPS) for i in range(3)]
    end = [score(i, i, (i + 1) * STEPS) for i in range(3)]  # C_i, after the method closed i
    per_task = bwt_by_hand(recs, 3, STEPS, EVAL)
    assert per_task, "no task learnt: BWT would be vacuous here"
    assert metrics["bwt_per_task"] == pytest.approx(per_task)
    assert metrics["bwt"] == pytest.approx(np.mean(list(per_task.values())))
    assert set(metrics["bwt_excluded"]) == {"0", "1"} - set(per_task)
    assert metrics["final_per_task"] == pytest.approx(final)
    assert metrics["end_of_task"] == pytest.approx(end)
    lopez = np.mean([final[i] - end[i] for i in range(2)])
    assert metrics["lopez_paz_bwt"] == pytest.approx(lopez)
    assert metrics["cw_forgetting"] == pytest.approx(-lopez)
    # FWT: composition task from its start vs the shared scratch curve (both at 0 and 100).
    scratch = json.loads((Path(metrics["scratch_dir"]) / "done.json").read_text())
    scr = {r["task_step"]: r["normalized_return"] for r in scratch}
    seq = {0: score(2, 2, 2 * STEPS), STEPS: score(2, 2, 3 * STEPS)}
    assert metrics["fwt"] == pytest.approx((seq[0] - scr[0] + seq[STEPS] - scr[STEPS]) / 2)
    assert np.isfinite(metrics["cw_forward_transfer"])

    cfg = json.loads((run.dir / CONFIG).read_text())
    assert cfg == json.loads(json.dumps(resolved_config(run.cfg, SUITE)))
    assert cfg["resolved_device"] == "cpu" and cfg["render"]["image_size"] == 64
    assert cfg["train"]["autocast"] == "off" and cfg["resolved_autocast"] == "off"
    assert cfg["train"]["steps"] == STEPS and cfg["train"]["eval_interval"] == EVAL
    assert cfg["model"]["batch_size"] == 16  # the smoke preset under the overrides
    assert cfg["model"]["latent_dim"] == 32 and cfg["resolved_seed_dataset"] is None
    assert cfg["method"] == {**cfg["method"], "type": method, **OPTIONS[method]}
    # The reference records what its seed dataset held, as the run does (here: none).
    reference = json.loads((Path(metrics["scratch_dir"]) / CONFIG).read_text())
    assert reference["resolved_seed_dataset_meta"] is None is cfg["resolved_seed_dataset_meta"]
    # A finished run leaves no per-task trainer checkpoint behind.
    assert not list((run.dir / "tasks").glob("*/checkpoint.pt"))


@pytest.mark.parametrize("method", METHODS)
def test_every_seen_task_is_evaluated_at_every_eval_point(runs, method):
    recs = _records(runs.runs[method].dir)
    # At a stage's first step only its own task: the others were evaluated at that global
    # step when the previous stage ended.
    expected = sorted(
        (j, stage, g)
        for stage in range(3)
        for g in range(stage * STEPS, (stage + 1) * STEPS + 1, EVAL)
        for j in (range(stage + 1) if g > stage * STEPS else [stage])
    )
    assert sorted((r["task_index"], r["stage"], r["global_step"]) for r in recs) == expected
    for r in recs:
        assert r["global_step"] % EVAL == 0
        assert r["task"] == TASKS[r["task_index"]]
        own = r["task_index"] == r["stage"]
        assert r["task_step"] == (r["global_step"] - r["stage"] * STEPS if own else None)
        assert r["normalized_return"] is not None and 0.0 <= r["success_rate"] <= 1.0
        assert r["episodes"] == 1
    # Logged in training order: stages and global steps never go back.
    order = [(r["stage"], r["global_step"]) for r in recs]
    assert order == sorted(order)
    # Task 0 is evaluated through stage 2 (with its stored heads, see the next test).
    assert {r["global_step"] for r in recs if r["task_index"] == 0 and r["stage"] == 2} == {
        3 * STEPS
    }


@pytest.mark.parametrize("method", METHODS)
def test_earlier_tasks_are_evaluated_with_their_stored_heads(runs, method):
    run = runs.runs[method]
    seen = run.seen
    trainers = [t for t in seen.trainers if t.run_dir.parent == run.dir / "tasks"]
    assert [t.task_id for t in trainers] == list(TASKS)
    # Each task is evaluated at its end; the curriculum does not wait for that evaluation
    # (the next task trains meanwhile), so its trainers return nothing.
    records = _records(run.dir)
    for t in trainers:
        own = [r for r in records if r["task_index"] == r["stage"] == t.task_index]
        assert own[-1]["task_step"] == STEPS and t.returned is None
    # The curriculum's evaluations come before the scratch run's.
    scratch = 2 if method == METHODS[0] else 0
    assert len(seen.evals) == len(records) + scratch
    earlier = [(e, r) for e, r in zip(seen.evals, records, strict=False)
               if r["task_index"] < r["stage"]]  # fmt: skip
    assert len(earlier) == 1 + 2  # task 0 at stage 1's end; tasks 0, 1 at stage 2's end
    for (env_task, heads, trainable, training), r in earlier:
        assert env_task == r["task"]
        assert heads is trainers[r["task_index"]].heads, "not the task's own (stored) heads"
        assert not trainable and not training, "stored heads must be frozen, in eval mode"
    # Stored heads never change after their task.
    final = torch.load(run.dir / C.STATE, map_location="cpu", weights_only=False)["heads"]
    assert [s["completed"] for s in seen.saves] == [1, 2, 3]
    for j in range(3):
        after_j = seen.saves[j]["heads"][j]
        assert all(torch.equal(after_j[k], final[j][k]) for k in after_j)


def test_scratch_reference_is_trained_once_and_shared(runs):
    dirs = {run.result["scratch_dir"] for run in runs.runs.values()}
    assert len(dirs) == 1
    (scratch_dir,) = dirs
    assert Path(scratch_dir).is_absolute()
    assert Path(scratch_dir).parent == runs.scratch_root.resolve()
    scratch_trainers = [
        (m, t) for m, run in runs.runs.items() for t in run.seen.trainers
        if t.run_dir == Path(scratch_dir)
    ]  # fmt: skip
    assert [(m, t.task_id, t.task_index) for m, t in scratch_trainers] == [("ft", "pnp-cube", 2)]
    assert len(set(runs.done_mtimes)) == 1, "a later run rewrote the shared scratch reference"
    done = json.loads((Path(scratch_dir) / "done.json").read_text())
    assert [(r["task"], r["global_step"]) for r in done] == [("pnp-cube", 0), ("pnp-cube", STEPS)]
    assert not (Path(scratch_dir) / "checkpoint.pt").exists()


# ========================================================================= the methods


def test_packnet_keeps_finished_tasks_weights_bit_identical(runs):
    run = runs.runs["packnet"]
    model, state = _final_model(run)
    final = dict(model.backbone.named_parameters())
    owner_end = state["method"]["owner"]
    assert owner_end and all((o >= 0).all() for o in owner_end.values()), "last task owns the rest"
    for t, snap in enumerate(run.seen.saves[:2]):
        owner = snap["method"]["owner"]
        for name, own in owner.items():
            mine = own == t
            n_free = int((own == t).sum() + (own == -1).sum())
            # keep_fraction 0.25 of the entries still free before task t
            assert int(mine.sum()) == round(0.25 * n_free), name
            assert torch.equal(final[name].detach()[mine], snap["backbone"][name][mine]), (
                f"{name}: weights owned by task {t} changed after task {t}"
            )
            assert torch.equal(owner_end[name][mine], own[mine])
    # Biases and other shared parameters are frozen with task 0.
    shared = [n for n in final if n not in owner_end]
    assert shared
    for name in shared:
        assert torch.equal(final[name].detach(), run.seen.saves[0]["backbone"][name]), name
    # Not vacuous: the entries left free after task 0 did train in tasks 1 and 2.
    moved = sum(
        int((final[n].detach() != run.seen.saves[0]["backbone"][n])[o == -1].sum())
        for n, o in run.seen.saves[0]["method"]["owner"].items()
    )
    assert moved > 0


def test_er_keeps_the_stated_fraction_of_each_task(runs):
    run = runs.runs["er"]
    trainers = [t for t in run.seen.trainers if t.run_dir.parent == run.dir / "tasks"]
    state = torch.load(run.dir / C.STATE, map_location="cpu", weights_only=False)["method"]
    fraction, seq_len = 0.05, run.cfg.model.seq_len  # ER's default; windows of the model's
    assert sorted(state["kept"]) == [0, 1, 2]
    for i, trainer in enumerate(trainers):
        n = trainer.buffer.num_transitions
        assert n > 0 and len(state["kept"][i]) == round(fraction * n / (seq_len - 1))
        assert len(set(state["kept"][i].tolist())) == len(state["kept"][i])
    tasks = state["memory"]["rows"]["task"]  # one per row; a kept window is seq_len rows
    counts = {i: int((tasks == i).sum()) // seq_len for i in range(3)}
    assert counts == {i: len(state["kept"][i]) for i in range(3)} and counts[0] > 0
    # After task 0 only task 0 was in memory (a later task never enters an earlier replay).
    after_0 = run.seen.saves[0]["method"]["memory"]["rows"]["task"]
    assert set(after_0.tolist()) == {0}


def test_ewc_anchors_at_the_last_task_and_penalty_grows_with_drift(runs):
    from ccfit.continual import make_method

    run = runs.runs["ewc"]
    model, state = _final_model(run)
    method = make_method(run.cfg.method, num_tasks=3)
    method.load_state_dict(state["method"])
    assert float(method.penalty(model.backbone, model.backbone_loss).detach()) == 0.0
    # Fisher accumulates over tasks (decay 1): never smaller than after the previous task.
    fishers = [s["method"]["fisher"] for s in run.seen.saves]
    for before, after in zip(fishers, fishers[1:], strict=False):
        assert all((after[n] >= before[n]).all() for n in before)
    assert sum(float(f.sum()) for f in fishers[-1].values()) > 0
    penalties = []
    for scale in (1e-3, 2e-3):
        with torch.no_grad():
            for name, p in model.backbone.named_parameters():
                if name in method.anchor:
                    p.copy_(method.anchor[name] + scale)
        penalties.append(float(method.penalty(model.backbone, model.backbone_loss).detach()))
    assert 0 < penalties[0] < penalties[1]
    assert penalties[1] == pytest.approx(4 * penalties[0], rel=1e-3)  # quadratic in the drift


# ============================================================================ leakage


@pytest.mark.parametrize("method", METHODS)
def test_each_task_trains_only_on_its_own_env_and_data(runs, method):
    from ccdata.env import make_env
    from ccfit.obs import obs_to_arrays

    run = runs.runs[method]
    trainers = [t for t in run.seen.trainers if t.run_dir.parent == run.dir / "tasks"]
    buffers = [t.buffer for t in trainers]
    assert len({id(b) for b in buffers}) == 3, "each task gets a fresh replay buffer"
    firsts = []
    for i, (trainer, buffer) in enumerate(zip(trainers, buffers, strict=True)):
        assert trainer.env.task_id == TASKS[i] and trainer.task_index == i
        assert buffer.added and {t for t, _ in buffer.added} == {i}, (
            f"buffer of task {i} holds episodes of tasks {sorted({t for t, _ in buffer.added})}"
        )
        # Its first episode starts from task i's own training layout.
        env = make_env(TASKS[i], render=False)
        obs, _ = env.reset(seed=derived_seed(0, 0, 0, i))
        env.close()
        assert np.array_equal(buffer.added[0][1], obs_to_arrays(obs, "state")["state"])
        firsts.append(buffer.added[0][1])
    assert not np.array_equal(firsts[0], firsts[2])  # the check can tell tasks apart


# ============================================================================= resume


@pytest.mark.integration
def test_killed_run_resumes_to_the_uninterrupted_result(runs, tmp_path):
    """SIGKILL a `ccfit run` once task 1 has a checkpoint (task 0 finished), rerun the same
    command, and compare with the fixture's uninterrupted run of the same seed."""
    method = "packnet"
    out = tmp_path / "killed"
    cmd = ccfit_command(_cli_argv(method, out, runs.scratch_root), EPISODE_STEPS)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    ckpt = out / "tasks" / f"1-{TASKS[1]}" / "checkpoint.pt"
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be killed"
        assert ckpt.exists(), "no task checkpoint within 300 s"
        proc.kill()  # SIGKILL: no cleanup runs
    finally:
        proc.kill()
        proc.communicate()
    state = torch.load(out / C.STATE, map_location="cpu", weights_only=False)
    assert state["completed"] == 1 and not (out / C.METRICS_JSON).exists()
    # As if killed between saving task 0 and removing its folder: the resumed run removes it.
    leftover = out / "tasks" / f"0-{TASKS[0]}"
    leftover.mkdir()
    (leftover / "checkpoint.pt").write_bytes(b"task 0's")

    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    ref = runs.runs[method].dir
    for name in (C.METRICS_JSON, CONFIG):
        ours, theirs = (json.loads((d / name).read_text()) for d in (out, ref))
        ours.pop("out", None), theirs.pop("out", None)  # the CLI run names its directory
        assert ours == theirs, name
    assert _records(out) == _records(ref)
    assert not list((out / "tasks").glob("*/checkpoint.pt")) and not leftover.exists()
    assert len(set(runs.done_mtimes)) == 1
    done_json = Path(runs.runs[method].result["scratch_dir"]) / "done.json"
    assert done_json.stat().st_mtime_ns == runs.done_mtimes[0], "scratch retrained"


# ================================================================================ CLI


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--suite", "Nope"], "valid suites: Reach, Grasp"),
        (["--suite", SUITE, "--method.type=nope"], "nope"),
        (["--suite", SUITE, "--method.type=experts", "--model.type=tdmpc2"], "pwm"),
        (["--suite", SUITE, "--model.router=state"], "router"),
        (["--suite", SUITE, "--model.type=pwm", "--model.router=latent"], "router"),
        (["--suite", SUITE, "--encoder", "frozen:/missing", "--obs", "pixels"], "not found"),
        (["--suite", SUITE, "--encoder", "frozen:/missing"], "needs --obs pixels"),
        (["--suite", SUITE, "--method.type=ewc", "--method.lamda=1"], "lamda"),
        (["--suite", SUITE, "--method", "packnet"], "chosen with --method.type=packnet"),
        (["--suite", SUITE, "--model=pwm"], "chosen with --model.type=pwm"),
        (["--suite", SUITE, "--obs", "rgb"], "--obs must be one of ('state', 'pixels'), got 'rgb'"),
        (["--suite", SUITE, "--train.steps=150"], "multiple of eval_interval"),
        (["--suite", SUITE, "--train.steps=abc"], "train.steps"),
        (["--suite", SUITE, "--model.lr=fast"], "model.lr"),
        (["--suite", "BinPnP", "--model.type=pwm", "--model.max_tasks=3"], "max_tasks=4"),
        (["--suite", SUITE, "--seed=-1"], "seed must be in [0, 2**31), got -1"),
        (["--suite", SUITE, "--model.train_ratio=inf"], "train_ratio must be finite, got inf"),
        (["--suite", SUITE, "--method.type=ewc", "--method.lam=nan"], "lam must be finite"),
        (
            ["--suite", SUITE, "--method.type=packnet", "--method.keep_fraction=1.5"],
            "keep_fraction",
        ),
    ],
)
def test_cli_run_bad_input_exits_2_with_one_line(argv, needle, capsys, tmp_path):
    from ccfit.cli import main

    try:
        code = main(["run", *argv, "--out", str(tmp_path / "x"), "--preset", "smoke"])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "x").exists(), "bad input must not leave a run directory"


def test_an_out_that_is_a_file_is_one_line(tmp_path, capsys):
    from ccfit.cli import main

    (tmp_path / "file").write_text("")
    run = ["run", "--suite", SUITE, "--preset", "smoke", "--seed_dataset", "null"]
    for argv in ([*run, "--out", str(tmp_path / "file")],
                 ["report", str(tmp_path), "--out", str(tmp_path / "file")],
                 ["sweep", "--suites", SUITE, "--methods", "ft", "--seeds", "0", "--preset",
                  "smoke", "--out", str(tmp_path / "file"), "--dry-run"]):  # fmt: skip
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err == f"ccfit: error: --out {tmp_path / 'file'} is a file, not a folder\n", err


def test_a_config_file_fills_what_it_leaves_out_from_its_preset(tmp_path):
    """`--config_path` with a partial config takes the rest from the preset the file names,
    as the command line does (it took the code's defaults: a `smoke` config trained 100 000
    steps at the `cpu` size); a file of the wrong shape is one ConfigError."""
    from ccfit.config_base import ConfigError

    path = tmp_path / "config.json"
    path.write_text(json.dumps({"preset": "smoke", "suite": SUITE, "seed_dataset": None,
                                "train": {"eval_episodes": 1}}))  # fmt: skip
    flags = ["--preset", "smoke", "--suite", SUITE, "--seed_dataset", "null",
             "--train.eval_episodes=1"]  # fmt: skip
    assert parse_cli(CurriculumConfig, ["--config_path", str(path)]) == parse_cli(
        CurriculumConfig, flags
    )
    for text, needle in [
        ("[1, 2]", "is not a JSON config: not an object"),
        ('{"train": 5}', "train must be an object of settings, got 5"),
        ('{"model": {"type": "nope"}}', "unknown model 'nope'"),
    ]:
        path.write_text(text)
        with pytest.raises(ConfigError, match=needle):
            parse_cli(CurriculumConfig, ["--config_path", str(path)])
    path.write_bytes(b'{"suite": "caf\xe9"}')
    with pytest.raises(ConfigError, match="is not a JSON config"):
        parse_cli(CurriculumConfig, ["--config_path", str(path)])


def test_a_suite_without_oracle_references_fails_before_the_run(capsys, tmp_path,
                                                                monkeypatch):  # fmt: skip
    """BWT and FWT need normalised returns: a missing reference stops the run at once, not
    after hours of training."""
    import ccdata.scoring
    from ccfit.cli import main

    monkeypatch.setattr(ccdata.scoring, "references", lambda: {"tasks": {}})
    code = main(["run", "--suite", SUITE, "--preset", "smoke", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "no oracle reference for 'pick-cube'" in err and not (tmp_path / "x").exists()


@pytest.mark.parametrize("content", ["garbage", "old", "code"])
def test_a_foreign_or_old_run_state_is_one_line(runs, tmp_path, capsys, content):
    """curriculum.pt that this ccfit did not write (another program's file, an older format,
    a pickle that would run code) ends `ccfit run` with one line and exit 2, and nothing in
    the file is executed."""
    import shutil

    from ccfit.cli import main

    out = tmp_path / "run"
    shutil.copytree(runs.runs["ft"].dir, out)
    marker = tmp_path / "executed"
    if content == "garbage":
        (out / C.STATE).write_bytes(b"not a checkpoint at all")
    elif content == "old":
        torch.save({"version": 2, "completed": 1}, out / C.STATE)
    else:
        torch.save(_Exploit(str(marker)), out / C.STATE)
    (out / C.METRICS_JSON).unlink()
    saved = json.loads((out / CONFIG).read_text())
    saved["out"] = str(out)
    (out / CONFIG).write_text(json.dumps(saved))
    argv = _cli_argv("ft", out, runs.scratch_root)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert str(out / C.STATE) in err and "Traceback" not in err
    assert not marker.exists(), "the checkpoint's pickle ran code"


def test_another_curriculum_in_a_finished_runs_folder_is_one_line(runs, tmp_path, capsys):
    """`--out` holding another method's run is refused by its config before its state is read
    (the method's state did not fit and ended in a traceback)."""
    import shutil

    from ccfit.cli import main

    out = tmp_path / "run"
    shutil.copytree(runs.runs["packnet"].dir, out)
    saved = json.loads((out / CONFIG).read_text())
    saved["out"] = str(out)
    (out / CONFIG).write_text(json.dumps(saved))
    state = (out / C.STATE).read_bytes()
    code = main(_cli_argv("ft", out, runs.scratch_root))
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{out} holds a run with a different config (differs in method." in err
    assert (out / C.STATE).read_bytes() == state


class _Exploit:
    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_is_printed_whatever_values_the_other_options_have(flag, capsys):
    # draccus converted the values even for help and failed on optional fields (`--out`)
    with pytest.raises(SystemExit) as stop:
        parse_cli(CurriculumConfig, ["--out", "runs/x", "--encoder", "frozen:enc.safetensors",
                                     "--model.type=pwm", flag])  # fmt: skip
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert "--out" in out and "--model.experts_per_task" in out


@pytest.mark.parametrize(
    "command, flags",
    [("train", ["--quiet"]), ("fit", ["--quiet", "--scratch-root DIR"]),
     ("run", ["--quiet", "--scratch-root DIR", "--keep-stages", "--branch-from RUN",
              "--branch-after K"])],
)  # fmt: skip
def test_help_lists_the_options_outside_the_config_tree(command, flags, capsys):
    from ccfit.cli import main

    with pytest.raises(SystemExit) as stop:
        main([command, "--keep-stages", "--help"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert "--model.type" in out
    listed = out.split("options outside the config tree:\n")[1]
    assert [line.split("  ")[1].strip() for line in listed.splitlines() if line[2] == "-"] == flags


@pytest.mark.parametrize(
    "argv, message",
    [(["--keep-stages=false"], "--keep-stages takes no value, got '--keep-stages=false'"),
     (["--branch-from", "--branch-after", "2"], "--branch-from takes a value: --branch-from RUN"),
     (["--scratch-root"], "--scratch-root takes a value: --scratch-root DIR")],
)  # fmt: skip
def test_a_misspelt_option_outside_the_config_tree_is_one_line(argv, message, capsys, tmp_path):
    from ccfit.cli import main

    assert main(["run", "--suite", SUITE, "--out", str(tmp_path / "x"), *argv]) == 2
    assert capsys.readouterr().err == f"ccfit: error: {message}\n"
    assert not (tmp_path / "x").exists()


def test_cli_run_model_and_method_options_reach_the_config():
    def config(*extra):
        return parse_cli(CurriculumConfig, ["--suite", SUITE, "--model.type=pwm",
                                            "--method.type=experts", *extra])  # fmt: skip

    assert config().model.router == "task"
    assert config("--model.router=state").model.router == "state"
    assert config("--model.experts_per_task=2").model.experts_per_task == 2
    assert config("--method.type=ewc", "--method.lam=7").method.lam == 7.0
    # a group given as a mapping is draccus's own syntax, left to it
    mapping = parse_cli(CurriculumConfig, ["--suite", SUITE, "--model", "{type: pwm}"])
    assert mapping.model.type == "pwm"


def test_a_models_suite_budget_sets_the_training_settings_unless_given(monkeypatch):
    from ccfit.models.tdmpc2.config import TDMPC2Config

    budget = {"steps": 9_000, "demo_fraction": 0.25, "buffer_capacity": 80_000}
    monkeypatch.setattr(TDMPC2Config, "SUITE_TRAIN", {"cpu": {"Grasp": budget}})

    def train(*argv, **over):
        cli = parse_cli(CurriculumConfig, ["--model.type=tdmpc2", *argv]).train
        nested = resolve(CurriculumConfig, {"model": {"type": "tdmpc2"}, **over}).train
        assert cli == nested
        return cli

    def steps(*argv, **over):
        return train(*argv, **over).steps

    grasp = train("--suite", "Grasp", "--preset", "cpu", suite="Grasp", preset="cpu")
    assert (grasp.demo_fraction, grasp.buffer_capacity) == (0.25, 80_000)
    reach = train("--suite", "Reach", "--preset", "cpu", suite="Reach", preset="cpu")
    assert (reach.demo_fraction, reach.buffer_capacity) == (0.0, 50_000)
    assert (
        train(
            "--suite",
            "Grasp",
            "--preset",
            "cpu",
            "--train.demo_fraction=0",
            suite="Grasp",
            preset="cpu",
            train={"demo_fraction": 0.0},
        ).demo_fraction
        == 0
    )

    assert steps("--suite", "Grasp", "--preset", "cpu", suite="Grasp", preset="cpu") == 9_000
    assert steps("--suite", "Reach", "--preset", "cpu", suite="Reach", preset="cpu") == 6_000
    assert steps("--suite", "Grasp", "--preset", "smoke", suite="Grasp", preset="smoke") == 600
    assert steps("--suite", "Grasp", "--preset", "cpu", "--train.steps=3000", suite="Grasp",
                 preset="cpu", train={"steps": 3_000}) == 3_000  # fmt: skip
    # measured from state: pixel runs keep the preset's steps
    assert steps("--suite", "Grasp", "--preset", "cpu", "--obs", "pixels", suite="Grasp",
                 preset="cpu", obs="pixels") == 6_000  # fmt: skip
    # a subclass (PWM's config extends TD-MPC2's) measures its own budgets
    pwm = parse_cli(CurriculumConfig, ["--model.type=pwm", "--suite", "Grasp", "--preset", "cpu"])
    assert pwm.train.steps == 6_000


def test_a_budgets_model_settings_come_with_it_unless_given(monkeypatch):
    """`SUITE_MODEL`: where a suite's budget applies (a state curriculum of the suite at the
    preset), so do the model settings it was measured with; elsewhere the preset's."""
    from ccfit.models.dreamerv3.config import DreamerV3Config

    monkeypatch.setattr(DreamerV3Config, "SUITE_TRAIN", {"cpu": {"Grasp": {"demo_fraction": 0.25}}})
    monkeypatch.setattr(DreamerV3Config, "SUITE_MODEL", {"cpu": {"Grasp": {"demo_bc_coef": 0.5}}})

    def cloning(*argv):
        cfg = parse_cli(CurriculumConfig, ["--model.type=dreamerv3", "--preset", "cpu", *argv])
        nested = resolve(CurriculumConfig, {"model": {"type": "dreamerv3"}, "preset": "cpu",
                                            "suite": cfg.suite, "obs": cfg.obs})  # fmt: skip
        if not argv[2:]:
            assert nested.model == cfg.model
        return cfg.model.demo_bc_coef

    assert cloning("--suite", "Grasp") == 0.5
    assert cloning("--suite", "Grasp", "--model.demo_bc_coef=0.25") == 0.25
    assert cloning("--suite", "Reach") == 0.0
    assert cloning("--suite", "Grasp", "--obs", "pixels", "--train.demo_fraction=0.25") == 0.0


@pytest.mark.parametrize("model", shipped_models())
def test_every_measured_budget_names_a_suite_and_resolves(model):
    """Each registered model's `SUITE_TRAIN` entry names a real suite and preset and gives a
    valid state curriculum config holding those settings, and its `SUITE_MODEL` settings
    (only where it has such a budget)."""
    from ccdata import SUITES
    from ccfit.models.registry import config_class

    for preset, suites in vars(config_class(model)).get("SUITE_TRAIN", {}).items():
        for suite, budget in suites.items():
            assert suite in SUITES, f"{model} budget for unknown suite {suite!r}"
            cfg = parse_cli(CurriculumConfig, ["--suite", suite, "--preset", preset,
                                                "--model.type", model])  # fmt: skip
            assert {k: getattr(cfg.train, k) for k in budget} == budget
            settings = vars(config_class(model)).get("SUITE_MODEL", {}).get(preset, {})
            assert {k: getattr(cfg.model, k) for k in settings.get(suite, {})} == settings.get(
                suite, {}
            )
    for preset, suites in vars(config_class(model)).get("SUITE_MODEL", {}).items():
        budgets = vars(config_class(model)).get("SUITE_TRAIN", {}).get(preset, {})
        assert set(suites) <= set(budgets), (
            f"{model}: model settings for a suite without a measured budget"
        )


def test_a_suite_without_a_measured_budget_says_so_once_per_sweep_and_run(
        monkeypatch, tmp_path, capsys):  # fmt: skip
    """Where the model measured budgets at this preset but not for this suite (or from pixels),
    `ccfit sweep` and `ccfit run` say how many steps each task trains and that they were not
    shown to suffice; nothing where the budget is measured or the steps are given."""
    from ccfit.cli import main
    from ccfit.config_parse import budget_note
    from ccfit.models.tdmpc2.config import TDMPC2Config

    monkeypatch.setattr(TDMPC2Config, "SUITE_TRAIN", {"cpu": {"Grasp": {"steps": 9_000}}})

    def note(*argv):
        return budget_note(parse_cli(CurriculumConfig, ["--preset", "cpu", *argv]).to_dict())

    assert note("--suite", "Grasp") is None
    assert note("--suite", "Reach", "--train.steps=4000") is None
    assert note("--suite", "Reach", "--preset", "smoke") is None  # no budgets at smoke
    assert note("--suite", "Reach", "--model.type=dreamerv3") is None  # its own Reach budget
    reach = note("--suite", "Reach")
    assert "no measured 'cpu' budget for Reach from state" in reach and "6000 steps" in reach
    assert "Grasp from pixels" in note("--suite", "Grasp", "--obs", "pixels")
    pwm = note("--suite", "Grasp", "--model.type=pwm")  # PWM measured none
    assert "pwm has no measured 'cpu' budget for Grasp from state (measured from state: none)" in (
        pwm
    )

    out = tmp_path / "sweep"
    code = main(["sweep", "--suites", "Reach,Grasp", "--methods", "ft,ewc", "--seeds", "0,1",
                 "--preset", "cpu", "--out", str(out), "--dry-run"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0 and err.splitlines() == [f"ccfit sweep: note: {reach}"]
    # `ccfit run` says it before anything is trained (here an empty dataset folder then stops
    # it, exit 2)
    (tmp_path / "empty").mkdir()
    code = main(["run", "--suite", "Reach", "--preset", "cpu", "--seed_dataset",
                 str(tmp_path / "empty"), "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err[0] == f"ccfit run: note: {reach}"


def test_a_curriculum_from_state_says_which_tasks_are_one_task_there(tmp_path, capsys):
    """BinPnP's and PnPBlock's tasks that differ only in a colour are one MDP from state
    (`Suite.same_from_state`): `ccfit run`, `ccfit fit` and `ccfit sweep` say so from state,
    not from pixels, and nothing on a suite without such tasks."""
    from ccfit.cli import main
    from ccfit.config_parse import state_note

    def note(*argv):
        return state_note(parse_cli(CurriculumConfig, ["--preset", "cpu", *argv]).to_dict())

    assert note("--suite", "Reach") is None and note("--suite", "Grasp") is None
    assert note("--suite", "BinPnP", "--obs", "pixels") is None
    blocks = note("--suite", "PnPBlock")
    assert "PnPBlock's pnp-red-block and pnp-blue-block are one task" in blocks
    assert "stack-blocks" not in blocks
    bins = note("--suite", "BinPnP")
    assert "bin-red-blue, bin-yellow-blue, bin-red-purple and bin-yellow-purple" in bins

    # (no demonstrations: BinPnP's `cpu` budget oversamples them, and no dataset is made here)
    code = main(["sweep", "--suites", "BinPnP,Reach", "--methods", "ft,ewc", "--seeds", "0,1",
                 "--preset", "cpu", "--train.demo_fraction=0", "--out", str(tmp_path / "sweep"),
                 "--dry-run"])  # fmt: skip
    notes = [line for line in capsys.readouterr().err.splitlines() if "one task" in line]
    assert code == 0 and notes == [f"ccfit sweep: note: {bins}"]
    # `ccfit run` and `ccfit fit` say it before anything is trained (an empty dataset folder
    # then stops them, exit 2)
    (tmp_path / "empty").mkdir()
    for command, dataset in (("run", "--seed_dataset"), ("fit", "--dataset")):
        code = main([command, "--suite", "PnPBlock", "--preset", "cpu", dataset,
                     str(tmp_path / "empty"), "--out", str(tmp_path / command)])  # fmt: skip
        err = capsys.readouterr().err.splitlines()
        assert code == 2 and f"ccfit {command}: note: {blocks}" in err


def test_report_writes_tables_plots_and_summary(runs, tmp_path, capsys):
    from ccfit.cli import main

    out = tmp_path / "report"
    assert main(["report", str(runs.root), "--out", str(out)]) == 0
    printed = set(capsys.readouterr().out.split())
    expected = {"table_tdmpc2.md", "table_tdmpc2.csv", "bars_tdmpc2.png", "summary.json",
                "orderings.md", "axes.md", "cost.md", "stages.md", "stages.csv"}  # fmt: skip
    expected |= {f"curves_tdmpc2_{SUITE}_{m}.png" for m in METHODS}
    assert {p.name for p in out.iterdir()} == expected
    assert printed == {str(out / name) for name in expected}
    # cost.md: each method's curricula, on this machine (every segment recorded)
    from ccfit.report.cost import machine_label
    from ccfit.train.cost import running_machine

    lines = (out / "cost.md").read_text().splitlines()
    for m in METHODS:
        (line,) = [x for x in lines if x.startswith(f"| tdmpc2 | {SUITE} | {m} |")]
        assert line.endswith(f"| {machine_label(running_machine())} x1 |"), line

    with (out / "table_tdmpc2.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["method"] for r in rows) == sorted(METHODS)
    for r in rows:
        assert (r["backbone"], r["suite"], r["seeds"]) == ("tdmpc2", SUITE, "1")
        metrics = runs.runs[r["method"]].result
        # one seed: the group's metric is the run's (forgetting: Continual World's)
        for name, key in (("bwt", "bwt"), ("forgetting", "cw_forgetting"), ("fwt", "fwt")):
            value = None if r[name] == "" else float(r[name])
            assert value == pytest.approx(metrics[key])
    md = (out / "table_tdmpc2.md").read_text().splitlines()
    header = next(line for line in md if line.startswith("| suite"))
    assert all(f"| {m} BWT | {m} F | {m} FWT |" in header for m in METHODS)
    assert [line.split("|")[1].strip() for line in md if line.startswith(f"| {SUITE}")] == [SUITE]
    orderings = (out / "orderings.md").read_text()
    for ordering in ("PackNet forgets least, FT most", "ER transfers most"):
        assert f"| {ordering} | tdmpc2 | {SUITE} |" in orderings
    axis = get_suite(SUITE).axis
    assert f"| tdmpc2 | {axis} | " in (out / "axes.md").read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary) == sorted(f"tdmpc2/{SUITE}/{m}" for m in METHODS)
    # stages.csv, read from the loop's records: each task's own stage ends at its end-of-task
    # score, the last stage at the final scores
    with (out / "stages.csv").open() as f:
        stages = list(csv.DictReader(f))
    for m in METHODS:
        mine = [r for r in stages if r["method"] == m]
        assert_stage_ends_are_the_metrics(mine, runs.runs[m].result)
    assert all(summary[f"tdmpc2/{SUITE}/{m}"]["seeds"] == [0] for m in METHODS)
    for name in expected:
        if name.endswith(".png"):
            data = (out / name).read_bytes()
            assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name


def test_publish_keeps_small_files_and_its_report_rebuilds_from_them(runs, tmp_path, capsys):
    from ccfit.cli import main
    from ccfit.publish import MAX_FILE_BYTES
    from ccfit.report import write_report

    published = tmp_path / "results" / "smoke"
    assert main(["publish", str(runs.root), "--out", str(published)]) == 0
    files = [p for p in published.rglob("*") if p.is_file()]
    assert not [p for p in files if p.suffix in (".pt", ".parquet", ".npz", ".mp4")]
    assert all(p.stat().st_size <= MAX_FILE_BYTES for p in files)
    assert {p.parent.name for p in published.glob("*/metrics.json")} == set(METHODS)
    # published again, the report is rebuilt whole: a file of an earlier one does not survive
    (published / "report" / "curves_of_a_group_gone.png").write_bytes(b"")
    assert main(["publish", str(runs.root), "--out", str(published)]) == 0
    assert not (published / "report" / "curves_of_a_group_gone.png").exists()
    assert (published / "report" / "table_tdmpc2.md").is_file()
    # moved elsewhere, the copy alone rebuilds the same tables (scratch found beside the runs)
    moved = tmp_path / "moved"
    published.rename(moved)
    again = tmp_path / "again"
    write_report([moved], again)
    tables = sorted(p.name for p in (moved / "report").glob("table_*"))
    assert tables == ["table_tdmpc2.csv", "table_tdmpc2.md"]
    for name in tables:
        assert (again / name).read_bytes() == (moved / "report" / name).read_bytes()


def test_report_table_frame_matches_runs(runs):
    from ccfit.report import load_groups, table_frame

    groups = load_groups([runs.root])
    frame = table_frame(groups, "tdmpc2")
    assert list(frame.index) == [SUITE]
    assert list(frame.columns.get_level_values(0)[::3]) == list(METHODS)
    for m in METHODS:
        for name, column in (("bwt", "BWT"), ("cw_forgetting", "F"), ("fwt", "FWT")):
            value = runs.runs[m].result[name]
            cell = frame.loc[SUITE, (m, column)]
            assert np.isnan(cell) if value is None else cell == pytest.approx(value)
    with pytest.raises(ValueError, match="valid: tdmpc2"):
        table_frame(groups, "pwm")


@pytest.mark.integration
def test_results_notebook_runs_on_smoke_runs(runs, tmp_path, monkeypatch):
    import nbformat
    from nbclient import NotebookClient

    monkeypatch.setenv("CCFIT_RUNS", str(runs.root))
    monkeypatch.setenv("CCFIT_FIGURES", str(tmp_path / "figures"))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "stored outputs"
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()  # fmt: skip
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    html = "".join(o.get("data", {}).get("text/html", "") for o in outputs)
    assert all(m in html for m in METHODS) and SUITE in html and "BWT" in html
    pngs = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(pngs) == 1 + len(METHODS)  # the bars and one curve plot per group
    assert len(list((tmp_path / "figures").glob("*.png"))) == 1 + len(METHODS)


# ============================================================================= memory


@pytest.mark.integration
def test_a_tasks_replay_is_freed_before_the_next_task_allocates_its_own(tmp_path, monkeypatch):
    """Two tasks' replay rings never coexist (the memory check counts one): when the
    curriculum makes task i's buffer, nothing references an earlier task's buffer any more."""
    import gc
    import weakref

    made, alive_when_making = [], []
    real = C.make_replay

    def watched(*args, **kwargs):
        gc.collect()  # unreachable cycles (torch's first import of Dynamo leaves some) aside
        alive_when_making.append(sum(ref() is not None for ref in made))
        buffer = real(*args, **kwargs)
        made.append(weakref.ref(buffer))
        return buffer

    monkeypatch.setattr(C, "make_replay", watched)
    train = {"steps": 40, "seed_steps": 20, "eval_interval": 40, "checkpoint_interval": 40,
             "parallel": "off", "episode_steps": EPISODE_STEPS}  # fmt: skip
    cfg = resolve(CurriculumConfig, {"suite": SUITE, "preset": "smoke", "seed_dataset": None,
                                     "train": train, "method": {"type": "ft"}})  # fmt: skip
    Curriculum(cfg, tmp_path / "run", tmp_path / "scratch", progress=False).run()
    assert alive_when_making == [0] * len(TASKS)


@pytest.mark.integration
def test_the_reference_records_what_the_seed_dataset_held(tmp_path):
    """With a seed dataset, the from-scratch reference's config.json records the dataset's
    contents as the run's does (its key leaves them out, its record keeps them)."""
    from ccdata.record import GenerateConfig, generate
    from ccfit.cli import main

    root = tmp_path / SUITE
    generate(GenerateConfig(SUITE, episodes=1, explore_episodes=1, image_size=32, max_steps=20,
                            root=root), progress=False)  # fmt: skip
    out = tmp_path / "run"
    argv = ["run", "--suite", SUITE, "--preset", "smoke", "--seed_dataset", str(root), "--quiet",
            "--out", str(out), *(f"--train.{k}={v}" for k, v in TRAIN.items())]  # fmt: skip
    assert main(argv) == 0
    run = json.loads((out / CONFIG).read_text())
    reference_dir = json.loads((out / C.METRICS_JSON).read_text())["scratch_dir"]
    reference = json.loads((Path(reference_dir) / CONFIG).read_text())
    info = json.loads((root / "meta" / "info.json").read_text())
    assert run["resolved_seed_dataset_meta"]["total_episodes"] == info["total_episodes"] > 0
    assert reference["resolved_seed_dataset_meta"] == run["resolved_seed_dataset_meta"]
    assert reference["resolved_seed_dataset"] == run["resolved_seed_dataset"]


class _Stopped(Exception):
    """Raised by the test's `_save` spy to stop a run between tasks."""


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        a[n].keys() == b[n].keys() and all(torch.equal(a[n][k], b[n][k]) for k in a[n]) for n in a
    )


@pytest.mark.integration
def test_kept_backbone_optimiser_state_crosses_tasks_and_a_stop_between_them(tmp_path, monkeypatch):
    """`--train.keep_backbone_optimizer`: each task's optimiser starts from the backbone's
    state where the last task left it; curriculum.pt holds it between tasks, so a run stopped
    there resumes to the uninterrupted result; the from-scratch reference (one task, nothing
    to carry) is the one runs without the option share."""
    train = {**TRAIN, "parallel": "off", "keep_backbone_optimizer": True}
    cfg = resolve(CurriculumConfig, {"suite": SUITE, "preset": "smoke", "seed_dataset": None,
                                     "train": train, "method": {"type": "ft"}})  # fmt: skip
    started, ended = [], []

    class SpyTrainer(C.Trainer):
        def __init__(self, **kwargs) -> None:
            super().__init__(**kwargs)
            started.append(backbone_optimizer_state(self.step.optim, self.model.backbone))

        def run(self, wait: bool = True) -> dict | None:
            out = super().run(wait)
            ended.append(backbone_optimizer_state(self.step.optim, self.model.backbone))
            return out

    real_save = Curriculum._save

    def save_then_stop(self, completed, *args) -> None:
        real_save(self, completed, *args)
        if completed == 1:
            raise _Stopped

    monkeypatch.setattr(C, "Trainer", SpyTrainer)
    scratch = tmp_path / "scratch"
    whole = Curriculum(cfg, tmp_path / "whole", scratch, progress=False).run()
    assert started[0] == {} and ended[0], "the first task starts fresh and trains"
    assert all(_same_state(s, e) for s, e in zip(started[1:], ended[:-1], strict=True))
    first_end = ended[0]
    started.clear()
    monkeypatch.setattr(Curriculum, "_save", save_then_stop)
    with pytest.raises(_Stopped):
        Curriculum(cfg, tmp_path / "stopped", scratch, progress=False).run()
    monkeypatch.setattr(Curriculum, "_save", real_save)
    started.clear()
    resumed = Curriculum(cfg, tmp_path / "stopped", scratch, progress=False).run()
    assert _same_state(started[0], first_end)
    assert _records(tmp_path / "stopped") == _records(tmp_path / "whole")
    assert resumed == whole
    fresh = dataclasses.replace(
        cfg, train=dataclasses.replace(cfg.train, keep_backbone_optimizer=False)
    )
    assert C.OnlineTrack(fresh).reference_key() == C.OnlineTrack(cfg).reference_key()
