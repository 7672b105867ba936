"""The offline track's data: each task's dataset episodes split by episode into training and
held-out ones; the training episodes as the task's replay, the held-out ones as a fixed set of
scoring windows.

The split is a function of the dataset's episode list, the run's seed and `fit.holdout`: per
task, a seeded permutation of its episodes, the first share held out. The scored windows
(context + horizon consecutive rows inside one held-out episode) are drawn once, seeded, from
every such position. Both are written to the run directory (`split.json`), and a resumed run
checks that the dataset still gives the same split. Held-out rows never reach training: the
training replay is built from the training episodes only, and the continual methods (ER's
memory, EWC's Fisher, PackNet's retraining) read nothing but that replay.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ccdata.errors import InputError
from ccfit.data import ACTION_KEY, load_episodes, resolve_source
from ccfit.io import atomic_write_json, derived_seed
from ccfit.models.base import Batch, WorldModel
from ccfit.offline.config import OfflineConfig
from ccfit.replay import ReplayBuffer
from ccfit.replay_prefill import check_render, replay_items
from ccfit.train.evaluate import REPLAY_TAG
from ccfit.train.run import render_settings

SPLIT = "split.json"
SPLIT_TAG, WINDOW_TAG = 20, 21
"""Seed streams of the episode split and of the scored windows (beside ccfit.train's)."""


def dataset_source(cfg: OfflineConfig) -> str:
    """The dataset the run fits: `cfg.dataset`, or for 'auto' the suite's local dataset (an
    InputError naming the command that makes it when there is none)."""
    if cfg.dataset != "auto":
        return cfg.dataset
    from ccdata.settings import suite_dataset_root

    root = suite_dataset_root(cfg.suite)
    if not (root / "meta" / "info.json").is_file():
        raise InputError(f"no dataset of suite {cfg.suite} at {root}: generate it with "
                         f"`ccdata generate --suite {cfg.suite}` or pass --dataset "
                         "REPO_ID_OR_DIR")  # fmt: skip
    return str(root)


@dataclass
class TaskSplit:
    """One task's episodes (dataset episode indices) and its scored windows."""

    train: list[int]
    heldout: list[int]
    windows: list[tuple[int, int]]
    """(held-out episode index, first row) of each scored window, in order."""


def make_splits(cfg: OfflineConfig, source: str) -> dict[str, TaskSplit]:
    """Every task's split (reads the dataset's tables, no images): InputError for a missing
    dataset, a task with fewer than two episodes, or held-out episodes too short to score."""
    root = str(resolve_source(source, cfg.dataset_endpoint))
    if cfg.obs == "pixels":
        check_render(root, render_settings(cfg), cfg.dataset_endpoint)
    fit, out = cfg.fit, {}
    for i, task in enumerate(cfg.tasks):
        episodes = load_episodes(root, task=task, images=False)
        frames = {int(ep["episode_index"]): len(ep[ACTION_KEY]) for ep in episodes}
        order = sorted(frames)
        if len(order) < 2:
            raise InputError(f"task {task} has {len(order)} episode(s) in {source}: the offline "
                             "track needs two or more (one to fit, one held out)")  # fmt: skip
        k = min(len(order) - 1, max(1, round(fit.holdout * len(order))))
        perm = np.random.default_rng(derived_seed(cfg.seed, SPLIT_TAG, 0, i)).permutation(order)
        heldout, train = sorted(int(e) for e in perm[:k]), sorted(int(e) for e in perm[k:])
        # A window starting at row s of an episode of n frames needs s + rows <= n (a dataset
        # episode of n frames is at least n replay rows in every observation mode).
        spots = [(e, s) for e in heldout for s in range(frames[e] - fit.rows + 1)]
        if not spots:
            raise InputError(f"task {task}: no held-out episode has {fit.rows} frames (context "
                             f"+ horizon); lower --fit.context/--fit.horizon or raise "
                             "--fit.holdout")  # fmt: skip
        rng = np.random.default_rng(derived_seed(cfg.seed, WINDOW_TAG, 0, i))
        pick = np.sort(rng.choice(len(spots), size=min(fit.windows, len(spots)), replace=False))
        out[task] = TaskSplit(train, heldout, [spots[j] for j in pick])
    return out


def write_split(run_dir: Path, splits: dict[str, TaskSplit], source: str) -> None:
    """`split.json` in `run_dir`; an existing one must hold the same split (InputError)."""
    data = {"dataset": source, "tasks": {t: asdict(s) for t, s in splits.items()}}
    data = json.loads(json.dumps(data))  # tuples as lists, as read back
    path = Path(run_dir) / SPLIT
    if path.is_file():
        if json.loads(path.read_text())["tasks"] != data["tasks"]:
            raise InputError(
                f"{path}: the dataset no longer gives this run's episode split "
                "(was it regenerated?); use another --out or delete the run"
            )
        return
    atomic_write_json(path, data)


def load_task(cfg: OfflineConfig, source: str, model: WorldModel, task_index: int,
              split: TaskSplit, train: bool = True
              ) -> tuple[ReplayBuffer | None, Batch]:  # fmt: skip
    """Task `task_index`'s training replay (None unless `train`) and its scored held-out
    windows (rows x windows, on the CPU), both through `model.replay_obs` (a frozen encoder's
    latents) and labelled with the task index."""
    task = cfg.tasks[task_index]
    buffer = ReplayBuffer(None, seed=derived_seed(cfg.seed, REPLAY_TAG, 0, task_index),
                          obs_transform=model.replay_obs) if train else None  # fmt: skip
    held = ReplayBuffer(None, obs_transform=model.replay_obs)
    fitting, scoring, first_row = set(split.train), set(split.heldout), {}
    for episode, _, item in replay_items(source, task, cfg.obs, render_settings(cfg),
                                      cfg.dataset_endpoint):  # fmt: skip
        if episode in fitting and buffer is not None:
            buffer.add_episode(**item, task=task_index)
        elif episode in scoring:
            first_row[episode] = held.size
            held.add_episode(**item, task=task_index)
    starts = torch.tensor([first_row[e] + s for e, s in split.windows])
    windows = held.gather(starts, cfg.fit.rows)
    if bool(windows.is_first[1:].any()):
        raise InputError(f"task {task}: a scored window crosses an episode boundary (the "
                         "dataset's episodes are shorter than its tables say)")  # fmt: skip
    return buffer, windows
