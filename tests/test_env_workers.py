"""Environments in worker processes (`ccfit.train.env_workers`) are the local ones: the same
observations, camera images included, rewards and ends, stepped side by side; what fails in a
worker fails in the evaluating process, with the worker's own traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import ccdata
from ccdata.env import DEFAULT_EPISODE_STEPS
from ccfit.config import TrainConfig
from ccfit.config_base import ConfigError
from ccfit.train import env_workers as ew
from ccfit.train.env_workers import EnvWorkers, resolve_env_workers, step_all

SIZE = 32


def _play(envs, seeds, actions):
    """Reset each env to its seed, then step all with `actions[t][i]` until every one ends."""
    firsts = [env.reset(seed=s)[0] for env, s in zip(envs, seeds, strict=True)]
    trace = [[first] for first in firsts]
    running = list(range(len(envs)))
    for moves in actions:
        outcomes = step_all([envs[i] for i in running], [moves[i] for i in running])
        still = []
        for i, (obs, reward, terminated, truncated, info) in zip(running, outcomes, strict=True):
            trace[i].append((obs, reward, terminated, truncated, info["success"]))
            if not (terminated or truncated):
                still.append(i)
        running = still
    return trace


@pytest.mark.integration
def test_remote_envs_render_and_step_as_local_ones(short_episodes):
    seeds = [3, 4, 5]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (short_episodes, len(seeds), 4)).astype(np.float32)
    local = [ccdata.make_env("reach-xy", image_size=SIZE, episode_steps=short_episodes)
             for _ in seeds]  # fmt: skip
    pool = EnvWorkers(2, render=True, image_size=SIZE, episode_steps=short_episodes)
    try:
        remote = [pool.make("reach-xy", worker=j) for j in range(len(seeds))]
        assert [env.worker for env in remote] == [0, 1, 0]
        theirs = _play(remote, seeds, actions)
    finally:
        pool.close()
    ours = _play(local, seeds, actions)
    for env in local:
        env.close()
    assert len(ours[0]) == short_episodes + 1
    for a, b in zip(ours, theirs, strict=True):
        assert len(a) == len(b)
        for obs_a, obs_b in zip([a[0]] + [x[0] for x in a[1:]], [b[0]] + [x[0] for x in b[1:]],
                                strict=True):  # fmt: skip
            assert obs_a.keys() == obs_b.keys() and "frontview" in obs_a
            assert all(np.array_equal(obs_a[k], obs_b[k]) for k in obs_a)
        assert [x[1:] for x in a[1:]] == [x[1:] for x in b[1:]]


def test_a_workers_episodes_end_at_the_length_it_was_given():
    pool = EnvWorkers(1, render=False, image_size=SIZE, episode_steps=3)
    try:
        env = pool.make("reach-xy", worker=0)
        env.reset(seed=0)
        ends = [env.step(np.zeros(4, np.float32))[3] for _ in range(3)]  # truncated flags
        assert ends == [False, False, True]
    finally:
        pool.close()


def test_what_fails_in_a_worker_fails_here_with_its_traceback():
    pool = EnvWorkers(1, render=False, image_size=SIZE, episode_steps=DEFAULT_EPISODE_STEPS)
    try:
        with pytest.raises(RuntimeError, match="(?s)worker 0 raised.*no-such-task"):
            pool.make("no-such-task", worker=0)
        env = pool.make("reach-xy", worker=0)  # the worker serves on after an error
        env.reset(seed=0)
        with pytest.raises(RuntimeError, match="(?s)worker 0 raised.*Traceback"):
            env.step(np.zeros(7, np.float32))  # not a 4-D action
        obs, *_ = env.step(np.zeros(4, np.float32))
        assert obs["state"].shape == (39,)
    finally:
        pool.close()


def test_a_dead_worker_is_named():
    pool = EnvWorkers(1, render=False, image_size=SIZE, episode_steps=DEFAULT_EPISODE_STEPS)
    try:
        env = pool.make("reach-xy", worker=0)
        os.kill(pool._procs[0].pid, signal.SIGKILL)
        pool._procs[0].join()
        with pytest.raises(RuntimeError, match="worker 0 died"):
            env.reset(seed=0)
    finally:
        pool.close()


def test_env_workers_resolve(monkeypatch):
    monkeypatch.setattr(ew, "available_cores", lambda: 16)
    auto = dict(obs_mode="pixels", parallel=True, episodes=10)
    assert resolve_env_workers("auto", **auto) == 10  # 13 free cores, 10 episodes
    assert resolve_env_workers("auto", **{**auto, "episodes": 5}) == 5
    assert resolve_env_workers("auto", **{**auto, "obs_mode": "state"}) == 0
    assert resolve_env_workers("auto", **{**auto, "parallel": False}) == 0
    assert resolve_env_workers("3", **{**auto, "obs_mode": "state"}) == 3
    assert resolve_env_workers("100000", **auto) == 10  # not 100 000 processes for 10 episodes
    monkeypatch.setattr(ew, "available_cores", lambda: 4)  # one core free: not worth a process
    assert resolve_env_workers("auto", **auto) == 0
    assert TrainConfig(env_workers=2).env_workers == "2"
    with pytest.raises(ConfigError, match="train.env_workers must be 'auto' or a count"):
        TrainConfig(env_workers="many")


@pytest.mark.integration
def test_workers_end_with_a_killed_evaluating_process():
    """A run killed outright (SIGKILL: no cleanup) leaves no environment worker behind: each
    sees its pipe close and exits."""
    code = (
        "import sys, time\n"
        "from ccfit.train.env_workers import EnvWorkers\n"
        "pool = EnvWorkers(2, render=False, image_size=32, episode_steps=250)\n"
        "envs = [pool.make('reach-xy', worker=j) for j in range(2)]\n"
        "print(*(p.pid for p in pool._procs), flush=True)\n"
        "time.sleep(600)\n"
    )
    _assert_workers_end_with(code, signal.SIGKILL, workers=2)


@pytest.mark.parametrize("initializer", [False, True])
def test_a_worker_pool_ends_with_a_killed_process(initializer):
    """The spawned pools of training (evaluation, a from-scratch reference, a sweep's local
    jobs: `ccdata.processes.worker_pool`) leave no worker behind a process killed by a signal,
    idle or busy, with or without an initializer of their own. A plain `ProcessPoolExecutor`
    worker would wait on its queue forever."""
    init = "initializer=time.sleep, initargs=(0,)" if initializer else ""
    code = (
        "import time\n"
        "from ccdata.processes import worker_pool\n"
        f"idle, busy = worker_pool(1, {init}), worker_pool(1, {init})\n"
        "idle.submit(time.sleep, 0).result()\n"
        "busy.submit(time.sleep, 0).result()\n"
        "busy.submit(time.sleep, 600)\n"
        "print(*idle._processes, *busy._processes, flush=True)\n"
        "time.sleep(600)\n"
    )
    _assert_workers_end_with(code, signal.SIGTERM, workers=2)  # Python runs no clean-up for it


def _assert_workers_end_with(code: str, sig: signal.Signals, workers: int) -> None:
    """Run `code` (it prints its workers' pids, then sleeps), send it `sig`: within 30 s none
    of its `workers` may run."""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(x) for x in proc.stdout.readline().split()]
    finally:
        proc.send_signal(sig)
        proc.wait()
    assert len(pids) == workers
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in pids)


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, exited but not reaped by its dead parent's init, is not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


class _HoldsAClosure(Exception):
    """An exception that cannot be pickled, as Inductor's errors cannot."""

    def __init__(self, message: str) -> None:
        super().__init__(f"{message}\n\nCommand: g++ ...")
        self.hook = lambda: message


class _NeedsTwoArguments(Exception):
    """An exception that pickles but unpickles only with other arguments than its message."""

    def __init__(self, what: str, why: str) -> None:
        super().__init__(f"{what} failed: {why}")


def _fail(how: str) -> None:
    if how == "plain":
        raise ValueError("a plain failure")
    if how == "two arguments":
        raise _NeedsTwoArguments("the merge", "disk full")
    raise _HoldsAClosure("C++ compile error")


def test_what_a_pooled_job_raises_comes_back_named():
    # An evaluation worker's Inductor error came back as "cannot pickle 'cell' object", and
    # a sweep's summary of the failed run said only that.
    from ccdata.processes import worker_pool

    pool = worker_pool(1)
    try:
        with pytest.raises(RuntimeError, match=r"^_HoldsAClosure: C\+\+ compile error$") as err:
            pool.submit(_fail, "closure").result()
        assert "in _fail" in str(err.value.__cause__)  # the worker's traceback, whole
        assert "Command: g++" in str(err.value.__cause__)
        with pytest.raises(RuntimeError, match="^_NeedsTwoArguments: the merge failed: disk full$"):
            pool.submit(_fail, "two arguments").result()
        with pytest.raises(ValueError, match="^a plain failure$"):
            pool.submit(_fail, "plain").result()
    finally:
        pool.shutdown()


def test_an_error_in_one_line_is_its_type_and_first_line():
    # What a sweep's summary says of a failed job: Inductor's errors end with a hint ("Set
    # TORCHDYNAMO_VERBOSE=1 ..."), not the error.
    from ccdata.processes import one_line

    err = RuntimeError("CppCompileError: C++ compile error\n\nCommand:\ng++ ...\n\nSet X=1")
    assert one_line(err) == "RuntimeError: CppCompileError: C++ compile error"
    assert one_line(ValueError("\n  indented\n")) == "ValueError: indented"
    assert one_line(ValueError()) == "ValueError"
