"""Rolling out planned episodes and writing each as a piece: the work of a generation.

A two-stage pipeline. A rollout process steps the environment (physics and rendering: the part
`ccdata generate` cannot avoid) and queues each finished episode, as numpy arrays, for the
writer processes (`EpisodeQueue`); a writer encodes the camera videos, computes LeRobot's
statistics and writes the episode as its own finalized LeRobot dataset (a piece, see
`ccdata.journal`). The writing (video encoding, statistics, parquet, LeRobot's bookkeeping,
roughly 0.3 s per episode plus a few ms per frame) then overlaps the next rollout on another
core instead of delaying it, and the two never contend for one interpreter lock.

`write_shard` is one rollout (in the calling process) with one writer: a whole generation, or
one job of a cluster's. `ccdata.record` runs several rollout processes on one queue instead.
A piece is the same bytes whichever process rolled it out or wrote it, so the dataset does not
depend on how the plan was split.
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import shutil
import signal
import time
import traceback
from collections.abc import Callable, Iterable
from multiprocessing.context import BaseContext
from pathlib import Path

import numpy as np

from ccdata.dataset_format import (
    FINAL_KEY,
    camera_key,
    features,
    quiet_libraries,
    write_json,
)
from ccdata.env import FPS, make_env
from ccdata.episode_plan import EpisodeSpec, policy_seed
from ccdata.lerobot_speedups import faster_lerobot
from ccdata.processes import die_with, end_processes, process_context, start_soon
from ccdata.render import CAMERAS
from ccdata.settings import VIDEO_ENCODER, DatasetSettings
from ccdata.suites import get_suite

QUEUED_BYTES = 256 * 2**20
"""Memory that rolled-out episodes waiting for a writer may hold (a 250-step episode at 64 px
is about 9 MB; one episode may always wait, whatever its size)."""
PIECE_RECORD = "piece.json"


def episode_policy(spec: EpisodeSpec, config: DatasetSettings):
    """The policy that plays `spec`, reset: its kind and seed, with the dataset's exploration
    noise for its task."""
    from ccdata.policies import make_policy

    noise = config.exploration(spec.task_id)
    policy = make_policy(spec.policy, spec.task_id, seed=policy_seed(spec.seed),
                         noise_std=noise.noise_std, random_prob=noise.random_prob)  # fmt: skip
    policy.reset()
    return policy


def rollout_episode(env, spec: EpisodeSpec, config: DatasetSettings) -> dict[str, np.ndarray]:
    """Play `spec` in `env`. Returns the episode as stacked per-frame arrays keyed by dataset
    feature: one frame per step (obs_t, action_t, next.*), then the final observation (the
    observation the last action led to, a success state when the episode succeeded) as a frame
    of its own with no transition: action zeros, next.reward 0, `FINAL_KEY` true."""
    policy = episode_policy(spec, config)
    obs, _ = env.reset(seed=spec.seed)
    limit = config.max_steps or config.episode_steps
    observations, actions, rewards, dones, successes = [obs], [], [], [], []
    while len(actions) < limit:
        action = np.asarray(policy.act(obs), dtype=np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        actions.append(action)
        rewards.append(reward)
        successes.append(bool(info["success"]))
        dones.append(terminated or truncated or len(actions) == limit)
        observations.append(obs)
        if dones[-1]:
            break
    steps = len(actions)
    episode = {camera_key(c): np.stack([o[c] for o in observations]) for c in CAMERAS}
    episode.update(
        {
            "observation.state": np.stack([o["proprio"] for o in observations]),
            "observation.environment_state": np.stack([o["state"] for o in observations]),
            "action": np.concatenate([np.stack(actions), np.zeros((1, 4), np.float32)]),
            "next.reward": np.array([*rewards, 0.0], dtype=np.float32)[:, None],
            "next.done": np.array([*dones, True])[:, None],
            "next.success": np.array([*successes, successes[-1]])[:, None],
            FINAL_KEY: (np.arange(steps + 1) == steps)[:, None],
            "task_id_index": np.full((steps + 1, 1), spec.task_index, dtype=np.int64),
            "policy_index": np.full((steps + 1, 1), spec.policy_index, dtype=np.int64),
            "episode_seed": np.full((steps + 1, 1), spec.seed, dtype=np.int64),
        }
    )
    return episode


def _video_encoder():
    from lerobot.configs import RGBEncoderConfig

    return RGBEncoderConfig(**json.loads(json.dumps(VIDEO_ENCODER)))


def write_piece(
    config: DatasetSettings,
    spec: EpisodeSpec,
    episode: dict[str, np.ndarray],
    pieces_dir: Path,
    instruction: str,
    rollout_s: float = 0.0,
) -> dict:
    """Write one rolled-out episode as the finalized LeRobot dataset `pieces_dir/<key>`,
    atomically (built in `.tmp-<key>`, renamed when complete). Returns its record."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    start = time.perf_counter()
    final, tmp = pieces_dir / spec.key, pieces_dir / f".tmp-{spec.key}"
    shutil.rmtree(tmp, ignore_errors=True)
    frames = len(episode["action"])
    ds = LeRobotDataset.create(
        f"{config.repo_id}-piece",
        fps=FPS,
        features=features(config.image_size),
        root=tmp,
        robot_type="sawyer",
        rgb_encoder=_video_encoder(),
        streaming_encoding=True,
        encoder_threads=1,
        # LeRobot's streaming encoder drops a frame (with a warning) when its queue is full;
        # a queue that holds the whole episode can never be.
        encoder_queue_maxsize=frames + 1,
    )
    try:
        for i in range(frames):
            ds.add_frame({**{k: v[i] for k, v in episode.items()}, "task": instruction})
        ds.save_episode()
        ds.finalize()
    except BaseException:
        _abandon(ds, tmp)
        raise
    write_s = time.perf_counter() - start
    record = {
        **dataclasses.asdict(spec),
        "key": spec.key,
        "steps": frames - 1,
        "frames": frames,
        "rollout_s": rollout_s,
        "write_s": write_s,
        "seconds": rollout_s + write_s,
    }
    write_json(tmp / PIECE_RECORD, record)
    os.replace(tmp, final)
    return record


