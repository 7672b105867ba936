"""Read a suite's LeRobot v3 dataset into whole episodes (numpy), fast.

LeRobot's `__getitem__` decodes video per item (~110 frames/s here). This reader instead takes
the layout from `LeRobotDatasetMetadata`, reads the parquet files with pyarrow, and decodes each
camera's video file once, sequentially, with PyAV, cutting it into episodes by the episodes
metadata (each episode's from/to timestamps inside its video file).

`ccfit.replay_prefill` turns the episodes into replay (the suite dataset seeds each task's replay).
"""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from ccdata.dataset_format import CCDATA_META, camera_key, read_ccdata_metadata
from ccdata.errors import InputError
from ccdata.render import CAMERAS

CAMERA_KEYS = {camera: camera_key(camera) for camera in CAMERAS}
"""Camera name (as in the env's obs dict) -> LeRobot video feature."""
PROPRIO_KEY = "observation.state"
"""7-D proprio: end-effector position, velocity, gripper opening."""
STATE_KEY = "observation.environment_state"
"""39-D privileged state."""
ACTION_KEY = "action"
REWARD_KEY = "next.reward"
SUCCESS_KEY = "next.success"
TASK_ID_INDEX_KEY = "task_id_index"
"""Per-frame index of the task id in the suite's order (names in meta/ccdata.json)."""
POLICY_INDEX_KEY = "policy_index"
"""Per-frame index of the policy that played the episode (names in meta/ccdata.json)."""
EPISODE_SEED_KEY = "episode_seed"
"""Per-frame layout seed: `make_env(task_id).reset(seed=...)` reproduces the episode."""
EPISODE_INDEX = "episode_index"
FRAME_INDEX = "frame_index"
TASK_INDEX = "task_index"
"""LeRobot's index into meta/tasks.parquet (the instruction string)."""


def resolve_source(source: str | Path, endpoint: str | None = None) -> Path:
    """A dataset's local root: a directory as given; a repo id from LeRobot's cache
    (`$HF_LEROBOT_HOME/<repo_id>`, where `ccdata generate` writes), else downloaded from the
    Hub endpoint (`endpoint`, else HF_ENDPOINT, else the public hub) through ccdata.hub."""
    path = Path(source)
    if path.is_dir():
        return path
    from lerobot.utils.constants import HF_LEROBOT_HOME

    from ccdata.hub import HubError, download_dataset

    local = HF_LEROBOT_HOME / str(source)
    if (local / "meta" / "info.json").is_file():
        return local
    try:
        return download_dataset(str(source), endpoint=endpoint)
    except HubError as e:
        raise InputError(
            f"cannot read LeRobot dataset {str(source)!r}: no such directory, and {e}"
        ) from None


@dataclass
class _Metadata:
    """The parts of a v3 dataset's meta/ the reader needs, read straight with pyarrow (LeRobot's
    metadata class goes through `datasets` and costs ~2 s even for a tiny dataset)."""

    info: dict
    episodes: pd.DataFrame
    """One row per episode (index: episode_index): data and video file locations, timestamps."""
    tasks: pd.DataFrame
    """Index: the task string; column task_index."""

    @property
    def fps(self) -> float:
        return float(self.info["fps"])

    @property
    def data_path(self) -> str:
        return self.info["data_path"]

    @property
    def video_path(self) -> str:
        return self.info["video_path"]

    @property
    def video_keys(self) -> list[str]:
        return [k for k, f in self.info["features"].items() if f["dtype"] == "video"]


def _open_metadata(source: str | Path, endpoint: str | None = None) -> tuple[_Metadata, Path]:
    """(metadata, root) for a local dataset directory or a Hub repo id."""
    root = resolve_source(source, endpoint)
    try:
        info = json.loads((root / "meta" / "info.json").read_text())
        if info.get("codebase_version") != "v3.0":
            raise ValueError(f"codebase_version {info.get('codebase_version')!r}, not v3.0")
        files = sorted((root / "meta" / "episodes").rglob("*.parquet"))
        if not files:
            raise ValueError("no meta/episodes/*.parquet")
        episodes = pa.concat_tables([pq.read_table(f) for f in files]).to_pandas()
        tasks = pq.read_table(root / "meta" / "tasks.parquet").to_pandas()
    except Exception as e:  # noqa: BLE001 - missing or corrupt metadata: one clear message
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"cannot read LeRobot dataset at {root}: {msg}") from e
    return _Metadata(info, episodes.set_index(EPISODE_INDEX), tasks), root


