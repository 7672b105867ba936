"""What a ccdata dataset is, beyond LeRobot's own format: its features, the generation
metadata in `meta/ccdata.json`, the settings that identify it, the video encoding, and readers of
its per-episode ids (task, policy, seed) straight from the parquet files.
"""

from __future__ import annotations

import json
import logging
import os
from importlib import metadata
from pathlib import Path

import numpy as np

from ccdata.env import ACTION_REPEAT, FPS, PROPRIO_DIM
from ccdata.errors import InputError
from ccdata.render import CAMERAS
from ccdata.settings import (
    FORMAT_VERSION,
    IDENTITY_KEYS,
    LEGACY_IDENTITY,
    POLICY_ORDER,
    VIDEO_ENCODER,
    DatasetSettings,
)
from ccdata.suites import get_suite
from ccdata.tasks.base import STATE_DIM

__all__ = [  # the settings' constants are re-exported: older code imports them from here
    "CCDATA_META",
    "CODEBASE_VERSION",
    "FINAL_KEY",
    "FORMAT_VERSION",
    "IDENTITY_KEYS",
    "POLICY_ORDER",
    "VIDEO_ENCODER",
    "camera_key",
    "ccdata_metadata",
    "check_identity",
    "check_lerobot_info",
    "episode_table",
    "existing_keys",
    "features",
    "measure_dataset",
    "quiet_libraries",
    "read_ccdata_metadata",
    "read_codebase_version",
    "write_json",
]

CCDATA_META = "meta/ccdata.json"
"""Generation settings stored inside every dataset (relative to its root)."""

CODEBASE_VERSION = "v3.0"
"""LeRobot's dataset format version (meta/info.json's codebase_version) that ccdata writes."""

FINAL_KEY = "is_final_observation"
"""Per frame: True on the last frame of every episode, which holds the observation after the
episode's last action and no transition of its own (action zeros, next.reward 0)."""


def camera_key(camera: str) -> str:
    return f"observation.images.{camera}"


def features(image_size: int) -> dict:
    """LeRobot feature spec of a ccdata dataset."""
    image = {
        "dtype": "video",
        "shape": (image_size, image_size, 3),
        "names": ["height", "width", "channels"],
    }
    feats = {camera_key(c): dict(image) for c in CAMERAS}
    feats.update(
        {
            "observation.state": {
                "dtype": "float32",
                "shape": (PROPRIO_DIM,),
                "names": ["ee_x", "ee_y", "ee_z", "ee_vx", "ee_vy", "ee_vz", "gripper_opening"],
            },
            "observation.environment_state": {
                "dtype": "float32",
                "shape": (STATE_DIM,),
                "names": None,
            },
            "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
            "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
            "next.done": {"dtype": "bool", "shape": (1,), "names": None},
            "next.success": {"dtype": "bool", "shape": (1,), "names": None},
            "task_id_index": {"dtype": "int64", "shape": (1,), "names": None},
            "policy_index": {"dtype": "int64", "shape": (1,), "names": None},
            "episode_seed": {"dtype": "int64", "shape": (1,), "names": None},
            FINAL_KEY: {"dtype": "bool", "shape": (1,), "names": None},
        }
    )
    return feats


