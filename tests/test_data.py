"""Seeding replay from a generated dataset (`ccfit.data`): every transition of every episode
reaches the buffer, the successes that ended episodes included, in pixel and in state mode."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ccdata
from ccdata.dataset_format import FINAL_KEY
from ccdata.record import GenerateConfig, generate
from ccdata.render import RenderSettings
from ccfit.data import load_episodes
from ccfit.obs import stack_cameras
from ccfit.replay import ReplayBuffer
from ccfit.replay_prefill import episode_to_replay, seed_buffer

TASK = "reach-xy"


@pytest.fixture(scope="module")
def reach(tmp_path_factory) -> Path:
    """Oracle and noisy-oracle reach episodes succeed within 40 steps; random ones are cut."""
    root = tmp_path_factory.mktemp("seed") / "Reach"
    root, _ = generate(
        GenerateConfig(
            "Reach", episodes=3, explore_episodes=1, image_size=32, max_steps=40, root=root
        ),
        progress=False,
    )
    return root


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 99.0 if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def all_transitions(buffer: ReplayBuffer) -> SimpleNamespace:
    """Every real transition of `buffer`: (obs, next_obs, terminated) of the 2-row windows
    that lie inside one episode."""
    pairs = buffer.gather(torch.arange(buffer.num_starts(2)), 2)
    real = pairs.valid()[0, :, 0].bool()
    return SimpleNamespace(obs={k: v[0, real] for k, v in pairs.obs.items()},
                           next_obs={k: v[1, real] for k, v in pairs.obs.items()},
                           terminated=pairs.terminated[0, real, 0])  # fmt: skip


def test_seeded_pixel_replay_holds_one_terminal_success_per_successful_episode(reach):
    episodes = load_episodes(reach, task=TASK)
    successful = [ep for ep in episodes if ep["next.success"].any()]
    assert len(successful) >= 3 and len(successful) < len(episodes)  # random ones fail
    buffer = ReplayBuffer(10_000)
    added = seed_buffer(buffer, reach, TASK, "pixels", RenderSettings(32))
    assert added == dict(Counter(ep["policy"] for ep in episodes))
    # Every step of every episode is a transition (the final frame is an observation only).
    steps = [int((~ep[FINAL_KEY].reshape(-1).astype(bool)).sum()) for ep in episodes]
    assert buffer.num_transitions == sum(steps)
    batch = all_transitions(buffer)
    terminal = batch.terminated == 1
    assert int(terminal.sum()) == len(successful)
    # Each terminal transition leads to its episode's success state: the recorded final frame,
    # which is what the env shows after replaying the episode's actions.
    reached = batch.next_obs["pixels"][terminal].numpy()
    for ep, pixels in zip(successful, reached, strict=True):
        final = {c: ep[f"observation.images.{c}"][-1] for c in ccdata.CAMERAS}
        np.testing.assert_array_equal(pixels, stack_cameras(final))
        env = ccdata.make_env(TASK, image_size=32)
        obs, _ = env.reset(seed=int(ep["episode_seed"].reshape(-1)[0]))
        for action in ep["action"][:-1]:
            obs, _, terminated, _, info = env.step(action)
        env.close()
        assert terminated and info["success"]
        np.testing.assert_array_equal(obs["state"], ep["observation.environment_state"][-1])
        assert psnr(pixels, stack_cameras({c: obs[c] for c in ccdata.CAMERAS})) >= 40.0


def test_state_replay_keeps_every_transition_without_a_simulator(reach):
    episodes = load_episodes(reach, task=TASK, images=False)
    for ep in episodes:
        item = episode_to_replay(ep, "state")
        steps = len(ep["action"]) - 1
        assert item["obs"]["state"].shape == (steps + 1, 39)
        np.testing.assert_array_equal(item["obs"]["state"], ep["observation.environment_state"])
        assert item["action"].shape == (steps, 4) and item["reward"].shape == (steps,)
        success = bool(ep["next.success"].any())
        assert item["terminated"].tolist() == [0.0] * (steps - 1) + [float(success)]
        with pytest.raises(ValueError, match="records its final observation"):
            episode_to_replay(ep, "state", final_obs={"state": item["obs"]["state"][-1]})
    buffer = ReplayBuffer(10_000)
    added = seed_buffer(buffer, reach, TASK, "state")
    assert added == dict(Counter(ep["policy"] for ep in episodes))
    batch = all_transitions(buffer)
    assert int(batch.terminated.sum()) == sum(bool(ep["next.success"].any()) for ep in episodes)


def test_an_atomic_write_reaches_the_disk_before_and_after_its_rename(tmp_path, monkeypatch):
    """The temp file is flushed before it is renamed over the target, and the directory after
    (a machine that goes down in between keeps the old file or the whole new one)."""
    import os
    import stat

    from ccdata import atomic

    calls = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        calls.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    def replace(src, dst):
        calls.append("rename")
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic.os, "replace", replace)
    atomic.atomic_write_text(tmp_path / "a.json", "{}")
    assert calls == ["file", "rename", "dir"]
    assert (tmp_path / "a.json").read_text() == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]