def dataset_meta(source: str | Path, endpoint: str | None = None) -> dict:
    """What a run records of a dataset beside its path, which alone does not say what lay
    there: its size, the SHA-256 of its frames (`content_sha256`) and, for a ccdata dataset
    (meta/ccdata.json), its repo id and the `ccdata generate` settings and package versions
    that made it."""
    meta, root = _open_metadata(source, endpoint)
    out = {k: meta.info.get(k) for k in ("total_episodes", "total_frames")}
    out["content_sha256"] = {part: content_sha256(root / part) for part in ("data", "videos")}
    if (root / CCDATA_META).is_file():
        made = read_ccdata_metadata(root)
        out |= {"repo_id": made.get("repo_id"), "generated_with": made.get("config"),
                "versions": made.get("versions")}  # fmt: skip
    return out


def content_sha256(folder: Path) -> str | None:
    """One SHA-256 over every file under `folder`, with its path there, in path order; None
    when there is no such folder. `data/` holds the frames a state run reads, `videos/` the
    cameras a pixel run reads: two datasets with the same settings and sizes can still differ
    (one regenerated on another machine kind, say), and these tell them apart."""
    if not folder.is_dir():
        return None
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(f"{path.relative_to(folder).as_posix()}\0{path.stat().st_size}\0".encode())
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _id_maps(root: Path) -> tuple[dict[str, int], dict[str, int]]:
    """task id -> task_id_index and policy name -> policy_index, from meta/ccdata.json."""
    if not (root / CCDATA_META).is_file():
        return {}, {}
    info = read_ccdata_metadata(root)
    tasks = {t["id"]: int(t["index"]) for t in info.get("tasks", [])}
    policies = {name: i for i, name in enumerate(info.get("policies", []))}
    return tasks, policies


def _index_of(value: str | int, names: dict[str, int], what: str) -> int:
    if isinstance(value, int | np.integer):
        return int(value)
    if value not in names:
        valid = ", ".join(names) or "(dataset has no meta/ccdata.json)"
        raise InputError(f"{what} {value!r} is not in this dataset; valid: {valid}")
    return names[value]


def _matches(table, column: str, index: int) -> np.ndarray:
    if column not in table.column_names:
        raise InputError(f"dataset has no {column!r} column to filter on")
    return _column(table, column).reshape(-1) == index


def _decode(path: Path, wanted: list[tuple[int, int]], fps: float) -> dict[int, np.ndarray]:
    """Frames of one video file whose indices fall in the [start, stop) ranges in `wanted`.

    Decodes sequentially from a keyframe before the first wanted frame to the last one.
    """
    import av

    first = min(a for a, _ in wanted)
    last = max(b for _, b in wanted)
    keep = np.zeros(last, dtype=bool)
    for a, b in wanted:
        keep[a:b] = True
    out: dict[int, np.ndarray] = {}
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        if first > 0 and stream.time_base is not None:
            container.seek(int(first / fps / stream.time_base), stream=stream, backward=True)
        for frame in container.decode(stream):
            idx = round(float(frame.pts * stream.time_base) * fps)
            if idx >= last:
                break
            if idx >= 0 and keep[idx]:
                out[idx] = frame.to_ndarray(format="rgb24")
    return out


def episode_lengths(source: str | Path, task: str | int, policy: str,
                    endpoint: str | None = None) -> list[int]:  # fmt: skip
    """Frames of each of `task`'s episodes by `policy` (names as `load_episodes` takes them),
    read from two index columns of the data files: what their episodes would weigh, without
    reading them."""
    meta, root = _open_metadata(source, endpoint)
    task_ids, policies = _id_maps(root)
    task_index = _index_of(task, task_ids, "task")
    policy_index = _index_of(policy, policies, "policy")
    counts: dict[int, int] = defaultdict(int)
    for rel in sorted({
        meta.data_path.format(chunk_index=int(r["data/chunk_index"]),
                              file_index=int(r["data/file_index"]))
        for _, r in meta.episodes.iterrows()
    }):  # fmt: skip
        table = pq.read_table(root / rel, columns=[TASK_ID_INDEX_KEY, POLICY_INDEX_KEY,
                                                   EPISODE_INDEX])  # fmt: skip
        mask = _matches(table, TASK_ID_INDEX_KEY, task_index)
        mask &= _matches(table, POLICY_INDEX_KEY, policy_index)
        for ep in _column(table, EPISODE_INDEX)[mask]:
            counts[int(ep)] += 1
    return [counts[ep] for ep in sorted(counts)]


