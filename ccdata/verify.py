"""`ccdata verify`'s engine: structural checks of a ccdata LeRobot v3 dataset.

`verify_dataset(root)` returns human-readable findings; an empty list means the dataset is
consistent. It reads metadata and parquet files fully but never decodes video frames (it counts
the containers' packets), so it is cheap enough for CI on small datasets.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ccdata.dataset_format import CODEBASE_VERSION, FINAL_KEY, FORMAT_VERSION
from ccdata.errors import InputError


def verify_dataset(root: str | Path) -> list[str]:
    """Findings about the dataset at `root` (empty = OK)."""
    root = Path(root)
    if not root.is_dir():
        return [f"{root}: no such directory"]
    findings: list[str] = []
    info = _load_json(root / "meta/info.json", findings)
    ccmeta = _load_json(root / "meta/ccdata.json", findings)
    if info is None:
        return findings
    features = info.get("features", {})
    if not isinstance(features, dict) or not all(isinstance(f, dict) for f in features.values()):
        return [*findings, "info.json features is not an object of feature objects"]
    _check_info(info, ccmeta, findings)
    if any(f.startswith("info.json lacks") for f in findings):
        return findings  # the rest is read through info.json's paths and features
    tasks = _read_tasks(root, info, findings)
    episodes = _read_episodes(root, info, findings)
    data = _read_data(root, info, findings)
    if data is not None:
        _check_frames(data, episodes, info, ccmeta, tasks, findings)
    if episodes is not None:
        _check_videos(root, info, episodes, findings)
    _check_stats(root, info, findings)
    return findings


def check_intact(root: Path, doing: str) -> None:
    """InputError unless the dataset at `root` passes `verify_dataset` (seconds: it decodes no
    video); `doing` says what would otherwise fail on it, for the message."""
    findings = verify_dataset(root)
    if findings:
        raise InputError(f"the dataset at {root} is damaged, so {doing} ({findings[0]}; "
                         f"`ccdata verify --root {root}` lists every finding): remove it to "
                         f"regenerate it")  # fmt: skip


def _load_json(path: Path, findings: list[str]) -> dict | None:
    if not path.is_file():
        findings.append(f"missing {path.relative_to(path.parent.parent)}")
        return None
    try:
        value = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        findings.append(f"unreadable {path.name}: {e}")
        return None
    if not isinstance(value, dict):
        findings.append(f"{path.name} is not a JSON object")
        return None
    return value


def _check_info(info: dict, ccmeta: dict | None, findings: list[str]) -> None:
    if info.get("codebase_version") != CODEBASE_VERSION:
        findings.append(
            f"info.json codebase_version is {info.get('codebase_version')!r}, "
            f"expected {CODEBASE_VERSION!r}"
        )
    for key in (
        "fps",
        "features",
        "total_episodes",
        "total_frames",
        "total_tasks",
        "data_path",
        "video_path",
    ):
        if key not in info:
            findings.append(f"info.json lacks {key!r}")
    if ccmeta is None:
        return
    from ccdata.dataset_format import features
    from ccdata.suites import SUITES

    identity = ccmeta.get("identity", {})
    if identity.get("format") != FORMAT_VERSION:
        findings.append(
            f"generated in ccdata format {identity.get('format')}, this version "
            f"writes format {FORMAT_VERSION} (final observations recorded): "
            "regenerate it"
        )
    if info.get("fps") != identity.get("fps"):
        findings.append(f"info.json fps {info.get('fps')} != generation fps {identity.get('fps')}")
    size = identity.get("image_size")
    if isinstance(size, int):
        expected = features(size)
        found = info.get("features", {})
        for name, spec in expected.items():
            got = found.get(name)
            if got is None:
                findings.append(f"feature {name!r} missing from info.json")
            elif got.get("dtype") != spec["dtype"] or list(got.get("shape", [])) != list(
                spec["shape"]
            ):
                findings.append(
                    f"feature {name!r} is {got.get('dtype')} {got.get('shape')}, "
                    f"expected {spec['dtype']} {list(spec['shape'])}"
                )
    suite = ccmeta.get("suite")
    if suite not in SUITES:
        findings.append(f"ccdata.json suite {suite!r} is not a known suite")
    else:
        ids = [t.get("id") for t in ccmeta.get("tasks", [])]
        if ids != list(SUITES[suite].task_ids):
            findings.append(
                f"ccdata.json tasks {ids} differ from suite {suite}'s "
                f"{list(SUITES[suite].task_ids)}"
            )


def _read_parquets(paths: list[Path], what: str, findings: list[str]):
    import pyarrow as pa
    import pyarrow.parquet as pq

    tables = []
    for path in paths:
        try:
            tables.append(pq.read_table(path))
        except Exception as e:  # noqa: BLE001 - any reader error is a finding
            findings.append(
                f"unreadable {what} file {path.name} ({path.parent.name}): {type(e).__name__}: {e}"
            )
    if not tables:
        return None
    try:
        return pa.concat_tables(tables, promote_options="default")
    except Exception as e:  # noqa: BLE001
        findings.append(f"{what} files have inconsistent schemas: {e}")
        return None


def _read_tasks(root: Path, info: dict, findings: list[str]) -> dict[int, str] | None:
    path = root / "meta/tasks.parquet"
    if not path.is_file():
        findings.append("missing meta/tasks.parquet")
        return None
    table = _read_parquets([path], "tasks", findings)
    if table is None:
        return None
    df = table.to_pandas()
    if "task_index" not in df:
        findings.append("meta/tasks.parquet has no task_index column")
        return None
    names = df["task"] if "task" in df else df.index
    tasks = {int(i): str(t) for i, t in zip(df["task_index"], names, strict=True)}
    if len(tasks) != info.get("total_tasks"):
        findings.append(
            f"info.json total_tasks {info.get('total_tasks')} != {len(tasks)} "
            "tasks in meta/tasks.parquet"
        )
    return tasks


def _read_folder(root: Path, folder: str, what: str, findings: list[str]):
    """The parquet files under `folder` as one table, or None with a finding."""
    paths = sorted((root / folder).rglob("*.parquet"))
    if not paths:
        findings.append(f"no {folder}/*.parquet files")
        return None
    return _read_parquets(paths, what, findings)


def _read_episodes(root: Path, info: dict, findings: list[str]):
    table = _read_folder(root, "meta/episodes", "episode metadata", findings)
    if table is None:
        return None
    df = table.to_pandas().sort_values("episode_index").reset_index(drop=True)
    if len(df) != info.get("total_episodes"):
        findings.append(
            f"info.json total_episodes {info.get('total_episodes')} != "
            f"{len(df)} episodes in meta/episodes"
        )
    if list(df["episode_index"]) != list(range(len(df))):
        findings.append("meta/episodes episode_index is not 0..N-1")
    if int(df["length"].sum()) != info.get("total_frames"):
        findings.append(
            f"info.json total_frames {info.get('total_frames')} != sum of "
            f"episode lengths {int(df['length'].sum())}"
        )
    return df


def _read_data(root: Path, info: dict, findings: list[str]):
    table = _read_folder(root, "data", "data", findings)
    if table is None:
        return None
    feats = info.get("features", {})
    expected = [k for k, v in feats.items() if v.get("dtype") not in ("video", "image")]
    missing = [k for k in expected if k not in table.column_names]
    if missing:
        findings.append(f"data files lack columns {missing}")
        return None
    if table.num_rows != info.get("total_frames"):
        findings.append(
            f"data files hold {table.num_rows} frames, info.json total_frames is "
            f"{info.get('total_frames')}"
        )
    data = {}
    for k in expected:
        col = table.column(k).to_pylist()
        arr = np.asarray(col, dtype=object if feats[k]["dtype"] == "string" else None)
        if arr.dtype.kind == "f" and np.isnan(arr).any():
            findings.append(f"column {k!r} holds NaN")
        data[k] = arr
    return data


def _check_frames(
    data: dict,
    episodes,
    info: dict,
    ccmeta: dict | None,
    tasks: dict[int, str] | None,
    findings: list[str],
) -> None:
    ep_col = data["episode_index"].reshape(-1)
    index = data["index"].reshape(-1)
    if not np.array_equal(np.sort(index), np.arange(len(index))):
        findings.append("global frame index is not 0..total_frames-1")
    task_ids = [t["id"] for t in ccmeta.get("tasks", [])] if ccmeta else None
    id_of_instruction = ccmeta.get("instruction_to_task_id", {}) if ccmeta else {}
    n_policies = len(ccmeta.get("policies", [])) if ccmeta else None
    lengths = (
        dict(zip(episodes["episode_index"], episodes["length"], strict=True))
        if episodes is not None
        else {}
    )
    for e in np.unique(ep_col):
        m = ep_col == e
        order = np.argsort(data["frame_index"].reshape(-1)[m])
        frame_index = data["frame_index"].reshape(-1)[m][order]
        where = f"episode {int(e)}"
        if not np.array_equal(frame_index, np.arange(m.sum())):
            findings.append(f"{where}: frame_index is not contiguous from 0")
        if lengths and lengths.get(e) != m.sum():
            findings.append(
                f"{where}: {m.sum()} frames in data, length {lengths.get(e)} in meta/episodes"
            )
        if "next.done" in data:
            done = data["next.done"].reshape(-1)[m][order].astype(bool)
            if FINAL_KEY in data:  # format 2: the last frame is the final observation
                final = data[FINAL_KEY].reshape(-1)[m][order].astype(bool)
                if not final[-1] or final[:-1].any():
                    findings.append(
                        f"{where}: its last frame, and only it, must be its final "
                        f"observation ({FINAL_KEY})"
                    )
                done = done[:-1] if final[-1] else done
            if len(done) and not done[-1]:
                findings.append(f"{where}: last step is not done (truncated episode)")
            if done[:-1].any():
                findings.append(f"{where}: done before its last step")
        if task_ids is None or "task_id_index" not in data:
            continue
        tid = np.unique(data["task_id_index"].reshape(-1)[m])
        if len(tid) != 1 or not 0 <= tid[0] < len(task_ids):
            findings.append(
                f"{where}: invalid task_id_index {tid.tolist()} for {len(task_ids)} tasks"
            )
            continue
        pid = np.unique(data["policy_index"].reshape(-1)[m])
        if len(pid) != 1 or not 0 <= pid[0] < n_policies:
            findings.append(f"{where}: invalid policy_index {pid.tolist()}")
        if len(np.unique(data["episode_seed"].reshape(-1)[m])) != 1:
            findings.append(f"{where}: several episode seeds")
        if tasks is not None:
            instr = {tasks.get(int(t)) for t in np.unique(data["task_index"].reshape(-1)[m])}
            ids = {id_of_instruction.get(i) for i in instr}
            if ids != {task_ids[int(tid[0])]}:
                findings.append(
                    f"{where}: instruction {sorted(map(str, instr))} does not "
                    f"match task {task_ids[int(tid[0])]!r}"
                )
    if episodes is not None and len(np.unique(ep_col)) != len(episodes):
        findings.append(
            f"data files hold {len(np.unique(ep_col))} episodes, meta/episodes {len(episodes)}"
        )


def _count_video_frames(path: Path) -> int:
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return sum(1 for p in container.demux(stream) if p.size > 0)


def _check_videos(root: Path, info: dict, episodes, findings: list[str]) -> None:
    fps = info.get("fps") or 1
    video_keys = [k for k, v in info.get("features", {}).items() if v.get("dtype") == "video"]
    for key in video_keys:
        cols = [
            f"videos/{key}/chunk_index",
            f"videos/{key}/file_index",
            f"videos/{key}/from_timestamp",
            f"videos/{key}/to_timestamp",
        ]
        if any(c not in episodes for c in cols):
            findings.append(f"meta/episodes lacks video columns for {key}")
            continue
        for (chunk, file), group in episodes.groupby(cols[:2]):
            rel = info["video_path"].format(
                video_key=key, chunk_index=int(chunk), file_index=int(file)
            )
            path = root / rel
            if not path.is_file():
                findings.append(f"missing video {rel}")
                continue
            try:
                n = _count_video_frames(path)
            except Exception as e:  # noqa: BLE001 - a broken container is a finding
                findings.append(f"unreadable video {rel}: {type(e).__name__}: {e}")
                continue
            if n != int(group["length"].sum()):
                findings.append(
                    f"video {rel} has {n} frames, its episodes {int(group['length'].sum())}"
                )
            span = (group[cols[3]] - group[cols[2]]) * fps
            bad = group["episode_index"][np.abs(span - group["length"]) > 0.5]
            if len(bad):
                findings.append(f"{key}: timestamps span != length for episodes {bad.tolist()[:5]}")


def _check_stats(root: Path, info: dict, findings: list[str]) -> None:
    path = root / "meta/stats.json"
    if not path.is_file():
        findings.append("missing meta/stats.json")
        return
    try:
        stats = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        findings.append(f"unreadable meta/stats.json: {e}")
        return
    if not isinstance(stats, dict):
        findings.append("meta/stats.json is not a JSON object")
        return
    for key, spec in info.get("features", {}).items():
        if spec.get("dtype") == "string":
            continue
        entry = stats.get(key)
        if not entry or any(s not in entry for s in ("mean", "std", "min", "max")):
            findings.append(f"meta/stats.json lacks stats for {key!r}")
