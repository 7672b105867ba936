"""`ccdata generate`'s engine: roll out a suite's policies and write one LeRobot v3 dataset.

How the work is laid out on disk (target root `R`, e.g. `$HF_LEROBOT_HOME/ccdata/Reach`):

- `R/` is always a finalized, readable LeRobot dataset (or absent). It is only ever replaced by
  an atomic rename of a freshly merged copy, so no interruption can leave it half-written.
- `R/../.<name>.ccdata-work/` is the journal of the run in progress: `settings.json` (the
  generation settings it belongs to) and `pieces/`, one small finalized LeRobot dataset per
  completed episode. An episode is written to `pieces/.tmp-<key>` and renamed to
  `pieces/<key>` only after LeRobot's `finalize()`, so a SIGKILL loses at most the episode in
  progress (its `.tmp-` directory is deleted by the next run).
- While episodes are being rolled out, a merger process (`merge_chunks`) aggregates each
  complete chunk of `GROUP` consecutive episodes into `batches/<n>` (again finalized before it
  is renamed into place, with `batch.json` naming its episodes), so most merging overlaps the
  rollouts instead of following them.
- At the end of a run, on Ctrl-C, or at the start of the next run after a SIGKILL, the batches
  and the remaining pieces are merged (with the existing `R`, if any) by
  `lerobot.datasets.aggregate` into `.<name>.ccdata-new`, which then replaces `R` (`R` ->
  `.ccdata-old`, new -> `R`, old deleted; a run killed between the renames is repaired on the
  next start).

Episodes are identified by (task id, policy, episode seed); a run skips every episode whose key
is already in `R` or in the journal, so re-running the same command completes the requested
counts without duplicates. Workers (`workers > 1`) are spawned processes, each running
`write_shard` on a contiguous slice of the plan with its own environment; the merge puts pieces
in plan order, so the result does not depend on the number of workers.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import sys
import time
import zlib
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from importlib import metadata
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from ccdata.env import ACTION_REPEAT, EPISODE_STEPS, FPS, PROPRIO_DIM, make_env
from ccdata.render import CAMERAS, RenderSettings
from ccdata.suites import SUITES, get_suite
from ccdata.tasks.base import STATE_DIM

POLICY_ORDER: tuple[str, ...] = ("oracle", "noisy-oracle", "random")
"""Policies in plan order; a frame's `policy_index` indexes this tuple."""

CCDATA_META = "meta/ccdata.json"
"""Generation settings stored inside every dataset (relative to its root)."""

FORMAT_VERSION = 1

VIDEO_ENCODER: dict = {
    "vcodec": "h264",
    "pix_fmt": "yuv444p",
    "crf": 0,
    "g": 10,
    "preset": "medium",
    "extra_options": {"bf": 0},
}
"""Camera video encoding. libx264 with crf 0 is lossless in YUV 4:4:4, so the only loss is the
RGB<->YUV rounding: ~52 dB PSNR on every frame (LeRobot's default AV1 4:2:0 crf 30 gives ~27 dB).
No B-frames keep presentation and decoding order equal, which keeps concatenated episode videos'
timestamps exact; a keyframe every 10 frames bounds the decoding work per random access."""

IDENTITY_KEYS = ("suite", "seed", "image_size", "noise_std", "random_prob", "max_steps")
"""Config fields that must match to append to an existing dataset (plus render, fps, video)."""

GROUP = 16
"""Datasets merged per `aggregate_datasets` call, and episodes per batch of the merger process;
merges are grouped in a tree because each call rewrites its growing output once per source
(quadratic in the number of sources)."""


def camera_key(camera: str) -> str:
    return f"observation.images.{camera}"


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


# ── Features and metadata ─────────────────────────────────────────────────────────────────


