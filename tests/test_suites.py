"""Suites, their order, and composition matrices derived from declared components."""

from __future__ import annotations

import numpy as np
import pytest

import ccdata
from ccdata.env import DEFAULT_EPISODE_STEPS as EPISODE_STEPS
from ccdata.policies import make_policy

EXPECTED_ORDER = {
    "Reach": ["reach-xy", "reach-xz", "reach-yz", "reach-xyz"],
    "Grasp": ["pick-cube", "place-cube", "pnp-cube"],
    "BinPnP": ["bin-red-blue", "bin-yellow-blue", "bin-red-purple", "bin-yellow-purple"],
    "PnPBlock": ["pnp-red-block", "pnp-blue-block", "stack-blocks"],
    "DrawerPnP": ["pnp-cube", "drawer-open", "drawer-pnp"],
    "PnPBoxClose": ["pnp-cube", "box-close", "box-pnp-close"],
}
AXES = {
    "Reach": "action",
    "Grasp": "action",
    "BinPnP": "perception",
    "PnPBlock": "perception",
    "DrawerPnP": "full",
    "PnPBoxClose": "full",
}

# By hand from the components each task declares (row i reuses column j).
EXPECTED_MATRICES = {
    # Every pair of reach planes shares a displacement axis.
    "Reach": np.ones((4, 4)),
    # pick and place share nothing; pick-and-place shares with both.
    "Grasp": [[1, 0, 1], [0, 1, 1], [1, 1, 1]],
    # Rows share a bin colour with earlier tasks: yellow->blue shares blue with red->blue,
    # red->purple shares red with red->blue, yellow->purple shares yellow and purple.
    "BinPnP": [[1, 1, 1, 0], [1, 1, 0, 1], [1, 0, 1, 1], [0, 1, 1, 1]],
    "PnPBlock": [[1, 0, 1], [0, 1, 1], [1, 1, 1]],
    "DrawerPnP": [[1, 0, 1], [0, 1, 1], [1, 1, 1]],
}


def test_six_suites_in_paper_order():
    assert list(ccdata.SUITES) == list(EXPECTED_ORDER)
    for name, order in EXPECTED_ORDER.items():
        suite = ccdata.get_suite(name)
        assert [t.id for t in suite.tasks] == order
        assert suite.axis == AXES[name]
        assert suite.composition is suite.tasks[-1]


def test_pick_place_cube_is_one_task_everywhere():
    grasp = ccdata.get_suite("Grasp").tasks[-1]
    for name in ("DrawerPnP", "PnPBoxClose"):
        assert ccdata.get_suite(name).tasks[0] is grasp


@pytest.mark.parametrize("name", EXPECTED_MATRICES)
def test_composition_matrices(name):
    matrix = ccdata.get_suite(name).composition_matrix()
    assert matrix.dtype == bool
    np.testing.assert_array_equal(matrix, np.asarray(EXPECTED_MATRICES[name], dtype=bool))


@pytest.mark.parametrize("name", list(EXPECTED_ORDER))
def test_matrix_properties(name):
    m = ccdata.get_suite(name).composition_matrix()
    assert m.shape == (len(EXPECTED_ORDER[name]),) * 2
    assert m.diagonal().all(), "every task reuses itself"
    assert (m == m.T).all(), "sharing a component is symmetric"
    # The composition task reuses something of every primitive... except where the axis
    # says otherwise (BinPnP's yellow->purple shares nothing with red->blue).
    assert m[-1].sum() >= 2


def test_box_close_reuses_grasping_on_the_full_axis():
    m = ccdata.get_suite("PnPBoxClose").composition_matrix()
    assert m[2].all()


def test_unknown_suite_lists_valid_names():
    with pytest.raises(ValueError, match="unknown suite 'Nope'.*PnPBoxClose"):
        ccdata.get_suite("Nope")


def test_normalize_floor_and_reference():
    from ccdata.scoring import floor_return, oracle_reference

    assert ccdata.normalize("reach-xy", floor_return()) == pytest.approx(0.0)
    assert ccdata.normalize("reach-xy", oracle_reference("reach-xy")) == pytest.approx(100.0)
    # Not capped: better than the oracle's mean scores above 100.
    assert ccdata.normalize("reach-xy", 0.0) > 100.0
    with pytest.raises(ValueError, match="unknown task"):
        ccdata.normalize("nope", -1.0)


def test_every_task_has_an_oracle_reference():
    from ccdata.scoring import references

    refs = references()
    assert set(refs["tasks"]) == set(ccdata.TASKS)
    assert refs["gamma"] == ccdata.GAMMA == 0.99
    for task_id, ref in refs["tasks"].items():
        assert ref["success_rate"] >= 0.95, task_id


def _replayed(task_id: str, actions: list[np.ndarray], seed: int) -> tuple[list, list]:
    """State observations and rewards of `task_id` along `actions`, from reset seed `seed`."""
    env = ccdata.make_env(task_id, seed=0, render=False)
    obs, _ = env.reset(seed=seed)
    states, rewards = [obs["state"]], []
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        states.append(obs["state"])
        rewards.append(reward)
        if terminated or truncated:
            break
    env.close()
    return states, rewards


def _oracle_actions(task_id: str, seed: int) -> list[np.ndarray]:
    """The actions of one successful oracle episode of `task_id` (every phase of its task)."""
    env = ccdata.make_env(task_id, seed=0, render=False)
    policy = make_policy("oracle", task_id)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    actions, info = [], {}
    for _ in range(EPISODE_STEPS):
        actions.append(policy.act(obs))
        obs, _, terminated, truncated, info = env.step(actions[-1])
        if terminated or truncated:
            break
    env.close()
    assert info["success"], f"the oracle failed seed {seed} of {task_id}"
    return actions


@pytest.mark.parametrize("name", list(ccdata.SUITES))
def test_tasks_declared_one_mdp_from_state_are_and_no_others(name):
    # Each task's oracle plays one episode and every later task of the suite replays its
    # actions from the same reset: the same state observations and rewards all along mean one
    # MDP from state, which the suite must declare (`same_from_state`), and only then.
    suite, seed = ccdata.get_suite(name), 5
    for i, first in enumerate(suite.task_ids[:-1]):
        actions = _oracle_actions(first, seed)
        states, rewards = _replayed(first, actions, seed)
        for task_id in suite.task_ids[i + 1 :]:
            other_states, other_rewards = _replayed(task_id, actions, seed)
            pairs = zip(states, other_states, strict=True)  # equal rewards: equal lengths
            same = other_rewards == rewards and all(
                a.shape == b.shape and np.array_equal(a, b) for a, b in pairs
            )
            assert same == suite.same_task_from_state(first, task_id), f"{name}: {task_id}, {first}"


def test_same_from_state_groups_name_the_suites_tasks():
    with pytest.raises(ValueError, match="same_from_state"):
        ccdata.suites.Suite("X", "perception", ("a", "b"), "", same_from_state=(("a", "c"),))