def _abandon(ds, tmp: Path) -> None:
    """Drop an episode in progress: stop its encoder threads, delete its directory."""
    try:
        ds.clear_episode_buffer()
        ds.finalize()
    except Exception:  # noqa: BLE001 - best effort; the directory goes anyway
        pass
    shutil.rmtree(tmp, ignore_errors=True)


class EpisodeQueue:
    """Rolled-out episodes on their way to the writer processes, and the stop signal of the
    writing. Made where the writers are started; a rollout process receives it as an argument
    at its start (multiprocessing queues travel only then).

    Held back by bytes, not episodes: rollouts never wait for a writer that is still starting
    (the fork server's imports take seconds, during which short oracle episodes pile up), and
    memory stays bounded whatever the image size."""

    def __init__(self, ctx: BaseContext) -> None:
        self.jobs = ctx.Queue()
        self.waiting_bytes = ctx.Value("q", 0)
        self.stop = ctx.Event()

    def put(
        self,
        spec: EpisodeSpec,
        episode: dict[str, np.ndarray],
        rollout_s: float,
        wait: Callable[[], None],
    ) -> bool:
        """Queue an episode once the episodes waiting leave it room (an empty queue always
        does), calling `wait()` until then. False if writing stopped meanwhile: not queued."""
        nbytes = sum(a.nbytes for a in episode.values())
        while not self.stop.is_set():
            with self.waiting_bytes.get_lock():
                waiting = self.waiting_bytes.value
                if waiting == 0 or waiting + nbytes <= QUEUED_BYTES:
                    self.waiting_bytes.value = waiting + nbytes
                    self.jobs.put((spec, episode, rollout_s, nbytes))
                    return True
            wait()
        return False

    def taken(self, nbytes: int) -> None:
        """A writer is done with an episode of `nbytes`."""
        with self.waiting_bytes.get_lock():
            self.waiting_bytes.value -= nbytes


def _writer_main(
    config: DatasetSettings, pieces_dir: Path, episodes: EpisodeQueue, results, parent: int
) -> None:
    """A writer process: write each episode taken from `episodes` until it takes the sentinel
    None, or until writing is stopped (the episodes still queued are then dropped)."""
    die_with(parent)
    # Ctrl-C reaches the whole process group: the generating process decides what stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    quiet_libraries()
    instructions = {t.id: t.instruction for t in get_suite(config.suite).tasks}
    try:
        with faster_lerobot():
            _write_jobs(config, pieces_dir, episodes, results, instructions)
    except BaseException:  # noqa: BLE001 - reported to the generating process, which raises it
        results.put(("error", f"a writer process failed:\n{traceback.format_exc()}"))
        return
    results.put(("exit", None))


def _write_jobs(
    config: DatasetSettings,
    pieces_dir: Path,
    episodes: EpisodeQueue,
    results,
    instructions: dict[str, str],
) -> None:
    while not episodes.stop.is_set():
        try:
            job = episodes.jobs.get(timeout=0.2)
        except queue.Empty:
            continue
        if job is None:
            return
        spec, episode, rollout_s, nbytes = job
        try:
            record = write_piece(
                config, spec, episode, pieces_dir, instructions[spec.task_id], rollout_s
            )
        finally:
            episodes.taken(nbytes)
        results.put(("piece", record))


class GenerationError(RuntimeError):
    """A writer or rollout process failed (its traceback is in the message) or died."""


