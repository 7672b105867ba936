"""`--train.parallel=on`: evaluation in a worker process beside training and the from-scratch
reference in another give a run the same records and metrics as doing everything in the
training process, and a run killed with evaluations in flight resumes to the same result."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

from ccfit.config import CurriculumConfig
from ccfit.config_parse import resolve
from ccfit.curriculum import Curriculum

try:
    from process_tree import PROC, ended, workers
    from short_episodes import EPISODE_STEPS, ccfit_command
except ImportError:  # tests/ imported as a package
    from tests.process_tree import PROC, ended, workers
    from tests.short_episodes import EPISODE_STEPS, ccfit_command

TRAIN = {"steps": 100, "seed_steps": 50, "eval_interval": 50, "checkpoint_interval": 50,
         "eval_episodes": 2, "end_eval_episodes": 3, "episode_steps": EPISODE_STEPS}  # fmt: skip
"""A task's end plays more episodes than the evaluations during it: a resumed run that replays
an end evaluation still in flight must replay it with its own count."""


def _config(parallel: str, method: str = "packnet", env_workers: str = "auto"
            ) -> CurriculumConfig:  # fmt: skip
    options = {"packnet": {"retrain_steps": 10}}.get(method, {})
    return resolve(CurriculumConfig, {
        "suite": "Grasp", "preset": "smoke", "seed_dataset": None,
        "train": {**TRAIN, "parallel": parallel, "env_workers": env_workers},
        "method": {"type": method, **options},
    })  # fmt: skip


def _outputs(run: Path) -> tuple[str, dict]:
    metrics = json.loads((run / "metrics.json").read_text())
    metrics.pop("scratch_dir")
    return (run / "metrics.jsonl").read_text(), metrics


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    root = tmp_path_factory.mktemp("serial")
    torch.set_num_threads(1)
    Curriculum(_config("off"), root / "run", root / "scratch", progress=False).run()
    return root


# Each variant is a whole 3-task curriculum (~1 min on 2 cores): those another test covers
# run under `make test-slow`. The killed run below ends as the serial one with the default
# 'auto'; environments in worker processes are test_env_workers'.
@pytest.mark.slow
@pytest.mark.parametrize("env_workers", ["auto", "2"])
def test_parallel_run_equals_the_serial_one(serial, tmp_path, env_workers):
    """'2': the evaluator's environments step in two processes of their own (started by the
    evaluation worker)."""
    torch.set_num_threads(1)
    Curriculum(
        _config("on", env_workers=env_workers),
        tmp_path / "run",
        tmp_path / "scratch",
        progress=False,
    ).run()
    assert _outputs(tmp_path / "run") == _outputs(serial / "run")
    (ours,), (theirs,) = (list((r / "scratch").glob("*/done.json")) for r in (tmp_path, serial))
    assert ours.read_text() == theirs.read_text()
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["train"]["parallel"] == "on" and saved["train"]["env_workers"] == env_workers


def test_killed_parallel_run_resumes_to_the_serial_result(serial, tmp_path):
    out = tmp_path / "run"
    argv = [
        "run",
        "--suite",
        "Grasp",
        "--preset",
        "smoke",
        "--seed_dataset",
        "null",
        "--method.type=packnet",
        "--method.retrain_steps=10",
        "--out",
        str(out),
        "--scratch-root",
        str(tmp_path / "scratch"),
        "--quiet",
        "--train.parallel=on",
    ]
    argv += [f"--train.{k}={v}" for k, v in TRAIN.items()]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    ckpt = out / "tasks" / "1-place-cube" / "checkpoint.pt"
    proc = subprocess.Popen(ccfit_command(argv), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read()[-2000:]
        assert ckpt.exists(), "no checkpoint in 300 s"
        proc.kill()  # SIGKILL: the evaluation worker of the run ends with it
    finally:
        proc.kill()
        proc.communicate()
    done = subprocess.run(ccfit_command(argv), env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert _outputs(out) == _outputs(serial / "run")
    (ours,), (theirs,) = (list(d.glob("*/done.json")) for d in (tmp_path / "scratch",
                                                                 serial / "scratch"))  # fmt: skip
    assert ours.read_text() == theirs.read_text()
    saved = json.loads((out / "config.json").read_text())
    assert saved["train"]["parallel"] == "on" and saved["train"]["env_workers"] == "auto"


# Stopped at a task's checkpoint, as the killed run above is (there at a time chosen by the
# kill, here exactly): slow. Stopped between tasks: after `make test` (one curriculum each).
@pytest.mark.parametrize(
    "at",
    [
        pytest.param("task-checkpoint", marks=pytest.mark.slow),
        pytest.param("curriculum-state", marks=pytest.mark.integration),
    ],
)
def test_a_run_stopped_with_evaluations_in_flight_resumes_to_the_serial_result(
        serial, tmp_path, monkeypatch, at):  # fmt: skip
    # A checkpoint lists the evaluations still running at its step, and so does the
    # curriculum's state at a task's end (the next task trains while the last one's
    # evaluation runs). Records of such a request that came in before a kill are kept, not
    # logged twice; those that did not are computed again. Built exactly: the run directory
    # as it stood when task 1's first checkpoint (with the records logged up to its step), or
    # the state after task 0 (with those logged until then), was written.
    import shutil

    import ccfit.runner as runner
    import ccfit.train.loop as loop

    out, snapshot = tmp_path / "run", tmp_path / "stopped"
    save = loop.atomic_torch_save
    assert runner.atomic_torch_save is save

    def save_and_snapshot(state, path):
        save(state, path)
        if snapshot.exists():
            return
        task = (state["kind"] == loop.CHECKPOINT_KIND and state["task_step"] == 50
                and state["global_offset"] == TRAIN["steps"])  # fmt: skip
        if task if at == "task-checkpoint" else state.get("completed") == 1:
            assert state["pending_evals"], "no evaluation in flight"
            shutil.copytree(out, snapshot)

    monkeypatch.setattr(loop, "atomic_torch_save", save_and_snapshot)
    monkeypatch.setattr(runner, "atomic_torch_save", save_and_snapshot)
    torch.set_num_threads(1)
    Curriculum(_config("on"), out, tmp_path / "scratch", progress=False).run()
    assert snapshot.exists()
    if at == "task-checkpoint":
        records = (out / "metrics.jsonl").read_text().splitlines(keepends=True)
        step = TRAIN["steps"] + 50
        logged = [r for r in records if json.loads(r)["global_step"] <= step]
        (snapshot / "metrics.jsonl").write_text("".join(logged))
    monkeypatch.setattr(loop, "atomic_torch_save", save)
    monkeypatch.setattr(runner, "atomic_torch_save", save)
    Curriculum(_config("on"), snapshot, tmp_path / "scratch", progress=False).run()
    assert _outputs(snapshot) == _outputs(serial / "run")


@pytest.mark.integration
def test_with_compiled_hot_paths_the_reference_starts_after_the_first_task(tmp_path, monkeypatch):
    # A compiled run's reference starts once the first task has trained (the compiled graphs
    # are then cached for it; an eager run's starts at once). The compiled paths are faked in
    # the resolved settings: compiling for real takes minutes, and the start reads only them.
    import ccfit.curriculum as curriculum
    import ccfit.train.run as run_module

    real_resolved, real_start = curriculum.resolved_config, curriculum.start_scratch
    seen = []

    def resolved(cfg, suite, *args, **kwargs):
        return {**real_resolved(cfg, suite, *args, **kwargs), "resolved_compile": ["loss"]}

    def start(cfg, out):
        seen.append(sorted(p.name for p in (tmp_path / "run" / "tasks").glob("*")))
        return real_start(cfg, out)

    monkeypatch.setattr(curriculum, "resolved_config", resolved)
    monkeypatch.setattr(curriculum, "start_scratch", start)
    # The model is built with the faked paths; this process trains them eagerly.
    monkeypatch.setattr(run_module, "compile_hot_paths",
                        lambda model, setting, paths=None, **kw: list(paths or ()))  # fmt: skip
    torch.set_num_threads(1)
    Curriculum(_config("on", "ft"), tmp_path / "run", tmp_path / "scratch",
               progress=False).run()  # fmt: skip
    assert seen == [["0-pick-cube"]]
    assert len(list((tmp_path / "scratch").glob("*/done.json"))) == 1


def _priority_in_a_scratch_worker(cfg: CurriculumConfig, out: Path) -> None:
    """`_scratch_worker` as a reference's process runs it, the reference itself replaced by a
    note of the process's priority (written to `out`)."""
    import ccfit.curriculum as curriculum

    curriculum.run_reference = lambda track, path, progress: Path(path).write_text(
        str(os.getpriority(os.PRIO_PROCESS, 0)))  # fmt: skip
    curriculum._scratch_worker(cfg, out)


