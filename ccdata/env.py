"""The gymnasium environment every benchmark task is played through.

It wraps a task's scene with the benchmark's dynamics: action repeat 2 (agent rate 40 Hz),
250 agent steps by default (`episode_steps`), termination exactly on success (absorbing),
reward = the scene's dense shaped reward rescaled from [0, 10] to [-1, 0] with 0 on success,
three upright cameras plus proprioception and the privileged state.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ccdata.render import CAMERAS, MultiCameraRenderer, RenderSettings
from ccdata.tasks import get_task
from ccdata.tasks.base import STATE_DIM

ACTION_REPEAT = 2
"""Meta-World steps per agent step (each is 5 physics steps of 2.5 ms)."""
DEFAULT_EPISODE_STEPS = 250
"""The benchmark's agent steps per episode (500 Meta-World steps): `make_env`'s default, at
which the oracle references are measured. A run or dataset that wants another length passes it
(`episode_steps`); nothing changes this value."""
AGENT_DT = ACTION_REPEAT * 5 * 0.0025
"""Seconds per agent step: 0.025 s, i.e. 40 Hz."""
FPS = round(1.0 / AGENT_DT)
PROPRIO_DIM = 7


class TaskEnv(gym.Env):
    """One benchmark task. Use `ccdata.make_env(task_id, seed=..., image_size=...,
    episode_steps=...)`."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        task_id: str,
        seed: int | None = None,
        image_size: int = 64,
        render: bool = True,
        render_settings: RenderSettings | None = None,
        render_mode: str | None = None,
        episode_steps: int = DEFAULT_EPISODE_STEPS,
    ) -> None:
        if episode_steps < 1:
            raise ValueError(f"episode_steps must be >= 1, got {episode_steps}")
        self.episode_steps = int(episode_steps)
        """Agent steps after which an unsolved episode is truncated."""
        self.task = get_task(task_id)
        self.render_settings = render_settings or RenderSettings(image_size=image_size)
        self.render_mode = render_mode
        self.scene = self.task.scene()
        self._renderer = (
            MultiCameraRenderer(self.scene.model, self.render_settings)
            if render or render_mode == "rgb_array"
            else None
        )
        self._with_images = render
        size = self.render_settings.image_size
        obs_spaces: dict[str, spaces.Space] = {}
        if render:
            for cam in CAMERAS:
                obs_spaces[cam] = spaces.Box(0, 255, (size, size, 3), np.uint8)
        obs_spaces["proprio"] = spaces.Box(-np.inf, np.inf, (PROPRIO_DIM,), np.float32)
        obs_spaces["state"] = spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
        self.observation_space = spaces.Dict(obs_spaces)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self._init_seed = seed
        self._seeded = False
        self._t = 0
        self._done = True
        self._last_hand = np.zeros(3)

    @property
    def task_id(self) -> str:
        return self.task.id

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        if seed is None and not self._seeded:
            seed = self._init_seed
        super().reset(seed=seed)
        self._seeded = True
        state = self.scene.reset_scene(self.np_random)
        self._t = 0
        self._done = False
        self._last_hand = state[0:3].copy()
        return self._observe(state, np.zeros(3)), {"success": False, "task": self.task.id}

    def step(self, action: np.ndarray):
        if self._done:
            raise RuntimeError("the episode has ended (success or time limit): call reset()")
        action = np.asarray(action, dtype=np.float32).reshape(-1)
        if action.shape != (4,):
            raise ValueError(f"action must have shape (4,), got {action.shape}")
        action = np.clip(action, -1.0, 1.0)
        raw_rewards = []
        success = False
        for _ in range(ACTION_REPEAT):
            state, raw, info = self.scene.sim_step(action)
            raw_rewards.append(raw)
            if info["success"]:
                success = True
                break
        self._t += 1
        raw = float(np.mean(raw_rewards))
        reward = 0.0 if success else float(np.clip(raw / 10.0 - 1.0, -1.0, 0.0))
        terminated = success
        truncated = (not success) and self._t >= self.episode_steps
        self._done = terminated or truncated
        velocity = (state[0:3] - self._last_hand) / AGENT_DT
        self._last_hand = state[0:3].copy()
        obs = self._observe(state, velocity)
        # The scene's own entries (stage flags, distances) of the last physics step, as
        # Meta-World's info carries its reward terms.
        scene_info = {k: v for k, v in info.items() if k != "success"}
        return (
            obs,
            reward,
            terminated,
            truncated,
            {**scene_info, "success": success, "task": self.task.id, "raw_reward": raw},
        )

    def _observe(self, state: np.ndarray, velocity: np.ndarray) -> dict[str, np.ndarray]:
        obs: dict[str, np.ndarray] = {}
        if self._with_images:
            obs.update(self._renderer.render(self.scene.data))
        obs["proprio"] = np.concatenate([state[0:3], velocity, state[3:4]]).astype(np.float32)
        obs["state"] = state.astype(np.float32)
        return obs

    def render(self) -> np.ndarray | None:
        """The three views side by side (H, 3W, 3)."""
        if self._renderer is None:
            return None
        images = self._renderer.render(self.scene.data)
        return np.concatenate([images[c] for c in CAMERAS], axis=1)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.scene.close()


def make_env(
    task_id: str,
    seed: int | None = None,
    image_size: int = 64,
    render: bool = True,
    render_settings: RenderSettings | None = None,
    episode_steps: int = DEFAULT_EPISODE_STEPS,
) -> TaskEnv:
    """Build task `task_id`'s environment. `render=False` omits the camera images;
    `episode_steps`: agent steps after which an unsolved episode is truncated."""
    return TaskEnv(
        task_id,
        seed=seed,
        image_size=image_size,
        render=render,
        render_settings=render_settings,
        episode_steps=episode_steps,
    )


def register_gym_ids() -> None:
    """Register every task as gymnasium id `ccdata/<task-id>`."""
    from ccdata.tasks import TASKS

    for task_id in TASKS:
        env_id = f"ccdata/{task_id}"
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="ccdata.env:TaskEnv", kwargs={"task_id": task_id})
