"""The processes a generation starts to write episodes and merge them (writers, the merger),
and ending any process it started (`end_processes`).

They are forked from one multiprocessing fork server that has imported their libraries once.
Spawning a fresh interpreter for each imported torch and LeRobot again every time (about 7 s of
CPU per writer or merger on a 2-core machine: more than the encoding of a short generation);
the fork server of a generating process imports them once and serves every later generation
of that process too. The generating process itself still imports neither torch nor LeRobot.

A forked process's parent in the OS is the fork server, so `die_with` watches the generating
process itself: killing it must leave no orphan writing into its journal. `worker_pool` gives
the same guarantee to the spawned process pools of training (evaluation, a from-scratch
reference, a sweep's local jobs).
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from multiprocessing.context import BaseContext
from multiprocessing.process import BaseProcess

PRELOAD = (
    "ccdata.writer", "ccdata.journal",
    "lerobot.datasets.lerobot_dataset", "lerobot.datasets.aggregate",
)  # fmt: skip
"""What the fork server imports before it forks anything: all a writer or the merger imports."""


def process_context() -> BaseContext:
    """The multiprocessing context of every process a generation starts.

    The fork server starts with the environment and `sys.path` of the process's first
    generation and keeps them: environment variables set later do not reach its children."""
    ctx = get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    _start_fork_server()
    return ctx


def _start_fork_server() -> None:
    """Start the fork server now, with SIGINT ignored. It imports PRELOAD (seconds) before it
    ignores SIGINT itself, and a Ctrl-C meanwhile (it reaches the whole process group) killed
    it mid-import: starting a writer then failed with EOFError, and the generation hung at
    exit instead of stopping. Ignored, not blocked: the spawn resets the child's signal mask,
    while an ignored signal stays ignored across exec and Python's start. Its children
    ignore SIGINT anyway (the generating process decides what stops). A Ctrl-C in the few
    milliseconds of the spawn is lost here."""
    from multiprocessing import forkserver

    if threading.current_thread() is not threading.main_thread():
        return  # only the main thread sets handlers; the server then starts with a child
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)


class _Starter(threading.Thread):
    def __init__(self, processes: tuple[BaseProcess, ...]) -> None:
        super().__init__(name=f"start-{processes[0].name}", daemon=True)
        self.processes, self.error = processes, None

    def run(self) -> None:
        try:
            for process in self.processes:
                process.start()
        except BaseException as err:  # noqa: BLE001 - raised again by join, in the caller
            self.error = err

    def join(self, timeout: float | None = None) -> None:
        super().join(timeout)
        if self.error is not None:
            raise self.error


def available_cores() -> int:
    """The CPU cores this process may run on. Its affinity mask, not `os.cpu_count()`: under
    taskset, a cgroup cpuset or a SLURM allocation the machine's count overstates it."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity masks (macOS)
        return os.cpu_count() or 1


def start_soon(*processes: BaseProcess) -> threading.Thread:
    """Start `processes` from a helper thread, returned: join it before using them (the join
    raises what starting them raised).

    The fork server forks its first child only once its imports are done (seconds); the
    rollouts of the calling process need not wait for them."""
    starter = _Starter(processes)
    starter.start()
    return starter


def end_processes(processes: list[BaseProcess], grace_s: float) -> None:
    """Wait up to `grace_s` in all for `processes` to exit (a second Ctrl-C ends the wait),
    then kill those still running."""
    deadline = time.monotonic() + grace_s
    for p in processes:
        while p.pid is not None and p.is_alive() and time.monotonic() < deadline:
            try:
                p.join(0.2)
            except KeyboardInterrupt:
                deadline = 0
        if p.pid is not None and p.is_alive():
            p.kill()
            p.join()


def die_with(parent: int) -> None:
    """SIGKILL this process as soon as process `parent` (the generating process) is gone."""
    if hasattr(os, "pidfd_open"):  # Linux: woken the moment it exits
        try:
            fd = os.pidfd_open(parent)
        except ProcessLookupError:
            os._exit(1)

        def wait_for_exit() -> None:
            select.select([fd], [], [])
    else:

        def wait_for_exit() -> None:
            while _alive(parent):
                time.sleep(0.5)

    def watch() -> None:
        wait_for_exit()
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="ccdata-die-with-parent", daemon=True).start()


def worker_pool(max_workers: int, initializer: Callable | None = None, initargs: tuple = (),
                **kwargs) -> ProcessPoolExecutor:  # fmt: skip
    """A pool of spawned worker processes that end with this process. A worker of a plain pool
    outlives a parent killed by a signal (no clean-up runs) and waits forever, idle, or goes on
    computing beside the parent's successor; these die with it (`die_with`), then run
    `initializer(*initargs)`. What a job raises comes back whole where it can (`_Reported`).
    `kwargs`: `ProcessPoolExecutor`'s."""
    return _Pool(max_workers, mp_context=get_context("spawn"), initializer=_die_with_then,
                 initargs=(os.getpid(), initializer, initargs), **kwargs)  # fmt: skip


class _Pool(ProcessPoolExecutor):
    """A `ProcessPoolExecutor` whose jobs run as `_Reported`."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._started: dict = {}  # pid -> process: `shutdown` forgets them, `kill_workers` not

    def submit(self, fn, /, *args, **kwargs):
        future = super().submit(_Reported(fn), *args, **kwargs)
        self._started.update(self._processes or {})  # submitting starts the workers
        return future

    def kill_workers(self) -> None:
        """Shut the pool down and SIGKILL its workers now (Python 3.14's method of this name),
        also after a `shutdown(wait=False)`. That alone leaves the running jobs running, and the
        interpreter's exit then waits for them: an interrupted launcher would hang until they
        end."""
        workers = list({**self._started, **(self._processes or {})}.values())
        self.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            if worker.is_alive():
                worker.kill()
        for worker in workers:
            worker.join()


class _Reported:
    """`fn` run in a worker, with what it raises sent back to the caller. An exception that
    cannot be pickled (Inductor's errors hold closures) would come back as the pickling error
    instead ("cannot pickle 'cell' object": all a sweep's summary of a failed run said of a C++
    compile error): it comes back as a RuntimeError of one line, its type and the first line
    of its message; the whole of it is in the worker's traceback, the RuntimeError's cause."""

    def __init__(self, fn: Callable) -> None:
        self.fn = fn

    def __call__(self, *args, **kwargs):
        try:
            return self.fn(*args, **kwargs)
        except Exception as err:
            try:
                pickle.loads(pickle.dumps(err))  # some unpickle only with other arguments
            except Exception:
                raise RuntimeError(one_line(err)) from err
            raise


def one_line(err: BaseException) -> str:
    """An exception in one line: its type and its message's first line (later lines are
    detail or hints: Inductor's last one says how to get more logs)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__


def _die_with_then(parent: int, initializer: Callable | None, initargs: tuple) -> None:
    die_with(parent)
    if initializer is not None:
        initializer(*initargs)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