def test_the_evaluation_worker_and_the_reference_run_behind_training(tmp_path):
    """Both helpers of a parallel run take the cores training leaves (`yield_to_training`)."""
    from ccdata.processes import worker_pool
    from ccfit.train.eval_worker import HELPER_NICENESS
    from ccfit.train.run import build_model, make_evaluator

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    behind = min(mine + HELPER_NICENESS, 19)  # 19: the lowest priority there is
    cfg = _config("on", "ft")
    evaluator = make_evaluator(cfg, build_model(cfg, torch.device("cpu"), []),
                               dict(enumerate(cfg.tasks)), compiled=[])  # fmt: skip
    try:
        assert evaluator._pool.submit(os.getpriority, os.PRIO_PROCESS, 0).result() == behind
    finally:
        evaluator.close()
    note = tmp_path / "priority"
    pool = worker_pool(1)
    try:
        pool.submit(_priority_in_a_scratch_worker, cfg, note).result()
    finally:
        pool.shutdown()
    assert int(note.read_text()) == behind
    assert os.getpriority(os.PRIO_PROCESS, 0) == mine  # the training process keeps its own


@pytest.mark.skipif(not PROC.is_dir(), reason="reads processes from /proc")
def test_an_interrupted_run_ends_its_reference_with_it(tmp_path):
    """Ctrl-C that reaches the run's process alone (SIGINT to it, as a launcher sends): the run
    stops at once, its from-scratch reference's worker with it, instead of the interpreter's
    exit waiting for the whole reference to train."""
    out, scratch = tmp_path / "run", tmp_path / "scratch"
    argv = ["run", "--suite", "Reach", "--preset", "smoke", "--seed_dataset", "null",
            "--out", str(out), "--scratch-root", str(scratch), "--quiet", "--train.parallel=on",
            "--train.steps=10000000", "--train.eval_interval=1000000"]  # fmt: skip
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.Popen(ccfit_command(argv), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while not list(scratch.glob("*/config.json")) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read()[-2000:]
            time.sleep(0.1)
        assert list(scratch.glob("*/config.json")), "no reference began in 300 s"
        running = workers(proc.pid)
        assert running
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=120)  # before: until the 10M-step reference ended
    finally:
        proc.kill()
        _, err = proc.communicate()
    assert "interrupted; rerun the same command to resume" in err.decode()
    assert all(ended(pid) for pid in running)


