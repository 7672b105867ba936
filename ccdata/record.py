"""`ccdata generate`'s engine: roll out a suite's policies and write one LeRobot v3 dataset.

Each episode is recorded into its own small finalized LeRobot dataset (a piece) in a journal
beside the target, and the pieces are merged into the target in plan order (`ccdata.journal`
describes the layout and why no interruption can leave a half-written dataset). Episodes are
identified by (task id, policy, episode seed); a run skips every episode already in the target
or the journal, so re-running the same command completes the requested counts without
duplicates. Workers (`workers > 1`) are spawned processes, each running `write_shard` on a
contiguous slice of the plan with its own environment; the merge puts pieces in plan order, so
the result does not depend on the number of workers.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
import zlib
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from ccdata.dataset_format import (
    FORMAT_VERSION,
    IDENTITY_KEYS,
    POLICY_ORDER,
    VIDEO_ENCODER,
    camera_key,
    episode_table,
    existing_keys,
    features,
    quiet_libraries,
    read_ccdata_metadata,
    write_json,
)
from ccdata.env import EPISODE_STEPS, FPS, make_env
from ccdata.journal import (
    JournalPaths,
    Merger,
    chunks_of,
    die_with_parent,
    finished_pieces,
    merge_pieces,
    prepare,
)
from ccdata.render import CAMERAS, RenderSettings
from ccdata.suites import SUITES, get_suite


@dataclass
class GenerateConfig:
    """Everything that determines a generated dataset. Validated on construction."""

    suite: str
    """Suite name (one of `ccdata.SUITES`); the dataset holds every task of the suite."""
    episodes: int = 50
    """Oracle episodes per task."""
    explore_episodes: int = 25
    """Episodes per task for each exploration policy (noisy-oracle and random)."""
    image_size: int = 64
    """Side of the square camera images in pixels."""
    seed: int = 0
    """Base seed; every episode seed derives from it, the task, the policy and the index."""
    workers: int = 1
    """Processes rolling out episodes in parallel (one environment each). No effect on content."""
    root: str | Path | None = None
    """Dataset directory; None -> LeRobot's default `$HF_LEROBOT_HOME/<repo_id>`, so that
    `LeRobotDataset(repo_id)` opens it with no other argument."""
    repo_id: str | None = None
    """LeRobot / Hub repository id; None -> `ccdata/<Suite>`."""
    noise_std: float = 0.3
    """Std of the Gaussian noise the noisy oracle adds to the oracle's action."""
    random_prob: float = 0.1
    """Probability that the noisy oracle takes a uniform random action instead."""
    shadows: bool = False
    """Render shadows (see `ccdata.RenderSettings`)."""
    reflections: bool = False
    """Render reflections."""
    skybox: bool = False
    """Render the skybox."""
    msaa_samples: int = 0
    """Multisample anti-aliasing samples."""
    max_steps: int | None = None
    """Cut every episode after this many agent steps (tests, previews); None -> full episodes
    (250 steps or success). A cut episode's last frame has `next.done` True."""

    def __post_init__(self) -> None:
        if self.suite not in SUITES:
            raise ValueError(f"unknown suite {self.suite!r}; valid suites: {', '.join(SUITES)}")
        for name in ("episodes", "explore_episodes"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.episodes + self.explore_episodes == 0:
            raise ValueError("episodes and explore_episodes are both 0: nothing to generate")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.max_steps is not None and not 1 <= self.max_steps <= EPISODE_STEPS:
            raise ValueError(
                f"max_steps must be in [1, {EPISODE_STEPS}] or None, got {self.max_steps}"
            )
        if self.noise_std < 0 or not 0.0 <= self.random_prob <= 1.0:
            raise ValueError("noise_std must be >= 0 and random_prob in [0, 1]")
        if self.repo_id is None:
            self.repo_id = f"ccdata/{self.suite}"
        if self.repo_id.count("/") != 1 or not all(self.repo_id.split("/")):
            raise ValueError(f"repo_id must look like 'owner/name', got {self.repo_id!r}")
        _ = self.render_settings  # validates image_size and msaa_samples

    @property
    def render_settings(self) -> RenderSettings:
        return RenderSettings(
            image_size=self.image_size,
            shadows=self.shadows,
            reflections=self.reflections,
            skybox=self.skybox,
            msaa_samples=self.msaa_samples,
        )

    @property
    def dataset_root(self) -> Path:
        if self.root is not None:
            return Path(self.root).expanduser().resolve()
        from lerobot.utils.constants import HF_LEROBOT_HOME

        return (HF_LEROBOT_HOME / self.repo_id).resolve()

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["root"] = str(self.dataset_root)
        return d

    def identity(self) -> dict:
        """The settings an existing dataset must share to be appended to."""
        ident = {k: getattr(self, k) for k in IDENTITY_KEYS}
        ident["render"] = self.render_settings.to_dict()
        ident["fps"] = FPS
        ident["video"] = VIDEO_ENCODER
        ident["format"] = FORMAT_VERSION
        return json.loads(json.dumps(ident))


# ── The plan ──────────────────────────────────────────────────────────────────────────────


@dataclass(frozen=True)
class EpisodeSpec:
    """One planned episode."""

    task_id: str
    task_index: int
    """Position of the task in the suite (the `task_id_index` column)."""
    policy: str
    index: int
    """Index among this task's episodes of this policy."""
    seed: int
    """Episode seed: `make_env(task_id).reset(seed=seed)` replays it."""

    @property
    def policy_index(self) -> int:
        return POLICY_ORDER.index(self.policy)

    @property
    def key(self) -> str:
        return f"{self.task_id}__{self.policy}__{self.seed}"


def episode_seed(seed: int, task_id: str, policy: str, index: int) -> int:
    """A 62-bit seed from (base seed, task, policy, index); stable across processes and runs.

    The task enters by a checksum of its id, so a task shared by several suites gets the same
    episodes in each of them."""
    entropy = [seed, zlib.crc32(task_id.encode()), POLICY_ORDER.index(policy), index]
    hi, lo = np.random.SeedSequence(entropy).generate_state(2, np.uint32)
    return int((int(hi) << 32 | int(lo)) >> 2)


def policy_seed(ep_seed: int) -> int:
    """The policy's own seed, decorrelated from the environment's stream of the same episode."""
    return int(np.random.SeedSequence([ep_seed, 0x9E3779B9]).generate_state(1, np.uint64)[0])


def plan(config: GenerateConfig) -> list[EpisodeSpec]:
    """Every episode of the dataset in order: per task, oracle then noisy-oracle then random."""
    counts = {
        "oracle": config.episodes,
        "noisy-oracle": config.explore_episodes,
        "random": config.explore_episodes,
    }
    specs = [
        EpisodeSpec(task.id, t, policy, i, episode_seed(config.seed, task.id, policy, i))
        for t, task in enumerate(get_suite(config.suite).tasks)
        for policy in POLICY_ORDER
        for i in range(counts[policy])
    ]
    if len({s.seed for s in specs}) != len(specs):  # 62-bit seeds: practically never
        raise RuntimeError("episode seed collision; choose another base seed")
    return specs


# ── Recording ─────────────────────────────────────────────────────────────────────────────


def _video_encoder():
    from lerobot.configs import RGBEncoderConfig

    return RGBEncoderConfig(**json.loads(json.dumps(VIDEO_ENCODER)))


def record_episode(dataset, env, spec: EpisodeSpec, config: GenerateConfig,
                   instruction: str) -> int:
    """Roll out `spec` in `env` and add its frames to `dataset` (not saved). Returns frames."""
    from ccdata.policies import make_policy

    policy = make_policy(spec.policy, spec.task_id, seed=policy_seed(spec.seed),
                         noise_std=config.noise_std, random_prob=config.random_prob)
    policy.reset()
    obs, _ = env.reset(seed=spec.seed)
    limit = config.max_steps or EPISODE_STEPS
    ids = {
        "task_id_index": np.array([spec.task_index], dtype=np.int64),
        "policy_index": np.array([spec.policy_index], dtype=np.int64),
        "episode_seed": np.array([spec.seed], dtype=np.int64),
    }
    for t in range(limit):
        action = np.asarray(policy.act(obs), dtype=np.float32)
        next_obs, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated or t + 1 == limit
        frame = {camera_key(c): obs[c] for c in CAMERAS}
        frame.update({
            "observation.state": obs["proprio"],
            "observation.environment_state": obs["state"],
            "action": action,
            "next.reward": np.array([reward], dtype=np.float32),
            "next.done": np.array([done], dtype=bool),
            "next.success": np.array([bool(info["success"])], dtype=bool),
            "task": instruction,
            **ids,
        })
        dataset.add_frame(frame)
        obs = next_obs
        if done:
            return t + 1
    raise AssertionError("unreachable: the loop ends on done")


def write_shard(
    config: GenerateConfig,
    specs: list[EpisodeSpec],
    pieces_dir: str | Path,
    on_piece: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Write each episode of `specs` as its own finalized LeRobot dataset in `pieces_dir`.

    An independent job (a process, a submitit/SLURM task): it needs only its arguments. It stops
    before the next episode when `<pieces_dir>/../STOP` exists. Returns the pieces' records."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    quiet_libraries()
    pieces_dir = Path(pieces_dir)
    stop_file = pieces_dir.parent / "STOP"
    suite = get_suite(config.suite)
    instructions = {t.id: t.instruction for t in suite.tasks}
    feats = features(config.image_size)
    done: list[dict] = []
    env, env_task = None, None
    try:
        for spec in specs:
            if stop_file.exists():
                break
            final = pieces_dir / spec.key
            if final.exists():
                continue
            if env_task != spec.task_id:
                if env is not None:
                    env.close()  # one render context per process at a time
                env = make_env(spec.task_id, render_settings=config.render_settings)
                env_task = spec.task_id
            tmp = pieces_dir / f".tmp-{spec.key}"
            shutil.rmtree(tmp, ignore_errors=True)
            start = time.perf_counter()
            ds = LeRobotDataset.create(
                f"{config.repo_id}-piece", fps=FPS, features=feats, root=tmp,
                robot_type="sawyer", rgb_encoder=_video_encoder(), streaming_encoding=True,
                encoder_threads=1,
            )
            try:
                frames = record_episode(ds, env, spec, config, instructions[spec.task_id])
                ds.save_episode()
                ds.finalize()
            except BaseException:
                _abandon(ds, tmp)
                raise
            record = {**dataclasses.asdict(spec), "key": spec.key, "frames": frames,
                      "seconds": time.perf_counter() - start}
            write_json(tmp / "piece.json", record)
            os.replace(tmp, final)
            done.append(record)
            if on_piece is not None:
                on_piece(record)
    finally:
        if env is not None:
            env.close()
    return done


def _abandon(ds, tmp: Path) -> None:
    """Drop an episode in progress: stop its encoder threads, delete its directory."""
    try:
        ds.clear_episode_buffer()
        ds.finalize()
    except Exception:  # noqa: BLE001 - best effort; the directory goes anyway
        pass
    shutil.rmtree(tmp, ignore_errors=True)


# ── generate ──────────────────────────────────────────────────────────────────────────────


def generate(
    config: GenerateConfig,
    on_episode: Callable[[dict], None] | None = None,
    progress: bool = True,
) -> tuple[Path, dict]:
    """Generate (or complete) the dataset of `config`. Returns (dataset root, summary).

    `on_episode(record)` is called in this process after each completed episode. A
    KeyboardInterrupt (Ctrl-C, or raised by `on_episode`) stops the workers after their current
    episode, merges every completed episode into a valid dataset, and is re-raised."""
    from tqdm.auto import tqdm

    paths = prepare(config)
    full_plan = plan(config)
    order = [s.key for s in full_plan]
    merge_pieces(config, order)  # pieces a killed run left behind
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    todo = [s for s in full_plan if s.key not in present]
    new_records: list[dict] = []
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc=f"{config.suite}", unit="ep", disable=not progress)

    def done_one(record: dict) -> None:
        new_records.append(record)
        bar.update(1)
        bar.set_postfix_str(f"{record['task_id']} {record['policy']}")
        if on_episode is not None:
            on_episode(record)

    interrupted = False
    merger = Merger(config, chunks_of([s.key for s in todo]))
    try:
        if config.workers == 1 or len(todo) <= 1:
            write_shard(config, todo, paths.pieces, on_piece=done_one)
        else:
            _run_workers(config, todo, paths, done_one)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
        merger.finish()
        merge_pieces(config, order)
        wall = time.perf_counter() - start  # end to end: the merge is part of the work
        (paths.work / "STOP").unlink(missing_ok=True)
    if interrupted:
        raise KeyboardInterrupt
    shutil.rmtree(paths.work, ignore_errors=True)
    return paths.root, summarize(paths.root, new_records, wall)


def _run_workers(config: GenerateConfig, todo: list[EpisodeSpec], paths: JournalPaths,
                 done_one: Callable[[dict], None]) -> None:
    slices = [list(s) for s in np.array_split(np.array(todo, dtype=object), config.workers)
              if len(s)]
    seen: set[str] = set(finished_pieces(paths))
    wanted = {s.key for s in todo}
    records = {}

    def poll() -> None:
        for key, piece in finished_pieces(paths).items():
            if key in wanted and key not in seen:
                seen.add(key)
                records[key] = json.loads((piece / "piece.json").read_text())
                done_one(records[key])

    pool = ProcessPoolExecutor(len(slices), mp_context=get_context("spawn"),
                               initializer=die_with_parent, initargs=(os.getpid(),))
    try:
        futures = [pool.submit(write_shard, config, s, paths.pieces) for s in slices]
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            poll()
            for f in finished:
                f.result()  # re-raise a worker's error here
    except BaseException:
        (paths.work / "STOP").touch()  # workers stop after their current episode
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    poll()


def summarize(root: Path, new_records: Iterable[dict] = (), wall_time: float | None = None
              ) -> dict:
    """Per task and policy: episodes, frames, success rate, mean normalised return (None without
    an oracle reference), and for this run's new episodes: count, seconds, frames/s."""
    from ccdata.scoring import normalize

    meta = read_ccdata_metadata(root)
    task_ids = [t["id"] for t in meta["tasks"]]
    table = episode_table(root)
    new = {}
    for r in new_records:
        agg = new.setdefault((r["task_id"], r["policy"]), [0, 0, 0.0])
        agg[0] += 1
        agg[1] += r["frames"]
        agg[2] += r["seconds"]
    rows = []
    for t, task_id in enumerate(task_ids):
        for p, policy in enumerate(meta["policies"]):
            m = (table["task_id_index"] == t) & (table["policy_index"] == p)
            if not m.any():
                continue
            try:
                norm = float(np.mean([normalize(task_id, r) for r in table["return"][m]]))
            except ValueError:
                norm = None
            n_new, f_new, s_new = new.get((task_id, policy), [0, 0, 0.0])
            rows.append({
                "task": task_id, "policy": policy, "episodes": int(m.sum()),
                "frames": int(table["frames"][m].sum()),
                "success_rate": float(table["success"][m].mean()),
                "mean_normalized_return": norm,
                "new_episodes": n_new, "wall_time_s": s_new,
                "frames_per_s": f_new / s_new if s_new > 0 else None,
            })
    new_frames = sum(r["frames"] for r in new_records)
    return {
        "root": str(root),
        "episodes": int(len(table["episode_index"])),
        "frames": int(table["frames"].sum()),
        "new_episodes": sum(r["new_episodes"] for r in rows),
        "wall_time_s": wall_time,
        "frames_per_s": new_frames / wall_time if wall_time else None,
        "per_task_policy": rows,
    }
