"""Real replay buffers filled with short random episodes, for model tests."""

from __future__ import annotations

import numpy as np

from ccfit.replay import ReplayBuffer


def random_episode(cfg, rng: np.random.Generator, steps: int, success: bool) -> dict:
    """`ReplayBuffer.add_episode` arguments of a random episode in `cfg.obs_mode`: rewards in
    [-1, 0), and reward 0 with terminated = 1 on the last step of a success."""
    if cfg.obs_mode == "state":
        obs = {"state": rng.normal(size=(steps + 1, cfg.state_dim)).astype(np.float32)}
    else:
        size = cfg.image_size
        obs = {
            "pixels": rng.integers(0, 256, (steps + 1, 9, size, size), dtype=np.uint8),
            "proprio": rng.normal(size=(steps + 1, cfg.proprio_dim)).astype(np.float32),
        }
    reward = -rng.uniform(0.05, 1.0, steps).astype(np.float32)
    terminated = np.zeros(steps, np.float32)
    if success:
        reward[-1], terminated[-1] = 0.0, 1.0
    action = rng.uniform(-1, 1, (steps, cfg.action_dim)).astype(np.float32)
    return {"obs": obs, "action": action, "reward": reward, "terminated": terminated}


def random_buffer(
    cfg, seed: int = 0, task: int = 0, episodes: int = 6, steps: tuple[int, int] = (2, 9)
) -> ReplayBuffer:
    """A buffer of `episodes` random episodes of `steps` (low, high) transitions, every second
    one a success, labelled with `task`; sampling seeded with `seed`."""
    rng = np.random.default_rng([seed, task])
    buf = ReplayBuffer(10_000, seed=seed)
    for i in range(episodes):
        length = int(rng.integers(steps[0], steps[1] + 1))
        buf.add_episode(**random_episode(cfg, rng, length, success=i % 2 == 1), task=task)
    return buf
