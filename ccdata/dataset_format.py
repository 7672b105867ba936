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
from typing import TYPE_CHECKING

import numpy as np

from ccdata.env import ACTION_REPEAT, EPISODE_STEPS, FPS, PROPRIO_DIM
from ccdata.render import CAMERAS
from ccdata.suites import get_suite
from ccdata.tasks.base import STATE_DIM

if TYPE_CHECKING:
    from ccdata.record import GenerateConfig

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


def camera_key(camera: str) -> str:
    return f"observation.images.{camera}"


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


def write_json(path: Path, content: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(content, indent=2, sort_keys=False))
    os.replace(tmp, path)


def check_identity(found: dict, config: GenerateConfig, where: Path) -> None:
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
