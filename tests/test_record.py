"""ccdata.record / ccdata.verify on tiny Reach datasets (real MuJoCo, real LeRobot)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import ccdata
from ccdata.dataset_format import POLICY_ORDER, existing_keys, features
from ccdata.episode_plan import plan
from ccdata.errors import InputError
from ccdata.record import GenerateConfig, generate
from ccdata.verify import verify_dataset

TINY = dict(suite="Reach", episodes=1, explore_episodes=1, image_size=32, max_steps=12)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 99.0 if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def data_table(root: Path) -> dict[str, np.ndarray]:
    tables = [pq.read_table(p).to_pandas() for p in sorted((root / "data").rglob("*.parquet"))]
    import pandas as pd

    df = pd.concat(tables).sort_values("index")
    return {c: np.stack(df[c].to_numpy()) for c in df.columns}


def decode_all(root: Path, key: str) -> np.ndarray:
    import av

    frames = []
    for path in sorted((root / "videos" / key).rglob("*.mp4")):
        with av.open(str(path)) as c:
            frames += [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    return np.stack(frames)


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


def descendants(pid: int) -> list[int]:
    """Children, their children, and so on (Linux /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        for child in (task / "children").read_text().split():
            found += [int(child), *descendants(int(child))]
    return found


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("tiny") / "Reach"
    return generate(GenerateConfig(**TINY, root=root), progress=False)


def test_config_is_validated():
    with pytest.raises(ValueError, match="valid suites"):
        GenerateConfig("Nope")
    with pytest.raises(ValueError, match="workers"):
        GenerateConfig("Reach", workers=0)
    with pytest.raises(ValueError, match="max_steps"):
        GenerateConfig("Reach", max_steps=0)
    with pytest.raises(ValueError, match="repo id 'no-slash' must have the form 'ORG/NAME'"):
        GenerateConfig("Reach", repo_id="no-slash")
    with pytest.raises(ValueError, match="NAME may only use"):
        GenerateConfig("Reach", repo_id="ccdata/..")  # would be the cache folder itself
    assert GenerateConfig("Reach").repo_id == "ccdata/Reach"


def test_plan_is_deterministic_complete_and_distinct():
    cfg = GenerateConfig("Reach", episodes=3, explore_episodes=2)
    specs = plan(cfg)
    assert specs == plan(GenerateConfig("Reach", episodes=3, explore_episodes=2))
    assert len(specs) == 4 * (3 + 2 + 2)
    assert len({s.seed for s in specs}) == len(specs)
    assert [s.task_id for s in specs[::7]] == list(ccdata.get_suite("Reach").task_ids)
    assert [s.policy for s in specs[:7]] == ["oracle"] * 3 + ["noisy-oracle"] * 2 + ["random"] * 2
    # a different base seed gives different episodes; growing the counts keeps the old ones
    assert {s.seed for s in plan(GenerateConfig("Reach", seed=1, episodes=3))}.isdisjoint(
        s.seed for s in specs
    )
    assert {s.key for s in specs} <= {s.key for s in plan(GenerateConfig("Reach", episodes=5))}


def test_dataset_features_metadata_and_loading(tiny):
    root, summary = tiny
    info = json.loads((root / "meta/info.json").read_text())
    assert info["fps"] == 40 and info["codebase_version"] == "v3.0"
    for name, spec in features(32).items():
        assert info["features"][name]["dtype"] == spec["dtype"]
        assert tuple(info["features"][name]["shape"]) == tuple(spec["shape"])
    assert info["features"]["observation.images.topview"]["info"]["video.pix_fmt"] == "yuv444p"
    meta = json.loads((root / "meta/ccdata.json").read_text())
    assert [t["id"] for t in meta["tasks"]] == list(ccdata.get_suite("Reach").task_ids)
    assert meta["video"]["crf"] == 0 and meta["versions"]["lerobot"].startswith("0.6")
    # The noisy oracle's noise is each task's calibration, recorded per task.
    noisy = meta["policy_params"]["noisy-oracle"]
    assert noisy["calibrated"] and set(noisy["per_task"]) == set(ccdata.get_suite("Reach").task_ids)
    for task_id, noise in noisy["per_task"].items():
        assert noise == ccdata.get_task(task_id).exploration.to_dict()
    assert meta["identity"]["exploration"] == noisy["per_task"]

    assert summary["episodes"] == 12 == info["total_episodes"]
    rows = {(r["task"], r["policy"]): r for r in summary["per_task_policy"]}
    # A random episode is cut after 12 steps: 12 transitions + the final observation.
    assert len(rows) == 12 and rows[("reach-xy", "random")]["steps"] == 12
    assert rows[("reach-xy", "random")]["frames"] == 13
    assert summary["frames"] == summary["steps"] + 12
    assert all(r["new_episodes"] == 1 and r["frames_per_s"] > 0 for r in rows.values())

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("ccdata/Reach", root=root)
    assert len(ds) == info["total_frames"]
    item = ds[3]
    assert item["observation.images.frontview"].shape == (3, 32, 32)
    assert item["observation.state"].shape == (7,)
    assert item["observation.environment_state"].shape == (39,)
    assert item["action"].shape == (4,)
    assert (
        item["task"] == ccdata.get_task(meta["tasks"][int(item["task_id_index"])]["id"]).instruction
    )

    cols = data_table(root)
    assert cols["action"].dtype == np.float32 and cols["next.done"].dtype == bool
    keys = existing_keys(root)
    assert keys == [s.key for s in plan(GenerateConfig(**TINY))]  # plan order


def test_fidelity_and_replay_reproduce_live_steps(tiny):
    """Frames read back match the live render (>= 40 dB every camera); replayed actions
    reproduce the recorded states."""
    root, _ = tiny
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("ccdata/Reach", root=root)
    cols = data_table(root)
    meta = json.loads((root / "meta/ccdata.json").read_text())
    worst = {c: 99.0 for c in ccdata.CAMERAS}
    for policy in ("oracle", "random"):
        ep = next(
            e
            for e in np.unique(cols["episode_index"])
            if cols["policy_index"][cols["episode_index"] == e][0] == POLICY_ORDER.index(policy)
            and cols["task_id_index"][cols["episode_index"] == e][0] == 3
        )
        rows = np.flatnonzero(cols["episode_index"] == ep)
        task_id = meta["tasks"][3]["id"]
        env = ccdata.make_env(task_id, image_size=32)
        obs, _ = env.reset(seed=int(cols["episode_seed"][rows[0]]))
        for t, row in enumerate(rows):
            assert cols["frame_index"][row] == t
            np.testing.assert_array_equal(obs["state"], cols["observation.environment_state"][row])
            np.testing.assert_array_equal(obs["proprio"], cols["observation.state"][row])
            item = ds[int(row)]
            for cam in ccdata.CAMERAS:
                img = item[f"observation.images.{cam}"].permute(1, 2, 0).numpy()
                worst[cam] = min(worst[cam], psnr((img * 255).round(), obs[cam]))
            if cols["is_final_observation"][row]:
                break  # the observation after the last action: no action of its own
            obs, reward, term, trunc, info = env.step(cols["action"][row])
            assert reward == pytest.approx(float(cols["next.reward"][row]), abs=1e-6)
            assert info["success"] == bool(cols["next.success"][row])
        env.close()
        final = cols["is_final_observation"][rows].reshape(-1)
        assert final[-1] and not final[:-1].any()  # the last frame, and only it
        assert not cols["action"][rows[-1]].any() and cols["next.reward"][rows[-1]] == 0
        assert cols["next.done"][rows[-2:]].all() and not cols["next.done"][rows[:-2]].any()
    assert min(worst.values()) >= 40.0, worst


def test_workers_give_the_same_episodes(tiny, tmp_path):
    """Two worker processes write the same episodes as one (here: the oracle episodes, which
    keep their seeds whatever the counts, against the single-process fixture)."""
    root1, _ = tiny
    cfg = GenerateConfig(**{**TINY, "explore_episodes": 0}, root=tmp_path / "Reach", workers=2)
    root2, summary = generate(cfg, progress=False)
    assert summary["episodes"] == 4
    a, b = data_table(root1), data_table(root2)
    rows = np.flatnonzero(a["policy_index"] == POLICY_ORDER.index("oracle"))
    assert set(a) == set(b) and len(rows) == len(b["index"])
    for col in set(a) - {"index", "episode_index"}:
        np.testing.assert_array_equal(a[col][rows], b[col], err_msg=col)
    for cam in ccdata.CAMERAS:
        fa = decode_all(root1, f"observation.images.{cam}")[rows]
        fb = decode_all(root2, f"observation.images.{cam}")
        assert fa.shape == fb.shape and psnr(fa, fb) >= 40.0
    assert verify_dataset(root2) == []


def test_episode_queue_holds_back_by_bytes(monkeypatch):
    """Episodes queue until their bytes would pass the budget (one always fits); a put waits,
    calling `wait`, until a writer takes enough; a stopped queue takes nothing more."""
    from multiprocessing import get_context

    from ccdata import writer

    monkeypatch.setattr(writer, "QUEUED_BYTES", 1000)
    q = writer.EpisodeQueue(get_context("spawn"))
    spec = plan(GenerateConfig("Reach", episodes=1, explore_episodes=0))[0]
    big, small = {"x": np.zeros(1200, np.uint8)}, {"x": np.zeros(600, np.uint8)}
    never = lambda: pytest.fail("should not wait")  # noqa: E731
    assert q.put(spec, big, 0.0, never)  # over the budget, but the queue is empty
    waited = []

    def take_the_big_one() -> None:
        waited.append(1)
        if len(waited) == 3:
            assert q.jobs.get(timeout=5)[3] == 1200
            q.taken(1200)

    assert q.put(spec, small, 0.0, take_the_big_one) and len(waited) == 3
    assert q.put(spec, {"x": np.zeros(400, np.uint8)}, 0.0, never)  # 600 + 400 fit
    q.stop.set()
    assert not q.put(spec, small, 0.0, never)
    assert [q.jobs.get(timeout=5)[3] for _ in range(2)] == [600, 400]


def test_a_failing_writer_is_raised_with_its_traceback(tmp_path):
    from ccdata.writer import GenerationError, write_shard

    cfg = GenerateConfig(**TINY, root=tmp_path / "Reach")
    (tmp_path / "not-a-directory").write_text("")
    with pytest.raises(GenerationError, match="(?s)a writer process failed.*NotADirectoryError"):
        write_shard(cfg, plan(cfg)[:1], tmp_path / "not-a-directory" / "pieces")


@pytest.mark.integration
def test_a_killed_rollout_process_fails_the_generation_without_a_hang(tmp_path):
    """A rollout process killed (say by the OOM killer), maybe in the middle of sending an
    episode: the generation raises at once, leaves no process behind, and a rerun completes."""
    import multiprocessing
    import threading

    from ccdata.writer import GenerationError

    cfg = GenerateConfig(
        "Reach",
        episodes=2,
        explore_episodes=0,
        image_size=32,
        max_steps=60,
        workers=2,
        root=tmp_path / "Reach",
    )

    def kill_a_rollout() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            for child in multiprocessing.active_children():
                if child.name == "ccdata-rollout-1" and child.pid:
                    # Into its rollouts, with episodes left for it however warm the fork
                    # server is (8 short episodes take the two rollouts ~4 s).
                    time.sleep(1.5)
                    os.kill(child.pid, signal.SIGKILL)
                    return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_a_rollout)
    killer.start()
    start = time.monotonic()
    with pytest.raises(GenerationError, match=r"ccdata-rollout-1 died \(exit code -9\)"):
        generate(cfg, progress=False)
    killer.join()
    assert time.monotonic() - start < 60
    assert not multiprocessing.active_children()
    _, summary = generate(cfg, progress=False)
    assert existing_keys(cfg.dataset_root) == [s.key for s in plan(cfg)]
    assert summary["episodes"] == 8 and verify_dataset(cfg.dataset_root) == []