def _versions() -> dict:
    out = {}
    for dist in ("ccbench", "lerobot", "metaworld", "mujoco", "torch", "av"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def ccdata_metadata(config: DatasetSettings) -> dict:
    """The content of `meta/ccdata.json`: how the dataset was made, and how to read its ids."""
    suite = get_suite(config.suite)
    return {
        "format": FORMAT_VERSION,
        "suite": suite.name,
        "axis": suite.axis,
        "repo_id": config.repo_id,
        "identity": config.identity(),
        "config": {
            k: v for k, v in DatasetSettings.to_dict(config).items() if k not in ("root", "workers")
        },
        "tasks": [
            {"index": i, "id": t.id, "title": t.title, "instruction": t.instruction}
            for i, t in enumerate(suite.tasks)
        ],
        "instruction_to_task_id": {t.instruction: t.id for t in suite.tasks},
        "composition_matrix": suite.composition_matrix().astype(int).tolist(),
        "policies": list(POLICY_ORDER),
        "policy_params": {
            "oracle": {"kind": "scripted privileged-state oracle"},
            "noisy-oracle": {
                "kind": "oracle + Gaussian noise (noise_std), uniform action w.p. random_prob",
                "per_task": config.exploration_table(),
                "calibrated": config.noise_std is None and config.random_prob is None,
            },
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
        "env": {
            "fps": FPS,
            "action_repeat": ACTION_REPEAT,
            "episode_steps": config.episode_steps,
            "max_steps": config.max_steps,
        },
        "frame_convention": (
            "frames 0..T-1: obs_t, action_t, next.reward_t, next.done_t, next.success_t; "
            f"frame T ({FINAL_KEY}): obs_T after the last action, action 0, next.reward 0, "
            "next.done true, next.success = success of obs_T"
        ),
        "versions": _versions(),
    }


def read_ccdata_metadata(root: Path) -> dict:
    path = Path(root) / CCDATA_META
    if not path.is_file():
        raise InputError(f"{root} holds no {CCDATA_META}: not a ccdata dataset")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise InputError(f"{path} is corrupt ({err}); regenerate the dataset") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path} is corrupt (not a JSON object); regenerate the dataset")
    return meta


def read_codebase_version(root: Path) -> str:
    """The LeRobot format version that meta/info.json of the dataset at `root` states (ccdata
    writes CODEBASE_VERSION); InputError naming the file if it is missing, corrupt or not a
    LeRobot info.json."""
    path = Path(root) / "meta" / "info.json"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path} is missing") from None
    except (OSError, ValueError) as err:  # ValueError: not JSON, or not UTF-8
        raise InputError(f"{path} is corrupt ({err})") from None
    if not isinstance(info, dict) or "codebase_version" not in info:
        raise InputError(f"{path} is not a LeRobot info.json (it has no codebase_version)")
    return info["codebase_version"]


def check_lerobot_info(root: Path) -> None:
    """A dataset already at `root` must have a readable LeRobot v3 meta/info.json: generation
    adds to it and trusts it, and a dataset whose info.json is damaged cannot be loaded
    (before this check such a dataset was reported complete)."""
    try:
        version = read_codebase_version(root)
    except InputError as err:
        raise InputError(
            f"{err}; `ccdata verify --root {root}` lists what is damaged; remove the dataset to "
            "regenerate it"
        ) from None
    if version != CODEBASE_VERSION:
        raise InputError(
            f"{Path(root) / 'meta' / 'info.json'} says LeRobot codebase {version!r}, not "
            f"{CODEBASE_VERSION!r}; remove the dataset to regenerate it"
        )


def write_json(path: Path, content: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(content, indent=2, sort_keys=False))
    os.replace(tmp, path)


def check_identity(found: dict, config: DatasetSettings, where: Path) -> None:
    expected = {**LEGACY_IDENTITY, **config.identity()}
    found = {**LEGACY_IDENTITY, **found}  # a dataset made before a setting existed had its value
    diffs = [
        f"{k}: found {found.get(k)!r}, requested {expected[k]!r}"
        for k in expected
        if found.get(k) != expected[k]
    ]
    if diffs:
        raise InputError(
            f"{where} was generated with other settings; refusing to mix them "
            f"(use another --root, or delete it): " + "; ".join(diffs)
        )


def quiet_libraries() -> None:
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