class Writers:
    """Writer processes sharing one `EpisodeQueue`, seen from the process that started them.

    Everything they report comes back on `results`, which rollout processes share to report
    their failures: a record per written piece (handed to `on_piece` and kept in `records`),
    a writer's exit, or an error, raised here as `GenerationError`."""

    def __init__(
        self,
        config: DatasetSettings,
        pieces_dir: Path,
        on_piece: Callable[[dict], None] | None,
        count: int = 1,
    ) -> None:
        ctx = process_context()
        self.episodes = EpisodeQueue(ctx)
        self.results = ctx.Queue()
        self.on_piece = on_piece
        self.records: list[dict] = []
        self.exits = 0
        self.processes = [
            ctx.Process(target=_writer_main, name=f"ccdata-writer-{i}", daemon=True,
                        args=(config, pieces_dir, self.episodes, self.results, os.getpid()))
            for i in range(count)
        ]  # fmt: skip
        self.starting = start_soon(*self.processes)

    def _handle(self, block: bool) -> bool:
        """Take one report; False when there was none."""
        try:
            kind, payload = self.results.get(timeout=0.2) if block else self.results.get_nowait()
        except queue.Empty:
            if self.starting.is_alive():
                return False
            self.starting.join()  # raises what starting the writers raised
            dead = [p for p in self.processes if not p.is_alive()]
            if len(dead) > self.exits:
                raise GenerationError(
                    f"a writer process died (exit code {dead[0].exitcode})"
                ) from None
            return False
        if kind == "error":
            raise GenerationError(payload)
        if kind == "exit":
            self.exits += 1
        else:
            self.records.append(payload)
            if self.on_piece is not None:
                self.on_piece(payload)
        return True

    def poll(self) -> None:
        """Handle every report that has arrived."""
        while self._handle(block=False):
            pass

    def wait(self) -> None:
        """Handle the reports of the next moment (0.2 s at most)."""
        if self._handle(block=True):
            self.poll()

    def finish(self) -> None:
        """Let the writers write everything queued, then wait for them to exit."""
        for _ in self.processes:
            self.episodes.jobs.put(None)
        while self.exits < len(self.processes):
            self._handle(block=True)
        self.starting.join()
        for p in self.processes:
            p.join()

    def abort(self, grace_s: float = 120) -> None:
        """Let each writer complete the piece it is writing (pieces are atomic) within
        `grace_s`, drop the rest."""
        self.episodes.stop.set()
        self.episodes.jobs.cancel_join_thread()  # episodes never written must not block exit
        self.starting.join()
        end_processes(self.processes, grace_s)
        try:  # report the pieces completed meanwhile; raise nothing more
            while True:
                kind, payload = self.results.get_nowait()
                if kind == "piece":
                    self.records.append(payload)
        except (queue.Empty, OSError, EOFError):
            pass


def roll_out(
    config: DatasetSettings,
    specs: Iterable[EpisodeSpec],
    episodes: EpisodeQueue,
    stop_file: Path,
    poll: Callable[[], None] = lambda: None,
) -> None:
    """Roll out each episode of `specs` and queue it for the writers, calling `poll()` after
    each one and while it waits for room. Stops before the next episode when `stop_file` exists
    or writing stopped."""

    def wait() -> None:
        poll()
        time.sleep(0.05)

    env, env_task = None, None
    try:
        for spec in specs:
            if stop_file.exists() or episodes.stop.is_set():
                return
            if env_task != spec.task_id:
                if env is not None:
                    env.close()  # one render context per process at a time
                env = make_env(
                    spec.task_id,
                    render_settings=config.render_settings,
                    episode_steps=config.episode_steps,
                )
                env_task = spec.task_id
            start = time.perf_counter()
            episode = rollout_episode(env, spec, config)
            if not episodes.put(spec, episode, time.perf_counter() - start, wait):
                return
            poll()
    finally:
        if env is not None:
            env.close()


def write_shard(
    config: DatasetSettings,
    specs: list[EpisodeSpec],
    pieces_dir: str | Path,
    on_piece: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Write each episode of `specs` as its own finalized LeRobot dataset in `pieces_dir`:
    rolled out here, written by a writer process.

    An independent job (a process, a submitit/SLURM task): it needs only its arguments. It stops
    before the next episode when `<pieces_dir>/../STOP` exists. Returns the pieces' records;
    `on_piece(record)` is called in this process as each piece is completed."""
    pieces_dir = Path(pieces_dir)
    todo = [s for s in specs if not (pieces_dir / s.key).exists()]
    if not todo:
        return []
    writers = Writers(config, pieces_dir, on_piece)
    try:
        roll_out(config, todo, writers.episodes, pieces_dir.parent / "STOP", writers.poll)
        writers.finish()
    except BaseException:
        writers.abort()
        raise
    return writers.records
