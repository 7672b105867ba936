"""Exploration policies: random and noisy-oracle, their parameters and determinism."""

from __future__ import annotations

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
