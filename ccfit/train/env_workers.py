"""Evaluation environments hosted in worker processes, so that the episodes of an evaluation
step and render side by side.

A pixel run's evaluation is mostly MuJoCo rendering (three cameras per step, in software GL on
a machine without a GPU), while its acting is one batched model call per step for all episodes
(`play_episodes`). Hosting the environments in `EnvWorkers` lets those renders run on as many
cores: `step_all` sends every environment its action before it waits for any result. A
`RemoteEnv` is the same `TaskEnv` as a local one (made by `make_env` from the same arguments),
so episodes are the same wherever their environment lives (tested).

Each worker is a spawned process that imports the simulator, not torch, and serves its
environments' calls in the order they were sent. It exits when the evaluating process closes
the pool or dies (its pipe closes). What an environment raises in a worker is raised again in
the evaluating process, with the worker's traceback.
"""

from __future__ import annotations

import multiprocessing as mp
import signal
import traceback
from collections import deque
from collections.abc import Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

from ccdata.processes import available_cores

JOIN_TIMEOUT_S = 10.0
"""How long `close` waits for a worker to exit before it is terminated."""


def _serve(conn: Connection, render: bool, image_size: int, episode_steps: int) -> None:
    """A worker's loop: (command, env key, argument) in, (ok, result or traceback) out."""
    import ccdata.env

    # Ctrl-C reaches the whole process group; the evaluating process handles it and ends us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    envs: dict[int, Any] = {}
    try:
        while True:
            try:
                command, key, arg = conn.recv()
            except EOFError:  # the evaluating process is gone
                return
            if command == "close":
                return
            try:
                if command == "make":
                    envs[key] = ccdata.env.make_env(arg, render=render, image_size=image_size,
                                                    episode_steps=episode_steps)  # fmt: skip
                    out = None
                elif command == "reset":
                    out = envs[key].reset(seed=arg)
                elif command == "step":
                    out = envs[key].step(arg)
                else:
                    raise ValueError(f"unknown command {command!r}")
            except Exception:  # noqa: BLE001 - raised again by the evaluating process
                conn.send((False, traceback.format_exc()))
            else:
                conn.send((True, out))
    finally:
        for env in envs.values():
            env.close()


class EnvWorkers:
    """`workers` processes hosting environments of one kind (`render`, `image_size`,
    `episode_steps`); `make` places an environment on a given worker. Started at construction,
    ended by `close`."""

    def __init__(self, workers: int, *, render: bool, image_size: int,
                 episode_steps: int) -> None:  # fmt: skip
        if workers < 1:
            raise ValueError(f"EnvWorkers needs at least one worker, got {workers}")
        ctx = mp.get_context("spawn")  # a fresh simulator and GL context per process
        self._conns: list[Connection] = []
        self._procs: list[BaseProcess] = []
        self._waiting: list[deque[int]] = []
        for k in range(workers):
            parent, child = ctx.Pipe()
            args = (child, render, image_size, episode_steps)
            proc = ctx.Process(target=_serve, name=f"ccfit-env-worker-{k}", args=args,
                               daemon=True)  # fmt: skip
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
            self._waiting.append(deque())
        self._keys = 0

    @property
    def workers(self) -> int:
        return len(self._procs)

    def make(self, task_id: str, worker: int) -> RemoteEnv:
        """A new environment of task `task_id` on worker `worker % workers`."""
        env = RemoteEnv(self, worker % self.workers, self._keys)
        self._keys += 1
        self.send(env, "make", task_id)
        self.receive(env)
        return env

    def send(self, env: RemoteEnv, command: str, arg: Any) -> None:
        try:
            self._conns[env.worker].send((command, env.key, arg))
        except (BrokenPipeError, ConnectionError) as err:
            raise self._died(env.worker) from err
        self._waiting[env.worker].append(env.key)

    def receive(self, env: RemoteEnv) -> Any:
        """The result of `env`'s oldest call; a worker answers its calls in the order sent."""
        waiting = self._waiting[env.worker]
        if not waiting or waiting[0] != env.key:
            raise RuntimeError(f"environment {env.key} waited out of turn on worker "
                               f"{env.worker} (calls pending: {list(waiting)})")  # fmt: skip
        try:
            ok, out = self._conns[env.worker].recv()
        except (EOFError, ConnectionError) as err:
            raise self._died(env.worker) from err
        waiting.popleft()
        if not ok:
            raise RuntimeError(f"environment worker {env.worker} raised:\n{out}")
        return out

    def _died(self, worker: int) -> RuntimeError:
        proc = self._procs[worker]
        proc.join(JOIN_TIMEOUT_S)
        return RuntimeError(f"environment worker {worker} died (exit code {proc.exitcode})")

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close", -1, None))
            except (BrokenPipeError, ConnectionError):  # already gone
                pass
        for proc in self._procs:
            proc.join(JOIN_TIMEOUT_S)
            if proc.is_alive():
                proc.terminate()
                proc.join()
        for conn in self._conns:
            conn.close()
        self._conns, self._procs, self._waiting = [], [], []


class RemoteEnv:
    """An environment in an `EnvWorkers` process: `reset` and `step` as `TaskEnv`'s, and
    `step_async` / `step_wait` to step several side by side (`step_all`). Closed by its pool."""

    def __init__(self, pool: EnvWorkers, worker: int, key: int) -> None:
        self.pool, self.worker, self.key = pool, worker, key

    def reset(self, *, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
        self.pool.send(self, "reset", seed)
        return self.pool.receive(self)

    def step_async(self, action: np.ndarray) -> None:
        self.pool.send(self, "step", action)

    def step_wait(self) -> tuple:
        return self.pool.receive(self)

    def step(self, action: np.ndarray) -> tuple:
        self.step_async(action)
        return self.step_wait()

    def close(self) -> None:
        """Nothing: the pool's `close` ends the worker and its environments."""


def step_all(envs: Sequence, actions: Sequence[np.ndarray]) -> list[tuple]:
    """`env.step(action)` for each pair, in order; every remote environment is sent its action
    before any result is waited on, so they step in parallel (local ones step in turn)."""
    for env, action in zip(envs, actions, strict=True):
        if isinstance(env, RemoteEnv):
            env.step_async(action)
    return [env.step_wait() if isinstance(env, RemoteEnv) else env.step(action)
            for env, action in zip(envs, actions, strict=True)]  # fmt: skip


RUN_PROCESSES = 3
"""Processes a run with `train.parallel` on keeps busy without environment workers: training,
its evaluator and (in a curriculum) the from-scratch reference."""


def resolve_env_workers(setting: str, *, obs_mode: str, parallel: bool, episodes: int) -> int:
    """`--train.env_workers`: a count as given, or for 'auto' one worker per core the run
    leaves free (`RUN_PROCESSES`) with pixel observations and `parallel` on (else 0: a state
    observation steps in microseconds, and 0 keeps a run that shares the machine with others,
    e.g. a sweep's, to its cores; fewer than two free cores: 0); either way at most one per
    evaluation episode."""
    if setting != "auto":
        return min(int(setting), episodes)  # more would have nothing to step
    if obs_mode != "pixels" or not parallel:
        return 0
    free = available_cores() - RUN_PROCESSES
    return min(free, episodes) if free >= 2 else 0