def load_episodes(
    source: str | Path,
    task: str | int | None = None,
    policy: str | None = None,
    *,
    images: bool = True,
    endpoint: str | None = None,
) -> list[dict[str, np.ndarray]]:
    """Episodes of a LeRobot v3 dataset (local directory or Hub repo id), in episode order.

    task (a task id such as 'reach-xy', or its index in the suite) and policy (a name such as
    'oracle', or its index) keep only matching episodes; names resolve through the dataset's
    meta/ccdata.json. Each episode is a dict of numpy arrays keyed by feature name (length T,
    as stored), plus 'episode_index' (int), 'task' (instruction string), 'task_id' and 'policy'
    (names, when the dataset says them) and, per camera feature, uint8 (T, H, W, 3) frames when
    `images` is true.
    """
    meta, root = _open_metadata(source, endpoint)
    if len(meta.episodes) == 0:
        raise InputError(f"dataset {str(source)!r} has no episodes")
    ep_meta = meta.episodes
    fps = float(meta.fps)
    tasks_by_index = {int(i): str(t) for t, i in meta.tasks["task_index"].items()}
    task_ids, policies = _id_maps(root)
    task_names = {i: n for n, i in task_ids.items()}
    policy_names = {i: n for n, i in policies.items()}

    # ---- tabular data: read each needed parquet file once, keep the selected rows
    data_files = sorted({
        meta.data_path.format(chunk_index=int(r["data/chunk_index"]),
                              file_index=int(r["data/file_index"]))
        for _, r in ep_meta.iterrows()
    })  # fmt: skip
    skip = set(meta.video_keys) | {"index", "timestamp"}
    columns = [c for c in pq.read_schema(root / data_files[0]).names if c not in skip]
    rows: dict[int, list] = defaultdict(list)
    for rel in data_files:
        table = pq.read_table(root / rel, columns=columns)
        mask = np.ones(table.num_rows, dtype=bool)
        if task is not None:
            mask &= _matches(table, TASK_ID_INDEX_KEY, _index_of(task, task_ids, "task"))
        if policy is not None:
            mask &= _matches(table, POLICY_INDEX_KEY, _index_of(policy, policies, "policy"))
        if not mask.any():
            continue
        table = table.filter(pa.array(mask))
        # Group rows by episode with one sort instead of one scan per episode.
        ep_col = _column(table, EPISODE_INDEX)
        order = np.argsort(ep_col, kind="stable")
        eps, starts = np.unique(ep_col[order], return_index=True)
        stops = [*starts[1:], len(order)]
        for ep, a, b in zip(eps, starts, stops, strict=True):
            rows[int(ep)].append(table.take(pa.array(order[a:b])))
    if not rows:
        raise InputError(f"no episodes in {str(source)!r} match task={task!r} policy={policy!r}")

    episodes: dict[int, dict[str, np.ndarray]] = {}
    for ep, parts in sorted(rows.items()):
        cols = {c: np.concatenate([_column(p, c) for p in parts]) for c in parts[0].column_names}
        order = np.argsort(cols[FRAME_INDEX], kind="stable")
        out = {c: v[order] for c, v in cols.items()}
        out["task"] = tasks_by_index.get(int(out[TASK_INDEX][0]), "")
        out["episode_index"] = ep
        if TASK_ID_INDEX_KEY in out:
            out["task_id"] = task_names.get(int(out[TASK_ID_INDEX_KEY].reshape(-1)[0]))
        if POLICY_INDEX_KEY in out:
            out["policy"] = policy_names.get(int(out[POLICY_INDEX_KEY].reshape(-1)[0]))
        episodes[ep] = out

    # ---- video: decode each file once, hand each episode its frame range
    if images:
        for key in meta.video_keys:
            by_file: dict[tuple[int, int], list[tuple[int, int, int]]] = defaultdict(list)
            for ep in episodes:
                r = ep_meta.loc[ep]
                start = round(float(r[f"videos/{key}/from_timestamp"]) * fps)
                length = len(episodes[ep][FRAME_INDEX])
                f = (int(r[f"videos/{key}/chunk_index"]), int(r[f"videos/{key}/file_index"]))
                by_file[f].append((ep, start, start + length))
            for (chunk, file), spans in sorted(by_file.items()):
                rel = meta.video_path.format(video_key=key, chunk_index=chunk, file_index=file)
                frames = _decode(root / rel, [(a, b) for _, a, b in spans], fps)
                for ep, a, b in spans:
                    missing = [i for i in range(a, b) if i not in frames]
                    if missing:
                        raise InputError(
                            f"{rel}: episode {ep} lacks {len(missing)} of its {b - a} frames"
                        )
                    episodes[ep][key] = np.stack([frames[i] for i in range(a, b)])
    return [episodes[ep] for ep in sorted(episodes)]


def _column(table, name: str) -> np.ndarray:
    col = table.column(name).combine_chunks()
    if pa.types.is_fixed_size_list(col.type) or pa.types.is_list(col.type):
        # vectors: one flat buffer reshaped (T, D) rather than T Python lists
        return col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1)
    return col.to_numpy(zero_copy_only=False)
