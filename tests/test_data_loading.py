"""The observation path and the LeRobot reader that seeds replay."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from ccdata.errors import InputError
from ccfit.obs import model_input, obs_to_arrays, stack_cameras
from ccfit.replay import ReplayBuffer

H = 3


def test_obs_path_stacks_cameras_in_order_for_live_frames():
    from ccdata import make_env

    env = make_env("reach-xy", seed=0, image_size=32)
    obs, _ = env.reset(seed=0)
    batch = model_input([obs_to_arrays(obs, "pixels")] * 2, torch.device("cpu"))
    env.close()
    assert batch["pixels"].shape == (2, 9, 32, 32) and batch["pixels"].dtype == torch.uint8
    x = {k: v[0] for k, v in batch.items()}
    for i, cam in enumerate(("topview", "frontview", "gripperPOV")):
        chw = torch.from_numpy(obs[cam]).permute(2, 0, 1)
        assert torch.equal(x["pixels"][3 * i : 3 * i + 3], chw)
    assert torch.equal(x["proprio"], torch.from_numpy(obs["proprio"]))
    assert set(obs_to_arrays(obs, "state")) == {"state"}
    seq = {c: np.stack([obs[c]] * 2) for c in ("topview", "frontview", "gripperPOV")}
    assert np.array_equal(stack_cameras(seq)[1], x["pixels"].numpy())
    with pytest.raises(ValueError, match="valid: state, pixels"):
        obs_to_arrays(obs, "rgb")


# ======================================================================== LeRobot reader


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """A finalized LeRobot v3 dataset in ccdata's schema from real rollouts (32 px cameras):
    an oracle reach-xy episode that ends in success, and 12 random steps of reach-xyz."""
    from lerobot.configs import RGBEncoderConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from ccdata import make_env
    from ccdata.dataset_format import VIDEO_ENCODER, ccdata_metadata, features
    from ccdata.policies import make_policy
    from ccdata.record import GenerateConfig

    root = tmp_path_factory.mktemp("ds") / "Reach"
    size = 32
    ds = LeRobotDataset.create(
        "ccdata/Reach", fps=40, features=features(size), root=root, use_videos=True,
        rgb_encoder=RGBEncoderConfig(**json.loads(json.dumps(VIDEO_ENCODER))),
    )  # fmt: skip
    meta = ccdata_metadata(GenerateConfig(suite="Reach", root=root, image_size=size))
    written = []
    # (task id, task_id_index, policy, policy_index, episode seed, step limit)
    plan = [("reach-xy", 0, "oracle", 0, 101, 250), ("reach-xyz", 3, "random", 2, 102, 12)]
    for task_id, task_i, policy_name, pol_i, seed, limit in plan:
        env = make_env(task_id, image_size=size)
        policy = make_policy(policy_name, task_id, seed=0)
        policy.reset()
        obs, _ = env.reset(seed=seed)
        rec = {"state": [], "img": []}
        for t in range(limit):
            action = np.asarray(policy.act(obs), np.float32)
            nxt, reward, terminated, truncated, info = env.step(action)
            last = terminated or truncated or t + 1 == limit
            imgs = [obs[c] for c in ("topview", "frontview", "gripperPOV")]
            rec["state"].append(obs["state"])
            rec["img"].append(imgs)
            ds.add_frame({
                "observation.images.topview": imgs[0],
                "observation.images.frontview": imgs[1],
                "observation.images.gripperPOV": imgs[2],
                "observation.state": obs["proprio"],
                "observation.environment_state": obs["state"],
                "action": action,
                "next.reward": np.array([reward], np.float32),
                "next.done": np.array([last]),
                "next.success": np.array([bool(info["success"])]),
                "task_id_index": np.array([task_i]),
                "policy_index": np.array([pol_i]),
                "episode_seed": np.array([seed]),
                # no final-observation frame: the layout of format-1 datasets
                "is_final_observation": np.array([False]),
                "task": meta["tasks"][task_i]["instruction"],
            })  # fmt: skip
            obs = nxt
            if last:
                break
        rec["final_state"], rec["success"] = obs["state"], bool(info["success"])
        env.close()
        ds.save_episode()
        written.append(rec)
    ds.finalize()
    (root / "meta" / "ccdata.json").write_text(json.dumps(meta))
    assert written[0]["success"] and not written[1]["success"]
    return root, written


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def test_load_episodes_matches_written_frames(tiny_dataset):
    from ccfit.data import load_episodes
    from ccfit.replay_prefill import episode_to_replay

    root, written = tiny_dataset
    eps = load_episodes(root)
    assert [e["episode_index"] for e in eps] == [0, 1]
    assert [e["task_id"] for e in eps] == ["reach-xy", "reach-xyz"]
    assert [e["policy"] for e in eps] == ["oracle", "random"]
    for ep, rec in zip(eps, written, strict=True):
        assert np.array_equal(ep["observation.environment_state"], np.stack(rec["state"]))
        for c, cam in enumerate(("topview", "frontview", "gripperPOV")):
            decoded = ep[f"observation.images.{cam}"]
            truth = np.stack([imgs[c] for imgs in rec["img"]])
            assert decoded.shape == truth.shape and decoded.dtype == np.uint8
            assert min(_psnr(d, w) for d, w in zip(decoded, truth, strict=True)) >= 40.0
    only = load_episodes(root, task="reach-xyz", policy="random", images=False)
    assert [e["episode_index"] for e in only] == [1]
    assert "observation.images.topview" not in only[0]
    with pytest.raises(ValueError, match="valid: reach-xy"):
        load_episodes(root, task="pick-cube")
    with pytest.raises(ValueError, match="match"):
        load_episodes(root, task="reach-xy", policy="random")

    # Into replay: T frames -> T observations and T-1 transitions, pixels via ccfit.obs.
    steps = len(written[1]["state"])
    r = episode_to_replay(eps[1], "pixels")
    assert r["obs"]["pixels"].shape == (steps, 9, 32, 32) and r["action"].shape == (steps - 1, 4)
    assert np.array_equal(r["obs"]["pixels"][:, 3:6], np.moveaxis(
        eps[1]["observation.images.frontview"], -1, 1))  # fmt: skip
    buf = ReplayBuffer(1000)
    buf.add_episode(**r)
    assert buf.num_transitions == steps - 1


def test_seed_buffer_preloads_the_tasks_episodes(tiny_dataset):
    from ccfit.data import load_episodes
    from ccfit.replay_prefill import final_observation, seed_buffer

    root, written = tiny_dataset
    steps = len(written[0]["state"])
    buf = ReplayBuffer(1000)
    assert seed_buffer(buf, root, "reach-xy", "state") == {"oracle": 1}
    assert buf.num_demo_starts(2) == steps  # the oracle's episode is a demonstration
    # The success ended the episode: its final observation is replayed, the terminal kept.
    assert buf.num_episodes == 1 and buf.num_transitions == steps
    b = buf.sample(256, 2)  # windows of two rows: one transition each
    final = b.terminated[0, :, 0] == 1
    assert final.any()
    assert torch.equal(b.obs["state"][1, final][0], torch.from_numpy(written[0]["final_state"]))
    ep = load_episodes(root, task="reach-xy", images=False)[0]
    ep["observation.environment_state"][2, 0] += 0.01
    with pytest.raises(ValueError, match="departs from the recorded states at step 2"):
        final_observation(ep, "reach-xy")
    from ccdata.render import RenderSettings

    with pytest.raises(InputError, match=r"rendered differently: image_size 32 \(run: 64\)"):
        seed_buffer(ReplayBuffer(1000), root, "reach-xyz", "pixels", RenderSettings(64))
    with pytest.raises(InputError, match=r"shadows True \(run: False\)"):
        meta_path = root / "meta" / "ccdata.json"
        meta = json.loads(meta_path.read_text())
        try:
            meta_path.write_text(
                json.dumps({**meta, "render": {**meta["render"], "shadows": True}})
            )
            seed_buffer(ReplayBuffer(1000), root, "reach-xyz", "pixels", RenderSettings(32))
        finally:
            meta_path.write_text(json.dumps(meta))
    random = ReplayBuffer(1000)
    assert seed_buffer(random, root, "reach-xyz", "pixels", RenderSettings(32)) == {"random": 1}
    assert random.num_demo_starts(2) == 0


def _demo_fraction_argv(root) -> list[str]:
    """`ccfit train` at the smoke preset for 200 steps, seeded from `root`, a quarter of each
    batch on its demonstrations (no task, no out)."""
    return ["train", "--preset", "smoke", "--seed_dataset", str(root), "--train.steps=200",
            "--train.seed_steps=100", "--train.eval_interval=200", "--train.demo_fraction=0.25",
            "--quiet"]  # fmt: skip


def test_demo_fraction_oversamples_the_oracle_episodes_of_the_seed_dataset(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """`--train.demo_fraction` trains with the seed dataset's oracle episodes oversampled (every
    update's batch is drawn with it) and records the setting; without demonstrations to
    oversample it is one line, exit 2."""
    from ccfit.cli import main
    from ccfit.replay_prefill import demonstration_rows

    root, _ = tiny_dataset
    sample, fractions = ReplayBuffer.sample, []

    def spy(self, batch_size, seq_len, demo_fraction=0.0):
        fractions.append(demo_fraction)
        return sample(self, batch_size, seq_len, demo_fraction)

    monkeypatch.setattr(ReplayBuffer, "sample", spy)
    base = _demo_fraction_argv(root)
    out = tmp_path / "xy"
    assert main([*base, "--task", "reach-xy", "--out", str(out)]) == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["train"]["demo_fraction"] == 0.25
    # Beside the dataset's path, what lay there: its size and how ccdata made it.
    recorded = saved["resolved_seed_dataset_meta"]
    assert (recorded["total_episodes"], recorded["repo_id"]) == (2, "ccdata/Reach")
    assert recorded["generated_with"]["suite"] == "Reach" and "lerobot" in recorded["versions"]
    assert set(recorded["content_sha256"]) == {"data", "videos"}
    assert len(fractions) >= 100 and set(fractions) == {0.25}  # smoke: 1 update per step
    assert main([*base, "--task", "reach-xyz", "--out", str(tmp_path / "xyz")]) == 2
    assert "holds no oracle episode of reach-xyz" in capsys.readouterr().err
    # Demonstrations shorter than one window (`demonstration_rows`: an upper bound).
    window = demonstration_rows(root, ["reach-xy"]) + 1
    argv = [*base, "--task", "reach-xy", f"--model.seq_len={window}", "--out", str(tmp_path / "w")]
    assert main(argv) == 2
    assert f"fewer than a training window of {window}" in capsys.readouterr().err
    assert main([*base[:4], "null", *base[5:], "--task", "reach-xy"]) == 2
    err = capsys.readouterr().err
    assert "needs a seed dataset" in err and "or --train.demo_fraction=0" in err
    assert main([*base, "--task", "reach-xy", "--train.demo_fraction=1"]) == 2
    assert "train.demo_fraction must be in [0, 1)" in capsys.readouterr().err


@pytest.mark.integration  # a 600-step run
def test_demo_fraction_draws_demonstrations_the_ring_overwrote(tiny_dataset, tmp_path):
    """A ring of one episode's rows: the online episodes overwrite the oracle's in the ring,
    and training with `demo_fraction` goes on to the end (this failed before)."""
    from ccfit.cli import main

    root, _ = tiny_dataset
    small = ["--train.buffer_capacity=251", "--train.steps=600", "--train.eval_interval=600"]
    argv = [*_demo_fraction_argv(root), *small, "--task", "reach-xy"]
    assert main([*argv, "--out", str(tmp_path / "ring")]) == 0
    meta = torch.load(tmp_path / "ring" / "checkpoint.pt", weights_only=False)["buffer"]
    ((first, end),) = meta["demo_spans"].tolist()
    assert first == 0 and meta["written"] - meta["capacity"] >= end  # every demo row overwritten


def test_demonstrations_are_kept_only_for_demo_fraction_and_counted_before_seeding(tiny_dataset):
    """Oracle episodes are marked as demonstrations (kept beside the ring) only when asked;
    `demonstration_rows` counts, from the index columns alone, the rows they then take."""
    from ccfit.data import episode_lengths
    from ccfit.replay_prefill import demonstration_rows, seed_buffer

    root, written = tiny_dataset
    kept, plain = ReplayBuffer(1000), ReplayBuffer(1000)
    seed_buffer(kept, root, "reach-xy", "state")
    seed_buffer(plain, root, "reach-xy", "state", demos=False)
    assert plain.num_transitions == kept.num_transitions and not plain.demo_spans
    rows = sum(end - first for first, end in kept.demo_spans)
    assert rows == len(written[0]["state"]) + 1  # the transitions and the final observation
    # This dataset records no final observation: the episode's frames are its transitions.
    assert episode_lengths(root, "reach-xy", "oracle") == [rows - 1]
    assert episode_lengths(root, "reach-xyz", "oracle") == []
    assert demonstration_rows(root, ["reach-xy", "reach-xyz"]) == rows
    with pytest.raises(InputError, match="task 'reach-zz' is not in this dataset"):
        episode_lengths(root, "reach-zz", "oracle")


def test_the_recorded_digest_tells_a_changed_frame_apart(tiny_dataset, tmp_path, capsys):
    # Same settings and sizes, one reward changed by one ulp: only the data digest differs; a
    # byte-for-byte copy elsewhere has the same digests.
    import pyarrow.parquet as pq

    from ccfit.data import REWARD_KEY, dataset_meta

    copy, changed = tmp_path / "copy", tmp_path / "changed"
    shutil.copytree(tiny_dataset[0], copy)
    shutil.copytree(tiny_dataset[0], changed)
    original = dataset_meta(tiny_dataset[0])
    assert original["content_sha256"]["data"] and original["content_sha256"]["videos"]
    assert dataset_meta(copy) == original
    (frames,) = (changed / "data").rglob("*.parquet")
    table = pq.read_table(frames)
    rewards = table[REWARD_KEY].to_numpy().copy()
    rewards[0] = np.nextafter(rewards[0], np.inf)
    column = table.schema.get_field_index(REWARD_KEY)
    pq.write_table(table.set_column(column, REWARD_KEY, [rewards]), frames)
    recorded = dataset_meta(changed)
    assert recorded["content_sha256"]["data"] != original["content_sha256"]["data"]
    assert {**recorded, "content_sha256": None} == {**original, "content_sha256": None}
    assert recorded["content_sha256"]["videos"] == original["content_sha256"]["videos"]
    # A run that recorded the original at this path and resumes on the changed copy there
    # says so, once (the resumed run records the new content).
    from ccfit.train.run import check_saved_config

    run = tmp_path / "run"
    run.mkdir()
    record = "resolved_seed_dataset", "resolved_seed_dataset_meta"
    check_saved_config(run, dict(zip(record, (str(changed), original), strict=True)))
    assert capsys.readouterr().err == ""
    for _ in range(2):
        check_saved_config(run, dict(zip(record, (str(changed), recorded), strict=True)))
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"the dataset at {changed} holds other data than" in err


def test_a_corrupt_ccdata_json_is_one_input_error(tiny_dataset, tmp_path):
    # Filtering by task name and recording the dataset both read meta/ccdata.json; damaged, it
    # is bad input with the file named, not a JSONDecodeError traceback.
    from ccfit.data import dataset_meta, load_episodes

    root = tmp_path / "damaged"
    shutil.copytree(tiny_dataset[0], root)
    (root / "meta" / "ccdata.json").write_text('{"tasks": [')
    for read in (lambda: load_episodes(root, task="reach-xy", images=False),
                 lambda: dataset_meta(root)):  # fmt: skip
        with pytest.raises(InputError, match=r"ccdata.json is corrupt"):
            read()
    # and a damaged meta/info.json, which recording the dataset reads for its size
    (root / "meta" / "ccdata.json").unlink()
    (root / "meta" / "info.json").write_text("{")
    with pytest.raises(InputError, match=r"cannot read LeRobot dataset at"):
        dataset_meta(root)


def test_a_run_read_back_from_its_config_finds_its_seed_dataset_or_says_how_to_make_it(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """`--config_path` of a run whose `--seed_dataset auto` had found the suite's dataset: with
    none there, or another one there, one line naming `ccdata generate`, exit 2; with the same
    one, it runs. A run whose auto finds none says so at its start, in one line."""
    import lerobot.utils.constants
    import pyarrow.parquet as pq

    from ccfit.cli import main
    from ccfit.config import TaskRunConfig
    from ccfit.config_parse import parse_cli
    from ccfit.data import REWARD_KEY
    from ccfit.train.run import check_seed_dataset_as_run, resolved_config

    home = tmp_path / "home"
    monkeypatch.setattr(lerobot.utils.constants, "HF_LEROBOT_HOME", home)
    argv = ["train", "--task", "reach-xy", "--preset", "smoke", "--quiet", "--train.steps=60",
            "--train.seed_steps=40", "--train.eval_interval=60",
            "--train.eval_episodes=1"]  # fmt: skip
    assert main([*argv, "--out", str(tmp_path / "none")]) == 0
    (note,) = [x for x in capsys.readouterr().err.splitlines() if "seed_dataset" in x]
    assert "found no Reach dataset" in note and "`ccdata generate --suite Reach`" in note

    shutil.copytree(tiny_dataset[0], home / "ccdata" / "Reach")
    cfg = parse_cli(TaskRunConfig, [a for a in argv[1:] if a != "--quiet"])
    saved = resolved_config(cfg, "Reach")
    assert saved["resolved_seed_dataset"] == str(home / "ccdata" / "Reach")
    config = tmp_path / "config.json"
    config.write_text(json.dumps(saved))
    check_seed_dataset_as_run(cfg, "Reach", saved, config)  # the same dataset: runs
    again = ["train", "--config_path", str(config), "--out", str(tmp_path / "again"), "--quiet"]

    (frames,) = (home / "ccdata" / "Reach" / "data").rglob("*.parquet")
    table = pq.read_table(frames)
    rewards = table[REWARD_KEY].to_numpy().copy()
    rewards[0] = np.nextafter(rewards[0], np.inf)
    column = table.schema.get_field_index(REWARD_KEY)
    pq.write_table(table.set_column(column, REWARD_KEY, [rewards]), frames)
    assert main(again) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not the one" in err and "(its data differ)" in err
    assert "`ccdata generate --suite Reach`" in err and "--seed_dataset null" in err
    # Into the directory that holds the run, it resumes: there the changed content is a note.
    (tmp_path / "had").mkdir()
    shutil.copy(config, tmp_path / "had" / "config.json")
    assert main([*again[:3], "--out", str(tmp_path / "had"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "holds other data than" in err and "is not the one" not in err

    shutil.rmtree(home / "ccdata" / "Reach")
    assert main(again) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "which is not here" in err
    assert "`ccdata generate --suite Reach`" in err and "--seed_dataset null" in err
    assert not (tmp_path / "again").exists()
