"""Rolling out planned episodes and writing each as a piece: the work of one generation job.

`write_shard` runs a two-stage pipeline. This process steps the environment (physics and
rendering: the part `ccdata generate` cannot avoid) and hands each finished episode, as numpy
arrays, to a writer process, which encodes the camera videos, computes LeRobot's statistics and
writes the episode as its own finalized LeRobot dataset (a piece, see `ccdata.journal`). The
writer's work (video encoding, statistics, parquet, LeRobot's bookkeeping, roughly 0.5 s per
episode plus a few ms per frame) then overlaps the next rollout on another core instead of
delaying it, and the two never contend for one interpreter lock. At most `QUEUED` episodes
wait between the stages.

Pieces are written in plan order by the one writer, and a piece is the same bytes whichever
process rolled it out, so the dataset does not depend on how the plan was split.
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
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ccdata.dataset_format import (
    FINAL_KEY,
    camera_key,
    features,
    quiet_libraries,
    write_json,
)
from ccdata.env import EPISODE_STEPS, FPS, make_env
from ccdata.episode_plan import EpisodeSpec, policy_seed
from ccdata.lerobot_speedups import faster_lerobot
from ccdata.processes import die_with, process_context, start_soon
from ccdata.render import CAMERAS
from ccdata.settings import VIDEO_ENCODER, DatasetSettings
from ccdata.suites import get_suite

QUEUED = 2
"""Rolled-out episodes that may wait for the writer (memory: one 250-step episode at 64 px is
about 9 MB)."""
PIECE_RECORD = "piece.json"


def rollout_episode(env, spec: EpisodeSpec, config: DatasetSettings) -> dict[str, np.ndarray]:
    """Play `spec` in `env`. Returns the episode as stacked per-frame arrays keyed by dataset
    feature: one frame per step (obs_t, action_t, next.*), then the final observation (the
    observation the last action led to, a success state when the episode succeeded) as a frame
    of its own with no transition: action zeros, next.reward 0, `FINAL_KEY` true."""
    from ccdata.policies import make_policy

    noise = config.exploration(spec.task_id)
    policy = make_policy(spec.policy, spec.task_id, seed=policy_seed(spec.seed),
                         noise_std=noise.noise_std, random_prob=noise.random_prob)
    policy.reset()
    obs, _ = env.reset(seed=spec.seed)
    limit = config.max_steps or EPISODE_STEPS
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
    episode.update({
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
    })
    return episode


def _video_encoder():
    from lerobot.configs import RGBEncoderConfig

    return RGBEncoderConfig(**json.loads(json.dumps(VIDEO_ENCODER)))


def write_piece(config: DatasetSettings, spec: EpisodeSpec, episode: dict[str, np.ndarray],
                pieces_dir: Path, instruction: str, rollout_s: float = 0.0) -> dict:
    """Write one rolled-out episode as the finalized LeRobot dataset `pieces_dir/<key>`,
    atomically (built in `.tmp-<key>`, renamed when complete). Returns its record."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    start = time.perf_counter()
    final, tmp = pieces_dir / spec.key, pieces_dir / f".tmp-{spec.key}"
    shutil.rmtree(tmp, ignore_errors=True)
    frames = len(episode["action"])
    ds = LeRobotDataset.create(
        f"{config.repo_id}-piece", fps=FPS, features=features(config.image_size), root=tmp,
        robot_type="sawyer", rgb_encoder=_video_encoder(), streaming_encoding=True,
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
    record = {**dataclasses.asdict(spec), "key": spec.key, "steps": frames - 1,
              "frames": frames, "rollout_s": rollout_s, "write_s": write_s,
              "seconds": rollout_s + write_s}
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


def _writer_main(config: DatasetSettings, pieces_dir: Path, jobs, results, stop,
                 parent: int) -> None:
    """The writer process: write each (spec, episode, rollout seconds) from `jobs` until the
    sentinel None, or until `stop` is set (then the episodes still queued are dropped)."""
    die_with(parent)
    # Ctrl-C reaches the whole process group: the rollout process decides what stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    quiet_libraries()
    instructions = {t.id: t.instruction for t in get_suite(config.suite).tasks}
    try:
        with faster_lerobot():
            _write_jobs(config, pieces_dir, jobs, results, stop, instructions)
    except BaseException:  # noqa: BLE001 - reported to the rollout process, which raises it
        results.put(("error", traceback.format_exc()))
        return
    results.put(("exit", None))


def _write_jobs(config: DatasetSettings, pieces_dir: Path, jobs, results, stop,
                instructions: dict[str, str]) -> None:
    while not stop.is_set():
        try:
            job = jobs.get(timeout=0.2)
        except queue.Empty:
            continue
        if job is None:
            return
        spec, episode, rollout_s = job
        results.put(("piece", write_piece(config, spec, episode, pieces_dir,
                                          instructions[spec.task_id], rollout_s)))


class WriterError(RuntimeError):
    """The writer process failed (its traceback is the message)."""


class _Writer:
    """The writer process and its two queues, seen from the rollout process."""

    def __init__(self, config: DatasetSettings, pieces_dir: Path,
                 on_piece: Callable[[dict], None] | None) -> None:
        ctx = process_context()
        self.jobs = ctx.Queue(maxsize=QUEUED)
        self.results = ctx.Queue()
        self.stop = ctx.Event()
        self.on_piece = on_piece
        self.records: list[dict] = []
        self.exited = False
        self.process = ctx.Process(
            target=_writer_main, name="ccdata-writer", daemon=True,
            args=(config, pieces_dir, self.jobs, self.results, self.stop, os.getpid()),
        )
        self.starting = start_soon(self.process)

    def _handle(self, block: bool) -> bool:
        """Take one message from the writer; False when there was none."""
        try:
            kind, payload = self.results.get(timeout=0.2) if block else self.results.get_nowait()
        except queue.Empty:
            if self.starting.is_alive():
                return False
            self.starting.join()  # raises what starting the writer raised
            if not self.process.is_alive() and not self.exited:
                raise WriterError(f"the writer process died (exit code {self.process.exitcode})"
                                  ) from None
            return False
        if kind == "error":
            self.exited = True
            raise WriterError(f"the writer process failed:\n{payload}")
        if kind == "exit":
            self.exited = True
        else:
            self.records.append(payload)
            if self.on_piece is not None:
                self.on_piece(payload)
        return True

    def poll(self) -> None:
        while self._handle(block=False):
            pass

    def submit(self, job) -> None:
        while True:
            self.poll()
            try:
                self.jobs.put(job, timeout=0.2)
                return
            except queue.Full:
                continue

    def finish(self) -> None:
        """Let the writer write everything submitted, then wait for it to exit."""
        self.submit(None)
        while not self.exited:
            self._handle(block=True)
        self.starting.join()
        self.process.join()

    def abort(self) -> None:
        """Let the writer complete the piece it is writing (pieces are atomic), drop the rest."""
        self.stop.set()
        self.starting.join()
        self.jobs.cancel_join_thread()  # episodes never written must not block our exit
        deadline = time.monotonic() + 120
        while self.process.is_alive() and time.monotonic() < deadline:
            try:
                self.process.join(0.2)
            except KeyboardInterrupt:  # a second Ctrl-C: still wait, briefly
                break
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        try:  # report the pieces it completed meanwhile; raise nothing more
            while True:
                kind, payload = self.results.get_nowait()
                if kind == "piece":
                    self.records.append(payload)
        except (queue.Empty, OSError, EOFError):
            pass


def write_shard(
    config: DatasetSettings,
    specs: list[EpisodeSpec],
    pieces_dir: str | Path,
    on_piece: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Write each episode of `specs` as its own finalized LeRobot dataset in `pieces_dir`.

    An independent job (a process, a submitit/SLURM task): it needs only its arguments. It stops
    before the next episode when `<pieces_dir>/../STOP` exists. Returns the pieces' records;
    `on_piece(record)` is called in this process as each piece is completed."""
    pieces_dir = Path(pieces_dir)
    stop_file = pieces_dir.parent / "STOP"
    todo = [s for s in specs if not (pieces_dir / s.key).exists()]
    if not todo:
        return []
    writer = _Writer(config, pieces_dir, on_piece)
    env, env_task = None, None
    try:
        for spec in todo:
            if stop_file.exists():
                break
            if env_task != spec.task_id:
                if env is not None:
                    env.close()  # one render context per process at a time
                env = make_env(spec.task_id, render_settings=config.render_settings)
                env_task = spec.task_id
            start = time.perf_counter()
            episode = rollout_episode(env, spec, config)
            writer.submit((spec, episode, time.perf_counter() - start))
        writer.finish()
    except BaseException:
        writer.abort()
        raise
    finally:
        if env is not None:
            env.close()
    return writer.records
