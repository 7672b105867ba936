"""Calibrating the noisy oracle per task: its episodes should succeed about half the time.

One global noise level cannot serve every task: noise that leaves reaching at 100% success
makes the precise tasks (box-close, drawer-pnp) fail almost always, and exploration data with no
successes (or no failures) tells a world model little about the task. Each task therefore
carries its own `ExplorationNoise` (`TaskSpec.exploration`), found here and typed once into the
task's registration.

The search moves along one line of noise settings, `level * (0.3 std, 0.1 random_prob)` (the
original global setting is level 1), narrowing a bracket on log(level) until the success rate
on a fixed block of seeds is near the target. Rollouts are state-only (no rendering), and every
candidate level replays the same seeds with the same policy streams, so the measured rate
changes with the level only, not with the luck of the draw.
"""

from __future__ import annotations

import math

import numpy as np

from ccdata.env import DEFAULT_EPISODE_STEPS, make_env
from ccdata.errors import InputError
from ccdata.scoring import discounted_return
from ccdata.tasks import ExplorationNoise, get_task

CALIBRATION_SEED_BASE = 800_000
"""Calibration episodes use layout seeds CALIBRATION_SEED_BASE + i (used nowhere else)."""
BASE_NOISE = ExplorationNoise(noise_std=0.3, random_prob=0.1)
"""Level 1 of the search line."""
TARGET_BAND = (0.3, 0.7)
"""Noisy-oracle success rates a calibrated task must reach on its datasets' episodes."""


def level_of(noise: ExplorationNoise) -> float:
    """The level of a noise on the search line (by its std)."""
    return noise.noise_std / BASE_NOISE.noise_std


def at_level(level: float) -> ExplorationNoise:
    """The noise at `level` on the search line (random_prob saturates at 1: a random policy)."""
    return ExplorationNoise(
        noise_std=round(BASE_NOISE.noise_std * level, 4),
        random_prob=round(min(1.0, BASE_NOISE.random_prob * level), 4),
    )


def noisy_oracle_rollouts(
    task_id: str,
    noise: ExplorationNoise,
    seeds: list[tuple[int, int]],
) -> dict[str, list]:
    """State-only noisy-oracle episodes: success, length and discounted return per episode.

    `seeds`: (layout seed, policy seed) pairs; the same pairs give the same episodes."""
    from ccdata.policies import make_policy

    # Calibrated on the benchmark's episodes: the noise is tuned for the datasets' defaults.
    env = make_env(task_id, render=False, episode_steps=DEFAULT_EPISODE_STEPS)
    out: dict[str, list] = {"successes": [], "lengths": [], "returns": []}
    try:
        for layout_seed, policy_seed in seeds:
            policy = make_policy(
                "noisy-oracle",
                task_id,
                seed=policy_seed,
                noise_std=noise.noise_std,
                random_prob=noise.random_prob,
            )
            policy.reset()
            obs, _ = env.reset(seed=int(layout_seed))
            rewards, success = [], False
            for _ in range(DEFAULT_EPISODE_STEPS):
                obs, reward, terminated, truncated, info = env.step(policy.act(obs))
                rewards.append(reward)
                success = bool(info["success"])
                if terminated or truncated:
                    break
            out["successes"].append(success)
            out["lengths"].append(len(rewards))
            out["returns"].append(discounted_return(rewards))
    finally:
        env.close()
    return out


def calibration_seeds(episodes: int) -> list[tuple[int, int]]:
    return [(CALIBRATION_SEED_BASE + i, CALIBRATION_SEED_BASE + 10**6 + i) for i in range(episodes)]


def success_rate(task_id: str, noise: ExplorationNoise, seeds: list[tuple[int, int]]) -> float:
    return float(np.mean(noisy_oracle_rollouts(task_id, noise, seeds)["successes"]))


def calibrate(
    task_id: str,
    target: float = 0.5,
    episodes: int = 40,
    iterations: int = 8,
    tolerance: float = 0.1,
    low: float = 1 / 16,
    high: float = 16.0,
    start: float = 1.0,
    step: float = 4.0,
    on_step=None,
) -> tuple[ExplorationNoise, float, list[dict]]:
    """Search the noise level whose success rate on `episodes` calibration seeds is within
    `tolerance` of `target`, in at most `iterations` evaluations. Returns (the best noise found,
    its rate, every evaluation); `on_step(record)` sees each evaluation as it is made.

    The success rate falls with the level, steeply. Starting from level `start` (1, or a
    previous calibration to refine), the search steps by x`step` until the target is bracketed,
    then interpolates log(level) linearly between the bracket's rates (kept inside the
    bracket's central 80%, so it always shrinks)."""
    get_task(task_id)
    if (
        not 0 < target < 1
        or episodes < 1
        or iterations < 1
        or not 0 < low <= start <= high
        or step <= 1
    ):
        raise InputError(
            "need 0 < target < 1, episodes >= 1, iterations >= 1, low <= start <= high, step > 1"
        )
    seeds = calibration_seeds(episodes)
    lo_bound, hi_bound = math.log(low), math.log(high)
    below: tuple[float, float] | None = None  # (log level, rate > target): too little noise
    above: tuple[float, float] | None = None  # (log level, rate <= target): too much
    x = math.log(start)
    history: list[dict] = []
    for _ in range(iterations):
        noise = at_level(math.exp(x))
        rate = success_rate(task_id, noise, seeds)
        record = {
            "task": task_id,
            "level": round(math.exp(x), 4),
            **noise.to_dict(),
            "success_rate": rate,
            "episodes": episodes,
        }
        history.append(record)
        if on_step is not None:
            on_step(record)
        if abs(rate - target) <= tolerance:
            break
        if rate > target:
            below = (x, rate)
        else:
            above = (x, rate)
        if below is not None and above is not None:
            (x0, r0), (x1, r1) = below, above
            t = (r0 - target) / (r0 - r1)
            x = x0 + min(0.9, max(0.1, t)) * (x1 - x0)
        elif above is None:
            if x >= hi_bound:
                break  # succeeds too often even at the highest level
            x = min(hi_bound, x + math.log(step))
        else:
            if x <= lo_bound:
                break  # fails too often even at the lowest level
            x = max(lo_bound, x - math.log(step))
    best = min(history, key=lambda r: (abs(r["success_rate"] - target), r["level"]))
    return ExplorationNoise(best["noise_std"], best["random_prob"]), best["success_rate"], history
