"""One contract over every registered task (dm_control-suite style)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import ccdata
from ccdata.env import DEFAULT_EPISODE_STEPS as EPISODE_STEPS
from ccdata.policies import make_policy
from ccdata.suites import SUITES, get_suite
from ccdata.tasks import base as scene_base

TASK_IDS = list(ccdata.TASKS)


def episode_digest(env: gym.Env, seed: int, steps: int = 10) -> str:
    """Hash of every observation and reward of the episode `reset(seed=seed)` starts, under
    random actions seeded with `seed`."""
    rng = np.random.default_rng(seed)
    digest = hashlib.sha256()
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        for key in sorted(obs):
            digest.update(obs[key].tobytes())
        obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        digest.update(np.float64(reward).tobytes())
        if terminated or truncated:
            break
    return digest.hexdigest()


def rollout_digest(task_id: str, seed: int, steps: int = 10, image_size: int = 32) -> str:
    """`episode_digest` of a fresh environment."""
    env = ccdata.make_env(task_id, image_size=image_size)
    try:
        return episode_digest(env, seed, steps)
    finally:
        env.close()


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_observation_spec_and_values(task_id):
    env = ccdata.make_env(task_id, seed=0, image_size=32)
    obs, info = env.reset()
    assert set(obs) == {*ccdata.CAMERAS, "proprio", "state"}
    assert env.observation_space.contains(obs)
    for cam in ccdata.CAMERAS:
        assert obs[cam].shape == (32, 32, 3) and obs[cam].dtype == np.uint8
        assert obs[cam].std() > 1.0, f"{cam} renders a blank image"
    assert obs["proprio"].dtype == np.float32 and obs["proprio"].shape == (7,)
    assert obs["state"].dtype == np.float32 and obs["state"].shape == (39,)
    np.testing.assert_allclose(obs["proprio"][:3], obs["state"][:3])
    assert info["success"] is False
    rng = np.random.default_rng(0)
    for _ in range(25):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 4))
        assert env.observation_space.contains(obs)
        assert all(np.isfinite(v).all() for v in obs.values())
        assert -1.0 <= reward <= 0.0
        assert terminated == info["success"]
        if terminated or truncated:
            break
    # the scene's own entries of its last physics step ride along (stage flags, distances)
    _, _, scene_info = env.unwrapped.scene.sim_step(np.zeros(4))
    assert set(scene_info) <= set(info) and info["task"] == task_id
    env.close()


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_state_only_mode_and_settings_are_readable(task_id):
    env = ccdata.make_env(task_id, seed=0, render=False)
    obs, _ = env.reset()
    assert set(obs) == {"proprio", "state"}
    assert env.render_settings == ccdata.RenderSettings(image_size=64)
    assert env.render_settings.shadows is False and env.render_settings.msaa_samples == 0
    env.close()


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_same_seed_same_episode_and_reset_randomises(task_id):
    # One environment, as a generation worker uses it: an episode in between must not leak
    # into the next one with the same seed.
    env = ccdata.make_env(task_id, image_size=32)
    first, other, again = (episode_digest(env, seed) for seed in (3, 4, 3))
    assert first == again != other
    states = [env.reset(seed=s)[0]["state"] for s in range(3)]
    # The goal or an object start must move between seeds.
    assert not np.allclose(states[0], states[1]) or not np.allclose(states[1], states[2])
    env.close()


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_an_environment_from_the_compiled_scene_plays_as_one_compiled_afresh(task_id, monkeypatch):
    """A process compiles each scene once and gives every environment a copy
    (`SceneEnv._initialize_simulation`): one made after another played (moving the goal sites
    of its own copy), in a process that built the other tasks before, plays the episode that
    an environment compiled from its file plays."""
    played = ccdata.make_env(task_id, render=False)
    episode_digest(played, seed=5)
    compiled = len(scene_base._COMPILED)
    from_cache = rollout_digest(task_id, seed=9)
    assert len(scene_base._COMPILED) == compiled  # found, not compiled again
    monkeypatch.setattr(scene_base, "_COMPILED", {})
    assert rollout_digest(task_id, seed=9) == from_cache
    played.close()


@pytest.mark.integration
def test_same_seed_same_episode_across_processes():
    """A fresh interpreter (its own hash seed) replays the same episodes: checked on each
    suite's last task, the composition (every task is checked in-process above)."""
    tasks = sorted({get_suite(s).task_ids[-1] for s in SUITES})
    here = {t: rollout_digest(t, seed=7) for t in tasks}
    code = (
        "import json, sys; sys.path.insert(0, 'tests');"
        "from test_tasks_contract import rollout_digest;"
        f"print(json.dumps({{t: rollout_digest(t, seed=7) for t in {tasks!r}}}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == here


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_success_terminates_with_zero_reward(task_id):
    env = ccdata.make_env(task_id, seed=0, render=False)
    policy = make_policy("oracle", task_id)
    obs, _ = env.reset()
    policy.reset()
    for _ in range(EPISODE_STEPS):
        obs, reward, terminated, truncated, info = env.step(policy.act(obs))
        if terminated or truncated:
            break
    assert terminated and info["success"] and reward == 0.0, f"oracle failed seed 0 of {task_id}"
    assert not truncated
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4, np.float32))
    env.close()


def test_time_limit_truncates():
    env = ccdata.make_env("reach-xy", seed=0, render=False)
    env.reset()
    steps = 0
    terminated = truncated = False
    while not (terminated or truncated):
        # Pushing into a table corner never reaches the goal.
        _, _, terminated, truncated, _ = env.step(np.array([1, -1, -1, 0], np.float32))
        steps += 1
    assert truncated and not terminated and steps == EPISODE_STEPS
    env.close()


def test_cameras_are_upright():
    env = ccdata.make_env("reach-xy", seed=0, image_size=64)
    env.reset()
    model, data = env.scene.model, env.scene.data
    for cam in ccdata.CAMERAS:
        up = data.cam_xmat[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, cam)].reshape(3, 3)
        up = up[:, 1]
        if cam == "frontview":
            assert up[2] > 0.3, "frontview: image up must point up in the world"
        else:
            assert up[1] > 0.9, f"{cam}: image up must point away from the robot base"
    # Rendered rows run top to bottom: the frontview sees the far table (deeper) at the top.
    renderer = mujoco.Renderer(model, 64, 64)
    renderer.enable_depth_rendering()
    renderer.update_scene(data, camera="frontview")
    depth = renderer.render()
    renderer.close()
    assert depth[:16].mean() > depth[-16:].mean()
    env.close()


@pytest.mark.parametrize("task_id", TASK_IDS[:1] + TASK_IDS[-1:])
def test_registered_as_gymnasium_id(task_id):
    env = gym.make(f"ccdata/{task_id}", render=False)
    obs, _ = env.reset(seed=0)
    assert obs["state"].shape == (39,)
    env.close()


def test_unknown_task_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown task 'nope'.*reach-xy"):
        ccdata.make_env("nope")