@pytest.mark.integration
def test_the_generating_process_imports_neither_torch_nor_lerobot(tmp_path):
    """Writing and merging happen in the writer and merger processes; the process that rolls
    out (and that a user's script runs in) never pays the seconds of importing torch."""
    script = textwrap.dedent(f"""
        import sys
        from ccdata import record
        cfg = record.GenerateConfig("Reach", episodes=1, explore_episodes=0, image_size=32,
                                    max_steps=3, root={str(tmp_path / "Reach")!r})
        root, summary = record.generate(cfg, progress=False)
        print(summary["episodes"], "torch" in sys.modules,
              any(m.split(".")[0] == "lerobot" for m in sys.modules))
    """)
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-3:] == ["4", "False", "False"]
    assert verify_dataset(tmp_path / "Reach") == []


def test_keyboard_interrupt_leaves_valid_dataset_and_resume_completes(tmp_path):
    cfg = GenerateConfig(
        "Reach", episodes=1, explore_episodes=0, image_size=32, max_steps=8, root=tmp_path / "Reach"
    )
    done = []

    def stop_after_two(record):
        done.append(record)
        if len(done) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate(cfg, on_episode=stop_after_two, progress=False)
    assert verify_dataset(cfg.dataset_root) == []
    # The two reported episodes, and any the writer was finishing meanwhile, in plan order.
    kept = existing_keys(cfg.dataset_root)
    assert 2 <= len(kept) < 4 and kept == [s.key for s in plan(cfg)[: len(kept)]]

    _, summary = generate(cfg, progress=False)
    assert summary["new_episodes"] == 4 - len(kept)
    keys = existing_keys(cfg.dataset_root)
    assert keys == [s.key for s in plan(cfg)] and len(set(keys)) == 4
    assert verify_dataset(cfg.dataset_root) == []
    assert not (tmp_path / ".Reach.ccdata-work").exists()