def existing_keys(root: Path) -> list[str]:
    """Keys (task__policy__seed) of the episodes in a ccdata dataset, in episode order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    meta = read_ccdata_metadata(root)
    task_ids = [t["id"] for t in meta["tasks"]]
    policies = meta["policies"]
    cols = ["episode_index", "task_id_index", "policy_index", "episode_seed"]
    first: dict[int, str] = {}
    for path in sorted((root / "data").rglob("*.parquet")):
        try:
            table = pq.read_table(path, columns=cols).to_pydict()
        except (OSError, pa.ArrowException) as err:  # pyarrow's errors for a damaged file
            raise InputError(
                f"{path} is corrupt ({err}); `ccdata verify --root {root}` lists "
                "what is damaged; remove the dataset to regenerate it"
            ) from None
        for e, t, p, s in zip(*(table[c] for c in cols), strict=True):
            first.setdefault(int(e), f"{task_ids[int(t)]}__{policies[int(p)]}__{int(s)}")
    return [first[e] for e in sorted(first)]


def episode_table(root: Path) -> dict[str, np.ndarray]:
    """Per-episode arrays read from the data parquet files, in episode order: task_id_index,
    policy_index, episode_seed, frames (stored, final observation included), steps (actions
    taken), success, discounted return."""
    import pyarrow.parquet as pq

    from ccdata.scoring import discounted_return

    cols = [
        "episode_index",
        "task_id_index",
        "policy_index",
        "episode_seed",
        "next.reward",
        "next.success",
    ]
    paths = sorted((Path(root) / "data").rglob("*.parquet"))
    if FINAL_KEY in pq.read_schema(paths[0]).names:
        cols.append(FINAL_KEY)
    tables = [pq.read_table(p, columns=cols).to_pydict() for p in paths]
    merged = {c: np.concatenate([np.asarray(t[c]) for t in tables]) for c in cols}
    final = (
        merged[FINAL_KEY].reshape(-1).astype(bool)
        if FINAL_KEY in merged
        else np.zeros(len(merged["episode_index"]), dtype=bool)
    )
    episodes = np.unique(merged["episode_index"])
    out = {
        k: []
        for k in (
            "episode_index",
            "task_id_index",
            "policy_index",
            "episode_seed",
            "frames",
            "steps",
            "success",
            "return",
        )
    }
    for e in episodes:
        m = merged["episode_index"] == e
        step = m & ~final
        out["episode_index"].append(int(e))
        for c in ("task_id_index", "policy_index", "episode_seed"):
            out[c].append(int(merged[c][m][0]))
        out["frames"].append(int(m.sum()))
        out["steps"].append(int(step.sum()))
        out["success"].append(bool(merged["next.success"][step].any()))
        out["return"].append(discounted_return(merged["next.reward"][step]))
    return {k: np.asarray(v) for k, v in out.items()}


def measure_dataset(root: Path, task_ids: list[str]) -> dict:
    """What a dataset holds, measured from its files: totals, bytes per 1000 stored frames, and
    per task and policy (in suite and plan order) episodes, frames, steps, success rate, mean
    discounted return and mean normalised return (None without an oracle reference)."""
    from ccdata.scoring import normalize

    root = Path(root)
    table = episode_table(root)
    rows = []
    for t, task_id in enumerate(task_ids):
        for p, policy in enumerate(POLICY_ORDER):
            m = (table["task_id_index"] == t) & (table["policy_index"] == p)
            if not m.any():
                continue
            try:
                norm = float(np.mean([normalize(task_id, r) for r in table["return"][m]]))
            except ValueError:
                norm = None
            rows.append(
                {
                    "task": task_id,
                    "policy": policy,
                    "episodes": int(m.sum()),
                    "frames": int(table["frames"][m].sum()),
                    "steps": int(table["steps"][m].sum()),
                    "success_rate": float(table["success"][m].mean()),
                    "mean_return": float(np.mean(table["return"][m])),
                    "mean_normalized_return": norm,
                }
            )
    frames = int(table["frames"].sum())

    def per_1000(sub: str) -> float:
        size = sum(p.stat().st_size for p in (root / sub).rglob("*") if p.is_file())
        return round(1000 * size / frames) if frames else 0

    return {
        "episodes": int(len(table["episode_index"])),
        "frames": frames,
        "steps": int(table["steps"].sum()),
        "bytes_per_1000_frames": {"videos": per_1000("videos"), "data": per_1000("data")},
        "per_task_policy": rows,
    }
