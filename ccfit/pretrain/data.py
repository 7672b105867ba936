"""The pretraining data: the episodes of every task of the requested suites, read from the
suites' LeRobot datasets, as frames that went through the same preprocessing as live
observations (`ccfit.obs.obs_to_arrays`), and their seeded per-task train / held-out split.

A task in several suites (pnp-cube) is read once, from the first suite (in `ccdata.SUITES`
order) that holds it. A missing dataset is reported with the `ccdata generate` command that
makes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ccdata.errors import InputError
from ccdata.suites import SUITES

if TYPE_CHECKING:
    from ccfit.pretrain.config import PretrainConfig

SPLIT_TAG = 1
"""Seed stream of the episode split (the training loop samples batches from another)."""


def episode_arrays(episode: dict, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """One loaded episode -> (pixels uint8 (T, 9, S, S), proprio float32 (T, 7)), through
    `ccfit.obs.obs_to_arrays`, the path live observations take."""
    from ccfit.data import CAMERA_KEYS, PROPRIO_KEY
    from ccfit.obs import obs_to_arrays

    missing = [key for key in CAMERA_KEYS.values() if key not in episode]
    if missing:
        raise InputError(f"episode {episode.get('episode_index')} lacks {missing}")
    obs = {cam: episode[key][::stride] for cam, key in CAMERA_KEYS.items()}
    obs["proprio"] = np.asarray(episode[PROPRIO_KEY], dtype=np.float32)[::stride]
    arrays = obs_to_arrays(obs, "pixels")
    return arrays["pixels"], arrays["proprio"]


@dataclass
class FrameStore:
    """Frames of the selected episodes, kept per episode (no big concatenation)."""

    pixels: list[np.ndarray]
    """Per episode uint8 (T, 9, S, S)."""
    proprio: list[np.ndarray]
    """Per episode float32 (T, 7)."""
    episodes: list[dict]
    """Per episode: suite, task_id, episode_index, episode_seed, frames."""

    def index(self, which: list[int]) -> np.ndarray:
        """(N, 2) int64 (episode, frame) pairs of every frame of episodes `which`."""
        parts = [np.stack([np.full(len(self.pixels[e]), e), np.arange(len(self.pixels[e]))], 1)
                 for e in which]  # fmt: skip
        return np.concatenate(parts) if parts else np.zeros((0, 2), dtype=np.int64)

    def lengths(self) -> np.ndarray:
        """Frames of each episode, int64."""
        return np.array([len(p) for p in self.pixels], dtype=np.int64)

    def batch(self, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pix = np.stack([self.pixels[e][t] for e, t in pairs])
        prop = np.stack([self.proprio[e][t] for e, t in pairs])
        return pix, prop


def missing_datasets(config: PretrainConfig) -> dict[str, Path]:
    """Suite -> expected root of every requested suite whose dataset is absent."""
    from ccdata.dataset_format import CCDATA_META

    return {s: r for s, r in config.resolved_roots().items() if not (r / CCDATA_META).is_file()}


def _generate_command(suite: str, root: Path) -> str:
    from ccdata.settings import suite_dataset_root

    cmd = f"ccdata generate --suite {suite}"
    if root != suite_dataset_root(suite):
        cmd += f" --root {root}"
    return cmd


def check_datasets(config: PretrainConfig) -> None:
    """InputError naming every missing suite dataset and the command that makes it."""
    missing = missing_datasets(config)
    if missing:
        cmds = "; ".join(_generate_command(s, r) for s, r in missing.items())
        raise InputError(
            f"missing suite dataset(s) {', '.join(missing)} "
            f"(looked in {', '.join(str(r) for r in missing.values())}); run: {cmds}"
        )


def load_frames(config: PretrainConfig, progress: bool = False) -> tuple[FrameStore, list]:
    """The episodes of `config.policies` of every task of the config's suites, each task once.

    Returns (frames, per-suite manifest entries)."""
    from ccdata.dataset_format import read_ccdata_metadata
    from ccfit.data import dataset_meta

    check_datasets(config)
    store = FrameStore([], [], [])
    manifest = []
    taken: dict[str, str] = {}  # task id -> suite it was read from
    # Shared tasks are read from the first suite in ccdata's order, whatever order was asked.
    for suite in sorted(config.suites, key=list(SUITES).index):
        root = config.resolved_roots()[suite]
        try:
            meta = read_ccdata_metadata(root)
        except ValueError as err:  # check_datasets saw the file: it is corrupt
            raise InputError(f"cannot read dataset {root} ({suite}): {err}") from None
        if meta.get("suite") != suite:
            raise InputError(f"dataset {root} holds suite {meta.get('suite')!r}, not {suite!r}")
        size = int(meta.get("identity", {}).get("image_size", -1))
        if size != config.image_size:
            raise InputError(
                f"dataset {root} ({suite}) has {size} px images but the encoder is for "
                f"{config.image_size} px; regenerate it with `ccdata generate --suite {suite} "
                f"--image-size {config.image_size}` or set the image size to {size}"
            )
        task_ids = [t["id"] for t in meta["tasks"]]
        wanted = [t for t in task_ids if t not in taken]
        counts = {p: {t: 0 for t in wanted} for p in config.policies}
        for policy in config.policies:
            stride = config.frame_stride if policy == "oracle" else config.explore_frame_stride
            for ep in _episodes(root, task_ids, wanted, policy):
                pix, prop = episode_arrays(ep, stride)
                store.pixels.append(pix)
                store.proprio.append(prop)
                store.episodes.append({
                    "suite": suite, "task_id": ep["task_id"], "policy": policy,
                    "episode_index": int(ep["episode_index"]),
                    "episode_seed": int(np.asarray(ep["episode_seed"]).reshape(-1)[0]),
                    "frames": len(pix),
                })  # fmt: skip
                counts[policy][ep["task_id"]] += 1
            absent = [t for t, n in counts[policy].items() if n == 0]
            if absent:
                more = "--episodes 50" if policy == "oracle" else "--explore-episodes 25"
                raise InputError(
                    f"dataset {root} ({suite}) has no {policy} episodes of {absent}; run "
                    f"`{_generate_command(suite, root)} {more}`"
                )
        for t in wanted:
            taken[t] = suite
        manifest.append({
            "suite": suite, "root": str(root), **dataset_meta(root),
            "render": meta.get("render"), "oracle_episodes": counts["oracle"],
            **{f"{p}_episodes": counts[p] for p in config.policies if p != "oracle"},
            "shared_tasks_read_elsewhere": {t: taken[t] for t in task_ids if t not in wanted},
        })  # fmt: skip
        if progress:
            read = ", ".join(f"{sum(c.values())} {p}" for p, c in counts.items())
            print(f"{suite}: {read} episodes of {len(wanted)} task(s)")
    return store, manifest


def _episodes(root: Path, task_ids: list[str], wanted: list[str], policy: str) -> list[dict]:
    """`policy`'s episodes of the tasks `wanted` of the dataset at `root`: one pass over each
    video file when every task is wanted, else task by task (a shared task's frames are not
    decoded twice)."""
    from ccfit.data import load_episodes

    def load(task_id: str | None) -> list[dict]:
        try:
            return load_episodes(root, task=task_id, policy=policy)
        except ValueError as err:
            if "no episodes" in str(err):
                return []  # reported by the caller with the command that fixes it
            raise

    if len(wanted) == len(task_ids):
        return [e for e in load(None) if e["task_id"] in wanted]
    return [e for t in wanted for e in load(t)]


def split_episodes(episodes: list[dict], fraction: float, seed: int) -> tuple[list, list]:
    """(train, held-out) episode positions: per task, round(fraction * n) held out (at most
    n - 1); if that holds out nothing while there are >= 2 episodes, one random episode."""
    rng = np.random.default_rng([seed, SPLIT_TAG])
    by_task: dict[str, list[int]] = {}
    for i, ep in enumerate(episodes):
        by_task.setdefault(ep["task_id"], []).append(i)
    held: list[int] = []
    for task in sorted(by_task):
        idx = by_task[task]
        n = min(int(math.floor(fraction * len(idx) + 0.5)), len(idx) - 1)
        held += [idx[j] for j in rng.permutation(len(idx))[:n]]
    if not held and fraction > 0 and len(episodes) >= 2:
        held = [int(rng.integers(len(episodes)))]
    held_set = set(held)
    return [i for i in range(len(episodes)) if i not in held_set], sorted(held)


class BatchSampler:
    """Draws a training batch of (episode, frame) pairs from `pairs`: uniformly over all of
    them ('all'), or uniformly within one suite, the suite drawn in proportion to its frames
    ('suite': every frame as likely as under 'all', a batch's frames from one scene)."""

    def __init__(self, store: FrameStore, pairs: np.ndarray, batch_from: str) -> None:
        self.pairs = pairs
        self.groups: list[np.ndarray] = []
        if batch_from == "suite":
            suite_of = np.array([ep["suite"] for ep in store.episodes])[pairs[:, 0]]
            self.groups = [np.flatnonzero(suite_of == s) for s in dict.fromkeys(suite_of)]
        elif batch_from != "all":
            raise ValueError(f"unknown batch_from {batch_from!r}")
        sizes = np.array([len(g) for g in self.groups], dtype=np.float64)
        self.weights = sizes / sizes.sum() if self.groups else None

    def __call__(self, size: int, rng: np.random.Generator) -> np.ndarray:
        if not self.groups:
            return self.pairs[rng.integers(0, len(self.pairs), size)]
        group = self.groups[rng.choice(len(self.groups), p=self.weights)]
        return self.pairs[group[rng.integers(0, len(group), size)]]