def features(image_size: int) -> dict:
    """LeRobot feature spec of a ccdata dataset."""
    image = {"dtype": "video", "shape": (image_size, image_size, 3),
             "names": ["height", "width", "channels"]}
    feats = {camera_key(c): dict(image) for c in CAMERAS}
    feats.update({
        "observation.state": {"dtype": "float32", "shape": (PROPRIO_DIM,), "names": [
            "ee_x", "ee_y", "ee_z", "ee_vx", "ee_vy", "ee_vz", "gripper_opening"]},
        "observation.environment_state": {"dtype": "float32", "shape": (STATE_DIM,),
                                          "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "task_id_index": {"dtype": "int64", "shape": (1,), "names": None},
        "policy_index": {"dtype": "int64", "shape": (1,), "names": None},
        "episode_seed": {"dtype": "int64", "shape": (1,), "names": None},
    })
    return feats


def _versions() -> dict:
    out = {}
    for dist in ("ccbench", "lerobot", "metaworld", "mujoco", "torch", "av"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def ccdata_metadata(config: GenerateConfig) -> dict:
    """The content of `meta/ccdata.json`: how the dataset was made, and how to read its ids."""
    suite = get_suite(config.suite)
    return {
        "format": FORMAT_VERSION,
        "suite": suite.name,
        "axis": suite.axis,
        "repo_id": config.repo_id,
        "identity": config.identity(),
        "config": {k: v for k, v in config.to_dict().items() if k not in ("root", "workers")},
        "tasks": [
            {"index": i, "id": t.id, "title": t.title, "instruction": t.instruction}
            for i, t in enumerate(suite.tasks)
        ],
        "instruction_to_task_id": {t.instruction: t.id for t in suite.tasks},
        "composition_matrix": suite.composition_matrix().astype(int).tolist(),
        "policies": list(POLICY_ORDER),
        "policy_params": {
            "oracle": {"kind": "scripted privileged-state oracle"},
            "noisy-oracle": {"noise_std": config.noise_std, "random_prob": config.random_prob},
            "random": {"kind": "uniform in [-1, 1]^4"},
        },
        "seeds": {
            "base": config.seed,
            "episode_seed": "SeedSequence([base, crc32(task_id), policy_index, index]) -> 62 bits",
            "policy_seed": "SeedSequence([episode_seed, 0x9E3779B9]) -> 64 bits",
        },
        "render": config.render_settings.to_dict(),
        "cameras": {c: camera_key(c) for c in CAMERAS},
        "video": VIDEO_ENCODER,
        "env": {"fps": FPS, "action_repeat": ACTION_REPEAT, "episode_steps": EPISODE_STEPS,
                "max_steps": config.max_steps},
        "frame_convention": "obs_t, action_t, next.reward_t, next.done_t, next.success_t",
        "versions": _versions(),
    }


def read_ccdata_metadata(root: Path) -> dict:
    path = Path(root) / CCDATA_META
    if not path.is_file():
        raise ValueError(f"{root} holds no {CCDATA_META}: not a ccdata dataset")
    return json.loads(path.read_text())


def _write_json(path: Path, content: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(content, indent=2, sort_keys=False))
    os.replace(tmp, path)


def _check_identity(found: dict, config: GenerateConfig, where: Path) -> None:
    expected = config.identity()
    diffs = [
        f"{k}: found {found.get(k)!r}, requested {expected[k]!r}"
        for k in expected
        if found.get(k) != expected[k]
    ]
    if diffs:
        raise ValueError(
            f"{where} was generated with other settings; refusing to mix them "
            f"(use another --root, or delete it): " + "; ".join(diffs)
        )


# ── Recording one episode ─────────────────────────────────────────────────────────────────


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


def _quiet_libraries() -> None:
    import av
    import datasets

    # LeRobot re-installs FFmpeg's own printer (restore_default_callback), which then prints
    # every encoder's statistics: raise FFmpeg's own threshold. PyAV's Python log callback
    # stays off (level None): with it on, FFmpeg's decoder threads take the GIL to log and
    # can deadlock a later decode in the same process.
    av.logging.set_level(None)
    av.logging.set_libav_level(av.logging.ERROR)
    datasets.disable_progress_bars()
    # Without system FFmpeg libraries LeRobot logs a page-long torchcodec traceback per process
    # before falling back to PyAV, which is what ccdata reads and writes with anyway.
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)


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

    _quiet_libraries()
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
            _write_json(tmp / "piece.json", record)
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


# ── Journal, merge, swap ──────────────────────────────────────────────────────────────────


@dataclass(frozen=True)
class _Paths:
    root: Path

    @property
    def work(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-work"

    @property
    def pieces(self) -> Path:
        return self.work / "pieces"

    @property
    def batches(self) -> Path:
        return self.work / "batches"

    @property
    def new(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-new"

    @property
    def old(self) -> Path:
        return self.root.parent / f".{self.root.name}.ccdata-old"


BATCH_RECORD = "batch.json"
"""In a finished batch: the keys of its episodes, in order."""


def _recover(paths: _Paths) -> None:
    """Finish or undo a swap that a killed run left half-done; drop incomplete leftovers."""
    if not paths.root.exists():
        if (paths.new / CCDATA_META).is_file():
            os.replace(paths.new, paths.root)
        elif paths.old.exists():
            os.replace(paths.old, paths.root)
    shutil.rmtree(paths.new, ignore_errors=True)
    shutil.rmtree(paths.old, ignore_errors=True)
    shutil.rmtree(paths.work / "merge", ignore_errors=True)
    (paths.work / "STOP").unlink(missing_ok=True)
    for journal in (paths.pieces, paths.batches):
        if journal.exists():
            for tmp in journal.glob(".tmp-*"):
                shutil.rmtree(tmp, ignore_errors=True)


def existing_keys(root: Path) -> list[str]:
    """Keys (task__policy__seed) of the episodes in a ccdata dataset, in episode order."""
    import pyarrow.parquet as pq

    meta = read_ccdata_metadata(root)
    task_ids = [t["id"] for t in meta["tasks"]]
    policies = meta["policies"]
    cols = ["episode_index", "task_id_index", "policy_index", "episode_seed"]
    first: dict[int, str] = {}
    for path in sorted((root / "data").rglob("*.parquet")):
        table = pq.read_table(path, columns=cols).to_pydict()
        for e, t, p, s in zip(*(table[c] for c in cols), strict=True):
            first.setdefault(int(e), f"{task_ids[int(t)]}__{policies[int(p)]}__{int(s)}")
    return [first[e] for e in sorted(first)]


def _pieces(paths: _Paths) -> dict[str, Path]:
    if not paths.pieces.exists():
        return {}
    return {p.name: p for p in paths.pieces.iterdir()
            if p.is_dir() and not p.name.startswith(".") and (p / "piece.json").is_file()}


def _batches(paths: _Paths) -> dict[tuple[str, ...], Path]:
    """Finished batches: their episode keys (in order) -> directory."""
    if not paths.batches.exists():
        return {}
    return {tuple(json.loads((b / BATCH_RECORD).read_text())["keys"]): b
            for b in paths.batches.iterdir()
            if b.is_dir() and not b.name.startswith(".") and (b / BATCH_RECORD).is_file()}


def chunks_of(keys: list[str]) -> list[list[str]]:
    """The batches a run's episodes (in plan order) are merged in: consecutive runs of `GROUP`;
    a shorter remainder is left to the final merge. Fixed by the run's episode list alone, so
    the merge tree, and with it every byte of the result, does not depend on timing."""
    return [keys[i:i + GROUP] for i in range(0, len(keys) - GROUP + 1, GROUP)]


def merge_batch(config: GenerateConfig, keys: list[str]) -> Path:
    """Aggregate the journal's pieces of `keys` (all finished) into one batch, atomically."""
    from lerobot.datasets.aggregate import aggregate_datasets

    paths = _Paths(config.dataset_root)
    final, tmp = paths.batches / keys[0], paths.batches / f".tmp-{keys[0]}"
    shutil.rmtree(tmp, ignore_errors=True)
    paths.batches.mkdir(parents=True, exist_ok=True)
    try:
        aggregate_datasets([config.repo_id] * len(keys), config.repo_id,
                           roots=[paths.pieces / k for k in keys], aggr_root=tmp)
        _write_json(tmp / BATCH_RECORD, {"keys": list(keys)})
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def merge_chunks(config: GenerateConfig, chunks: list[list[str]], finished) -> None:
    """What the merger process runs: batch each chunk, in order, as soon as all its pieces
    exist; return when all are batched or `finished` (an Event) is set, leaving the rest to the
    final merge. Needs only its arguments and the journal (an independent job)."""
    _quiet_libraries()
    paths = _Paths(config.dataset_root)
    done = set(_batches(paths))
    try:
        for keys in chunks:
            if tuple(keys) in done:
                continue
            while not all((paths.pieces / k / "piece.json").is_file() for k in keys):
                if finished.wait(0.25):
                    return
            if finished.is_set():
                return
            merge_batch(config, keys)
    except KeyboardInterrupt:
        return  # Ctrl-C reaches the whole process group; the main process merges the rest


def _merger_main(config: GenerateConfig, chunks: list[list[str]], finished, parent: int) -> None:
    _die_with_parent(parent)
    merge_chunks(config, chunks, finished)


def _die_with_parent(parent: int) -> None:
    """On Linux, be SIGKILLed when the generating process dies, so that killing it leaves no
    orphan writing into its journal."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # it died before prctl took effect
        os._exit(1)


def _aggregate(sources: list[Path], dst: Path, repo_id: str, scratch: Path) -> None:
    """Merge finalized datasets, in order, into a new dataset at `dst` (grouped in a tree)."""
    from lerobot.datasets.aggregate import aggregate_datasets

    level = 0
    while len(sources) > GROUP:
        groups = [sources[i:i + GROUP] for i in range(0, len(sources), GROUP)]
        merged = []
        for g, group in enumerate(groups):
            out = scratch / f"level{level}-{g:05d}"
            shutil.rmtree(out, ignore_errors=True)
            aggregate_datasets([repo_id] * len(group), repo_id, roots=group, aggr_root=out)
            merged.append(out)
        if level > 0:
            for s in sources:
                shutil.rmtree(s, ignore_errors=True)
        sources, level = merged, level + 1
    aggregate_datasets([repo_id] * len(sources), repo_id, roots=sources, aggr_root=dst)


def merge_pieces(config: GenerateConfig, order: list[str] | None = None) -> int:
    """Merge the journal (batches and pieces) after the episodes already at the root; swap
    atomically. `order`: the plan's keys, which fixes the episode order and the chunks.

    Journal entries whose episodes are already at the root are dropped. Returns the episodes
    added."""
    paths = _Paths(config.dataset_root)
    present = set(existing_keys(paths.root)) if paths.root.exists() else set()
    pieces, batches = _pieces(paths), _batches(paths)
    for keys in list(batches):
        if set(keys) & present:  # a run killed after its swap, before its clean-up
            shutil.rmtree(batches.pop(keys))
    for key in [k for k in pieces if k in present]:
        shutil.rmtree(pieces.pop(key))
    if not pieces and not batches:
        return 0
    _quiet_libraries()
    # Complete chunks the merger did not get to are batched here: the same tree either way.
    batched = {k for keys in batches for k in keys}
    for keys in chunks_of([k for k in order or [] if k not in present]):
        if all(k in pieces and k not in batched for k in keys):
            batches[tuple(keys)] = merge_batch(config, keys)
            batched.update(keys)
    rank = {k: i for i, k in enumerate(order or [])}
    entries = [(keys[0], path, list(keys)) for keys, path in batches.items()]
    entries += [(k, p, [k]) for k, p in pieces.items() if k not in batched]
    entries.sort(key=lambda e: (rank.get(e[0], len(rank)), e[0]))
    sources = ([paths.root] if paths.root.exists() else []) + [e[1] for e in entries]
    shutil.rmtree(paths.new, ignore_errors=True)
    scratch = paths.work / "merge"
    scratch.mkdir(parents=True, exist_ok=True)
    _aggregate(sources, paths.new, config.repo_id, scratch)
    shutil.rmtree(scratch, ignore_errors=True)
    from ccdata.cards import render_card

    (paths.new / "README.md").write_text(render_card(config.suite))  # the dataset card
    _write_json(paths.new / CCDATA_META, ccdata_metadata(config))  # written last: "complete"
    if paths.root.exists():
        os.replace(paths.root, paths.old)
    os.replace(paths.new, paths.root)
    shutil.rmtree(paths.old, ignore_errors=True)
    shutil.rmtree(paths.batches, ignore_errors=True)
    for p in pieces.values():
        shutil.rmtree(p, ignore_errors=True)
    return sum(len(e[2]) for e in entries)


def _prepare(config: GenerateConfig) -> _Paths:
    """Check the target and the journal belong to these settings; repair leftovers."""
    paths = _Paths(config.dataset_root)
    _recover(paths)
    if paths.root.exists():
        if not any(paths.root.iterdir()):
            paths.root.rmdir()
        else:
            _check_identity(read_ccdata_metadata(paths.root).get("identity", {}), config,
                            paths.root)
    settings = paths.work / "settings.json"
    if settings.is_file():
        _check_identity(json.loads(settings.read_text()), config, paths.work)
    paths.pieces.mkdir(parents=True, exist_ok=True)
    _write_json(settings, config.identity())
    return paths


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

    paths = _prepare(config)
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
    merger = _Merger(config, chunks_of([s.key for s in todo]))
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
        wall = time.perf_counter() - start
        merge_pieces(config, order)
        (paths.work / "STOP").unlink(missing_ok=True)
    if interrupted:
        raise KeyboardInterrupt
    shutil.rmtree(paths.work, ignore_errors=True)
    return paths.root, summarize(paths.root, new_records, wall)


class _Merger:
    """`merge_chunks` in a spawned process beside the rollouts (none when nothing is to batch)."""

    def __init__(self, config: GenerateConfig, chunks: list[list[str]]) -> None:
        self.process = None
        if not chunks:
            return
        ctx = get_context("spawn")
        self.finished = ctx.Event()
        self.process = ctx.Process(target=_merger_main, name="ccdata-merger", daemon=True,
                                   args=(config, chunks, self.finished, os.getpid()))
        self.process.start()

    def finish(self) -> None:
        """Let the merger complete the batch it is writing, then stop it."""
        if self.process is None:
            return
        self.finished.set()
        while True:
            try:
                self.process.join()
                return
            except KeyboardInterrupt:  # a second Ctrl-C: still wait, the batch is atomic
                continue


def _run_workers(config: GenerateConfig, todo: list[EpisodeSpec], paths: _Paths,
                 done_one: Callable[[dict], None]) -> None:
    slices = [list(s) for s in np.array_split(np.array(todo, dtype=object), config.workers)
              if len(s)]
    seen: set[str] = set(_pieces(paths))
    wanted = {s.key for s in todo}
    records = {}

    def poll() -> None:
        for key, piece in _pieces(paths).items():
            if key in wanted and key not in seen:
                seen.add(key)
                records[key] = json.loads((piece / "piece.json").read_text())
                done_one(records[key])

    pool = ProcessPoolExecutor(len(slices), mp_context=get_context("spawn"),
                               initializer=_die_with_parent, initargs=(os.getpid(),))
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


# ── Summary ───────────────────────────────────────────────────────────────────────────────


def episode_table(root: Path) -> dict[str, np.ndarray]:
    """Per-episode arrays read from the data parquet files: task_id_index, policy_index,
    episode_seed, frames, success, discounted return, in episode order."""
    import pyarrow.parquet as pq

    from ccdata.scoring import discounted_return

    cols = ["episode_index", "task_id_index", "policy_index", "episode_seed", "next.reward",
            "next.success"]
    tables = [pq.read_table(p, columns=cols).to_pydict()
              for p in sorted((Path(root) / "data").rglob("*.parquet"))]
    merged = {c: np.concatenate([np.asarray(t[c]) for t in tables]) for c in cols}
    episodes = np.unique(merged["episode_index"])
    out = {k: [] for k in ("episode_index", "task_id_index", "policy_index", "episode_seed",
                           "frames", "success", "return")}
    for e in episodes:
        m = merged["episode_index"] == e
        out["episode_index"].append(int(e))
        for c in ("task_id_index", "policy_index", "episode_seed"):
            out[c].append(int(merged[c][m][0]))
        out["frames"].append(int(m.sum()))
        out["success"].append(bool(merged["next.success"][m].any()))
        out["return"].append(discounted_return(merged["next.reward"][m]))
    return {k: np.asarray(v) for k, v in out.items()}


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