def test_sigkill_loses_only_episodes_not_yet_written(tmp_path):
    root = tmp_path / "Reach"
    kwargs = dict(suite="Reach", episodes=1, explore_episodes=0, image_size=32, max_steps=40)
    script = textwrap.dedent(f"""
        from ccdata import journal, record
        journal.GROUP = 2  # so that a merger process is running when the kill comes
        record.generate(record.GenerateConfig(**{kwargs!r}, root={str(root)!r}), progress=False)
    """)
    log = tmp_path / "generate.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-c", script], env={**os.environ}, stdout=out, stderr=subprocess.STDOUT
        )
    pieces = tmp_path / ".Reach.ccdata-work" / "pieces"
    deadline = time.time() + 240  # spawned writer and merger import torch, LeRobot: slow
    try:
        while time.time() < deadline:
            if (
                pieces.exists()
                and len([p for p in pieces.iterdir() if not p.name.startswith(".")]) >= 2
            ):
                break
            time.sleep(0.05)
        else:
            pytest.fail(
                f"the generating subprocess made no progress (exit {proc.poll()}): "
                f"{log.read_text()[-2000:]}"
            )
        children = descendants(proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # the fork server, the resource tracker and the server's children: writer and merger
    assert len(children) >= 4, "the writer and merger processes should be running"
    deadline = time.time() + 10
    while time.time() < deadline and any(alive(c) for c in children):
        time.sleep(0.1)
    assert not any(alive(c) for c in children), "a process outlived the killed generate"
    saved = [p.name for p in pieces.iterdir() if not p.name.startswith(".")]
    assert len(saved) >= 2 and not root.exists()  # nothing merged yet, nothing half-written

    cfg = GenerateConfig(**kwargs, root=root)
    _, summary = generate(cfg, progress=False)
    keys = existing_keys(root)
    assert keys == [s.key for s in plan(cfg)]  # complete, in plan order, no duplicates
    assert summary["new_episodes"] == 4 - len(saved)  # the killed run's pieces were kept
    assert verify_dataset(root) == []


def test_a_ctrl_c_while_the_fork_server_imports_does_not_kill_it():
    """Ctrl-C reaches the whole process group, the fork server too, which spends its first
    seconds importing torch and LeRobot: killed there, a writer's start failed with EOFError
    and the interrupted generation hung at exit. The server starts with SIGINT ignored."""
    script = textwrap.dedent("""
        import os, signal
        from multiprocessing import forkserver
        from ccdata.processes import process_context
        ctx = process_context()
        server = forkserver._forkserver._forkserver_pid
        os.kill(server, signal.SIGINT)  # at once: it is importing
        child = ctx.Process(target=os.getpid)
        child.start()
        child.join()
        print(child.exitcode, forkserver._forkserver._forkserver_pid == server)
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=300)  # fmt: skip
    assert (result.returncode, result.stdout) == (0, "0 True\n"), result.stderr[-2000:]


def test_other_suite_or_settings_at_target_are_refused(tiny):
    root, _ = tiny
    with pytest.raises(ValueError, match="suite"):
        generate(GenerateConfig("Grasp", episodes=1, image_size=32, max_steps=12, root=root))
    with pytest.raises(ValueError, match="image_size"):
        generate(GenerateConfig(**{**TINY, "image_size": 48}, root=root))


def test_a_damaged_target_or_journal_is_refused_before_any_rollout(tiny, tmp_path):
    """Adding to a dataset whose meta/episodes is cut, or resuming a journal whose settings are
    damaged, is one InputError before anything is rolled out: the final merge failed on the
    first only after every new episode, with a pyarrow traceback."""
    root, _ = tiny
    damaged = tmp_path / "Reach"
    shutil.copytree(root, damaged)
    episodes = next((damaged / "meta/episodes").rglob("*.parquet"))
    episodes.write_bytes(episodes.read_bytes()[:100])
    more = GenerateConfig(**{**TINY, "episodes": 2}, root=damaged)
    with pytest.raises(InputError, match=f"the dataset at {damaged} is damaged, so nothing can"):
        generate(more, progress=False)
    assert not (tmp_path / ".Reach.ccdata-work" / "pieces").exists()  # nothing rolled out

    fresh = GenerateConfig(**TINY, root=tmp_path / "fresh" / "Reach")
    journal = tmp_path / "fresh" / ".Reach.ccdata-work"
    journal.mkdir(parents=True)
    (journal / "settings.json").write_text('{"suite": "Re')
    with pytest.raises(InputError, match="settings.json is corrupt .* delete .* to start"):
        generate(fresh, progress=False)


def test_verify_reports_corruption(tiny, tmp_path):
    root, _ = tiny
    assert verify_dataset(root) == []

    broken = tmp_path / "parquet"
    shutil.copytree(root, broken)
    data = next((broken / "data").rglob("*.parquet"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    assert any("unreadable data file" in f for f in verify_dataset(broken))

    missing = tmp_path / "video"
    shutil.copytree(root, missing)
    next((missing / "videos/observation.images.gripperPOV").rglob("*.mp4")).unlink()
    assert any("missing video" in f for f in verify_dataset(missing))

    truncated = tmp_path / "truncated"
    shutil.copytree(root, truncated)
    data = next((truncated / "data").rglob("*.parquet"))
    table = pq.read_table(data)
    pq.write_table(table.slice(0, table.num_rows - 1), data)
    findings = verify_dataset(truncated)
    assert any("must be its final observation" in f for f in findings)
    assert any("frames in data" in f for f in findings)

    no_episodes = tmp_path / "no-episodes"
    shutil.copytree(root, no_episodes)
    for path in (no_episodes / "meta/episodes").rglob("*.parquet"):
        path.unlink()
    assert "no meta/episodes/*.parquet files" in verify_dataset(no_episodes)

    # JSON of the wrong shape is a finding too, not an AttributeError or KeyError
    info = json.loads((root / "meta/info.json").read_text())
    for name, text, finding in [
        ("meta/info.json", "[1, 2]", "info.json is not a JSON object"),
        ("meta/info.json", json.dumps({**info, "features": [1]}), "features is not an object"),
        ("meta/info.json", json.dumps({k: v for k, v in info.items() if k != "video_path"}),
         "info.json lacks 'video_path'"),
        ("meta/ccdata.json", "[]", "ccdata.json is not a JSON object"),
        ("meta/stats.json", "[]", "meta/stats.json is not a JSON object"),
    ]:  # fmt: skip
        shaped = tmp_path / f"shape-{finding.split()[0]}-{len(text)}"
        shutil.copytree(root, shaped)
        (shaped / name).write_text(text)
        assert finding in " | ".join(verify_dataset(shaped)), name


def test_merger_batches_complete_chunks_only(tiny, tmp_path):
    """`merge_chunks` batches each chunk whose pieces are all written; the final merge puts
    batches and loose pieces in plan order."""
    import threading

    from ccdata import journal, record

    cfg = GenerateConfig(**TINY, root=tmp_path / "Reach")
    specs = plan(cfg)
    paths = journal.prepare(cfg)
    record.write_shard(cfg, specs[:6], paths.pieces)  # chunk 2 of 4 incomplete
    chunks = [[s.key for s in specs[i : i + 4]] for i in (0, 4)]
    stop = threading.Event()

    def stop_once_the_first_chunk_is_batched() -> None:  # the second chunk never completes
        deadline = time.monotonic() + 120
        while not journal.finished_batches(paths) and time.monotonic() < deadline:
            time.sleep(0.05)
        stop.set()

    watcher = threading.Thread(target=stop_once_the_first_chunk_is_batched)
    watcher.start()
    journal.merge_chunks(cfg, chunks, stop)
    watcher.join()
    batches = journal.finished_batches(paths)
    assert list(batches) == [tuple(chunks[0])]
    record.write_shard(cfg, specs[6:], paths.pieces)
    assert journal.merge_pieces(cfg, [s.key for s in specs]) == len(specs)
    assert existing_keys(cfg.dataset_root) == [s.key for s in specs]
    assert verify_dataset(cfg.dataset_root) == []
    a, b = data_table(tiny[0]), data_table(cfg.dataset_root)
    for col in a:
        np.testing.assert_array_equal(a[col], b[col], err_msg=col)
    assert not paths.batches.exists() and not any(paths.pieces.iterdir())


def test_a_run_resumed_after_a_gap_completes_in_plan_order(tmp_path, monkeypatch):
    """A stopped run with two workers can leave episodes done after one that is not (here
    the fourth of twelve): the resumed run merges the first three to the root, rolls out the
    fourth and the last four, and batches only whole chunks of the plan, so no batch spans the
    episodes waiting in the journal (batched from what was left to do, [4th, 9th] was merged
    before the 5th to 8th). Its statistics list the features in sorted order."""
    from ccdata import journal, record

    monkeypatch.setattr(journal, "GROUP", 2)
    cfg = GenerateConfig(**TINY, root=tmp_path / "Reach")
    specs = plan(cfg)
    paths = journal.prepare(cfg)
    record.write_shard(cfg, specs[:3] + specs[4:8], paths.pieces)
    _, summary = generate(cfg, progress=False)
    assert summary["new_episodes"] == 5
    assert existing_keys(cfg.dataset_root) == [s.key for s in specs]
    assert verify_dataset(cfg.dataset_root) == []
    stats = json.loads((cfg.dataset_root / "meta/stats.json").read_text())
    assert list(stats) == sorted(stats)


@pytest.mark.slow  # two generations (~50 s); test_workers_give_the_same_episodes runs in CI
def test_batched_generation_is_byte_identical_across_workers(tmp_path, monkeypatch):
    """With chunks of 2 (6 batches, merged in a tree of pairs), the merge tree is fixed by the
    plan: one worker or two, merger fast or slow, the dataset's data files are the same bytes
    and its statistics the same numbers."""
    from ccdata import journal

    monkeypatch.setattr(journal, "GROUP", 2)
    roots = []
    for workers in (1, 2):
        cfg = GenerateConfig(**TINY, root=tmp_path / f"w{workers}" / "Reach", workers=workers)
        root, summary = generate(cfg, progress=False)
        assert summary["episodes"] == 12 and verify_dataset(root) == []
        roots.append(root)
    # Same numbers to the last bit, the features in the same (sorted) order.
    stats = [(r / "meta/stats.json").read_text() for r in roots]
    assert stats[0] == stats[1]
    files = sorted(
        p
        for sub in ("data", "videos", "meta/episodes")
        for p in (roots[0] / sub).rglob("*")
        if p.is_file()
    )
    assert files
    for path in files:
        rel = path.relative_to(roots[0])
        assert path.read_bytes() == (roots[1] / rel).read_bytes(), rel
    assert existing_keys(roots[0]) == [s.key for s in plan(cfg)]


def _assert_same_stats(a, b, where) -> None:
    """Dataset statistics equal, except the cameras' (deferred to one update by
    `faster_lerobot`): min, max and count equal, mean and std up to float32 rounding (one
    update against one per frame), quantiles within two of the 5000 histogram bins over the
    0-1 range."""
    assert a.keys() == b.keys(), where
    for key in a:
        if isinstance(a[key], dict):
            _assert_same_stats(a[key], b[key], f"{where}:{key}")
        elif "observation.images." not in f"{where}:{key}" or key.endswith(("min", "max", "count")):
            assert a[key] == b[key], (where, key)
        else:
            quantile = "/q" in key or key.startswith("q")
            np.testing.assert_allclose(
                np.asarray(a[key], dtype=float),
                np.asarray(b[key], dtype=float),
                err_msg=key,
                atol=2 / 5000 if quantile else 0,
                rtol=0 if quantile else 1e-3,
            )  # std = sqrt(E[x^2] - E[x]^2) in float32


def test_faster_lerobot_writes_and_merges_the_same_bytes(tmp_path):
    """`ccdata.lerobot_speedups` changes LeRobot's speed, not its output: pieces written and
    merged with and without it are the same files, byte for byte, but for the cameras'
    statistics, which agree to rounding (quantiles: to the histogram's resolution)."""
    from lerobot.datasets.aggregate import aggregate_datasets

    from ccdata.env import make_env
    from ccdata.lerobot_speedups import faster_lerobot
    from ccdata.writer import rollout_episode, write_piece

    cfg = GenerateConfig(**{**TINY, "max_steps": 6})
    specs = plan(cfg)[:2]
    instruction = ccdata.get_task(specs[0].task_id).instruction
    env = make_env(specs[0].task_id, render_settings=cfg.render_settings)
    episodes = [rollout_episode(env, s, cfg) for s in specs]
    env.close()
    roots = {}
    for name in ("lerobot", "faster"):
        pieces = tmp_path / name / "pieces"
        pieces.mkdir(parents=True)
        with faster_lerobot() if name == "faster" else contextlib.nullcontext():
            for spec, episode in zip(specs, episodes, strict=True):
                write_piece(cfg, spec, episode, pieces, instruction)
            roots[name] = tmp_path / name / "merged"
            aggregate_datasets(
                [cfg.repo_id] * 2,
                cfg.repo_id,
                aggr_root=roots[name],
                roots=[pieces / s.key for s in specs],
            )
    for sub in ("pieces", "merged"):
        a_root, b_root = tmp_path / "lerobot" / sub, tmp_path / "faster" / sub
        files = sorted(
            p.relative_to(a_root)
            for p in a_root.rglob("*")
            if p.is_file() and p.name != "piece.json"
        )  # piece.json holds timings
        assert files == sorted(
            p.relative_to(b_root)
            for p in b_root.rglob("*")
            if p.is_file() and p.name != "piece.json"
        )
        for rel in files:
            a, b = (a_root / rel).read_bytes(), (b_root / rel).read_bytes()
            if rel.name == "stats.json":  # LeRobot writes the stats' keys in no fixed order
                _assert_same_stats(json.loads(a), json.loads(b), rel)
            elif "episodes" in rel.parts and rel.suffix == ".parquet":
                ta, tb = pq.read_table(a_root / rel), pq.read_table(b_root / rel)
                assert ta.column_names == tb.column_names, rel
                for name in ta.column_names:
                    ca, cb = ta[name].to_pylist(), tb[name].to_pylist()
                    if name.startswith("stats/observation.images."):
                        _assert_same_stats({name: ca}, {name: cb}, rel)
                    else:
                        assert ca == cb, (rel, name)
            elif a != b and "data" in rel.parts and rel.suffix == ".parquet":
                # The same table; LeRobot's embedding pass also stamps its `datasets` cache
                # fingerprint into the schema metadata, which the skipped pass does not.
                ta, tb = pq.read_table(a_root / rel), pq.read_table(b_root / rel)
                assert ta.equals(tb) and ta.schema.equals(tb.schema), rel
                meta_a = json.loads(ta.schema.metadata[b"huggingface"])
                meta_a.pop("fingerprint")
                assert meta_a == json.loads(tb.schema.metadata[b"huggingface"]), rel
            else:
                assert a == b, rel
    info = json.loads((roots["faster"] / "meta/info.json").read_text())
    assert info["total_episodes"] == 2
    assert info["total_frames"] == sum(len(e["action"]) for e in episodes)


@pytest.mark.parametrize("damage", ["info.json", "parquet"])
def test_generating_into_a_damaged_dataset_is_one_line(damage, tiny, tmp_path, capsys):
    """A dataset at the target whose meta/info.json or a data file is damaged is refused with
    one line naming the file (a corrupt info.json was reported complete before; a cut parquet
    file was a pyarrow traceback)."""
    from ccdata.cli import main as ccdata_main

    root = tmp_path / "Reach"
    shutil.copytree(tiny[0], root)
    path = (
        root / "meta" / "info.json"
        if damage == "info.json"
        else next((root / "data").rglob("*.parquet"))
    )
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    damaged = f"is damaged, so nothing can be added to it \\(unreadable data file {path.name}"
    with pytest.raises(InputError, match=f"{path.name} is (missing|corrupt)|{damaged}"):
        generate(GenerateConfig(**TINY, root=root), progress=False)
    args = ["generate", "--suite", TINY["suite"], "--root", str(root)]
    args += [f"--{k.replace('_', '-')}={v}" for k, v in TINY.items() if k != "suite"]
    assert ccdata_main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and path.name in err
