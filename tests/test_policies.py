"""Exploration policies: random and noisy-oracle, their parameters and determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest

import ccdata
from ccdata.policies import NoisyOracle, RandomPolicy


def rollout_actions(policy, task_id="pnp-cube", seed=0, steps=20):
    env = ccdata.make_env(task_id, seed=seed, render=False)
    obs, _ = env.reset()
    policy.reset()
    actions = []
    for _ in range(steps):
        a = policy.act(obs)
        actions.append(a)
        obs, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            break
    env.close()
    return np.stack(actions)


def test_random_is_uniform_in_range_and_seeded():
    a = rollout_actions(ccdata.make_policy("random", "pnp-cube", seed=1), steps=200)
    assert a.dtype == np.float32 and a.min() >= -1 and a.max() <= 1
    assert abs(a.mean()) < 0.1 and a.std() > 0.5  # uniform on [-1, 1]: std 0.577
    again = rollout_actions(ccdata.make_policy("random", "pnp-cube", seed=1), steps=200)
    np.testing.assert_array_equal(a, again)


def test_noisy_oracle_stays_near_the_oracle_and_records_its_parameters():
    oracle = rollout_actions(ccdata.make_policy("oracle", "pnp-cube"))
    noisy = ccdata.make_policy("noisy-oracle", "pnp-cube", seed=0, noise_std=0.1, random_prob=0.0)
    assert isinstance(noisy, NoisyOracle)
    assert noisy.params() == {"noise_std": 0.1, "random_prob": 0.0}
    a = rollout_actions(noisy)
    n = min(len(a), len(oracle))
    # Same start state, small noise: the first action differs from the oracle's by the noise.
    assert 0 < np.abs(a[0] - oracle[0]).max() < 0.5
    assert a.shape[1] == 4 and np.abs(a).max() <= 1 and n > 1


def test_noisy_oracle_random_prob_one_is_uniform():
    policy = NoisyOracle(ccdata.make_policy("oracle", "reach-xy"), noise_std=0.0,
                         random_prob=1.0, seed=3)  # fmt: skip
    a = rollout_actions(policy, "reach-xy", steps=100)
    assert a.std() > 0.4


def test_bad_policy_name_and_parameters():
    with pytest.raises(ValueError, match="unknown policy 'greedy'.*oracle, noisy-oracle, random"):
        ccdata.make_policy("greedy", "reach-xy")
    with pytest.raises(ValueError, match="random_prob"):
        ccdata.make_policy("noisy-oracle", "reach-xy", random_prob=1.5)
    assert isinstance(ccdata.make_policy("random", "reach-xy"), RandomPolicy)


# ---------------------------------------------------------------- calibrated noisy oracle


def dataset_noisy_rates(task_id: str, episodes: int = 20) -> float:
    """Success rate of the noisy-oracle episodes a default dataset holds for `task_id` (its
    first `episodes`, seed 0), rolled out state-only with the dataset's own seeds."""
    from ccdata.calibration import noisy_oracle_rollouts
    from ccdata.episode_plan import EpisodeSpec, episode_seed, policy_seed

    seeds = [episode_seed(0, task_id, "noisy-oracle", i) for i in range(episodes)]
    assert EpisodeSpec(task_id, 0, "noisy-oracle", 0, seeds[0]).seed == seeds[0]
    noise = ccdata.get_task(task_id).exploration
    out = noisy_oracle_rollouts(task_id, noise, [(s, policy_seed(s)) for s in seeds])
    return float(np.mean(out["successes"]))


def check_band(task_ids) -> None:
    from ccdata.calibration import TARGET_BAND

    rates = {t: dataset_noisy_rates(t) for t in task_ids}
    low, high = TARGET_BAND
    outside = {t: r for t, r in rates.items() if not low <= r <= high}
    assert not outside, f"noisy-oracle success outside {TARGET_BAND} on 20 episodes: {outside}"


@pytest.mark.parametrize("task_id", ["reach-xy", "box-close"])
def test_noisy_oracle_succeeds_about_half_the_time_on_an_easy_and_a_precise_task(task_id):
    check_band([task_id])


@pytest.mark.slow
def test_noisy_oracle_succeeds_about_half_the_time_on_every_task():
    check_band(list(ccdata.TASKS))


def test_noisy_oracle_defaults_to_the_tasks_calibration():
    for task_id in ("reach-xy", "drawer-pnp"):
        calibrated = ccdata.get_task(task_id).exploration
        policy = ccdata.make_policy("noisy-oracle", task_id, seed=0)
        assert policy.params() == calibrated.to_dict()
    assert (
        ccdata.make_policy("noisy-oracle", "reach-xy", noise_std=0.05).params()["random_prob"]
        == ccdata.get_task("reach-xy").exploration.random_prob
    )


def test_calibration_search_reaches_the_target_and_is_reproducible():
    from ccdata.calibration import at_level, calibrate, calibration_seeds, success_rate

    noise, rate, history = calibrate("reach-xz", target=0.5, episodes=10, tolerance=0.15)
    assert abs(rate - 0.5) <= 0.15
    assert history[0]["level"] == 1.0 and history[-1]["success_rate"] == rate
    assert (noise.noise_std, noise.random_prob) == (
        history[-1]["noise_std"],
        history[-1]["random_prob"],
    )
    # More noise, fewer successes; the same seeds give the same rate.
    seeds = calibration_seeds(10)
    assert success_rate("reach-xz", noise, seeds) == rate
    assert success_rate("reach-xz", at_level(16.0), seeds) < rate
    assert at_level(16.0).random_prob == 1.0


def test_calibrate_refine_starts_at_the_tasks_calibration_in_smaller_steps(capsys):
    """`ccdata calibrate --refine`: the first evaluation is the task's stored noise, the next
    one level x1.5 away (a target no 8-episode rate can hit keeps the search going)."""
    from ccdata.cli import main

    stored = ccdata.get_task("reach-xz").exploration
    main(["calibrate", "--task", "reach-xz", "--refine", "--target", "0.37", "--tolerance",
          "0", "--episodes", "8", "--iterations", "2"])  # fmt: skip
    steps = [json.loads(x) for x in capsys.readouterr().err.splitlines() if x.startswith("{")]
    assert len(steps) == 2
    assert (steps[0]["noise_std"], steps[0]["random_prob"]) == (
        stored.noise_std,
        stored.random_prob,
    )
    ratio = steps[1]["level"] / steps[0]["level"]
    assert ratio == pytest.approx(1.5, rel=1e-3) or ratio == pytest.approx(1 / 1.5, rel=1e-3)
    # More noise when the stored one succeeded too often, less when too rarely.
    assert (ratio > 1) == (steps[0]["success_rate"] > 0.37)


def test_a_task_must_declare_its_exploration_noise():
    from ccdata.tasks import TaskSpec

    reach = ccdata.get_task("reach-xy")
    with pytest.raises(ValueError, match="declare its calibrated exploration"):
        TaskSpec(
            id="x",
            title="x",
            instruction="x",
            success="x",
            scene=reach.scene,
            oracle=reach.oracle,
            components={"action": ("reach",)},
        )