@pytest.mark.skipif(not PROC.is_dir(), reason="reads processes from /proc")
def test_closing_with_an_evaluation_in_flight_kills_the_worker():
    """A run that stops early (Ctrl-C, an error) closes its evaluator with an evaluation
    running; its checkpoint lists that request for the resumed run, so the worker is killed,
    not waited for (before: `ccfit train` beside a sweep took over 9 minutes to exit after
    SIGINT). This evaluation never ends by itself: a fresh policy does not pick the cube up, and
    its episode is a billion steps long."""
    import threading

    from ccfit.train.run import build_model, make_evaluator

    cfg = resolve(CurriculumConfig, {
        "suite": "Grasp", "preset": "smoke", "seed_dataset": None, "method": {"type": "ft"},
        "train": {**TRAIN, "parallel": "on", "episode_steps": 10**9,
                  "buffer_capacity": 10**9 + 1},
    })  # fmt: skip
    before = set(workers(os.getpid()))
    model = build_model(cfg, torch.device("cpu"), [])
    evaluator = make_evaluator(cfg, model, {0: cfg.tasks[0]}, compiled=[])
    evaluator.heads[0] = model.new_heads()
    evaluator.submit([0], stage=0, global_step=0, task_step=0)
    [(_, future)] = evaluator._queue
    deadline = time.monotonic() + 120
    while not future.running() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert future.running(), "the evaluation did not start in 120 s"
    running = [pid for pid in workers(os.getpid()) if pid not in before]
    assert running
    closing = threading.Thread(target=evaluator.close, daemon=True)
    closing.start()
    closing.join(timeout=60)  # before: forever
    assert not closing.is_alive()
    assert all(ended(pid) for pid in running)
