"""Grasp and PnPBlock scenes: oracles solve them, episodes end on success, layouts vary."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import ccdata
from ccdata.tasks import get_task
from ccdata.tasks.blocks import BlockScene
from ccdata.tasks.grasp import GraspScene

GRASP_TASKS = ("pick-cube", "place-cube", "pnp-cube")
BLOCK_TASKS = ("pnp-red-block", "pnp-blue-block", "stack-blocks")
TASKS = GRASP_TASKS + BLOCK_TASKS


@functools.cache
def run_oracle(task_id: str, seed: int) -> dict:
    """One oracle episode: its rewards, how it ended, and whether stepping on is refused."""
    env = ccdata.make_env(task_id, seed=seed, render=False)
    oracle = get_task(task_id).oracle()
    obs, _ = env.reset()
    oracle.reset()
    rewards, info = [], {"success": False}
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(oracle.act(obs))
        rewards.append(reward)
    try:
        env.step(np.zeros(4, np.float32))
        refused = False
    except RuntimeError:
        refused = True
    env.close()
    return {
        "rewards": np.array(rewards),
        "success": info["success"],
        "terminated": terminated,
        "truncated": truncated,
        "refused": refused,
    }


def first_state(task_id: str, seed: int) -> np.ndarray:
    env = ccdata.make_env(task_id, seed=seed, render=False)
    obs, _ = env.reset()
    env.close()
    return obs["state"].astype(np.float64)


@pytest.mark.parametrize("task_id", TASKS)
@pytest.mark.parametrize("seed", range(5))
def test_oracle_succeeds_and_success_terminates(task_id, seed):
    run = run_oracle(task_id, seed)
    assert run["success"]
    assert run["terminated"] and not run["truncated"]
    assert len(run["rewards"]) < ccdata.env.DEFAULT_EPISODE_STEPS
    assert run["rewards"][-1] == 0.0
    assert run["refused"], "stepping after success must raise"


@pytest.mark.parametrize("task_id", TASKS)
def test_rewards_stay_in_range_and_start_low(task_id):
    for seed in range(3):
        rewards = run_oracle(task_id, seed)["rewards"]
        assert np.all(rewards >= -1.0) and np.all(rewards <= 0.0)
        # Only the success step earns 0; the episode starts far from it.
        assert np.all(rewards[:-1] < 0.0)
        assert rewards[0] < -0.15


@pytest.mark.parametrize("task_id", TASKS)
def test_reset_randomises_layout(task_id):
    states = [first_state(task_id, seed) for seed in range(3)]
    objects = [s[4:7] for s in states]
    goals = [s[36:39] for s in states]
    for i in range(3):
        for j in range(i + 1, 3):
            assert np.linalg.norm(objects[i] - objects[j]) > 1e-3
            assert np.linalg.norm(goals[i] - goals[j]) > 1e-3
    # Same seed, same layout.
    np.testing.assert_array_equal(first_state(task_id, 7), first_state(task_id, 7))


@pytest.mark.parametrize("seed", range(5))
def test_place_cube_starts_held_above_table(seed):
    s = first_state("place-cube", seed)
    hand, gripper, cube, goal = s[0:3], s[3], s[4:7], s[36:39]
    assert cube[2] > 0.08, "the cube starts in the air"
    assert np.linalg.norm(cube[:2] - hand[:2]) < 0.02, "between the fingers"
    assert gripper < 0.6, "gripper closed on the cube"
    assert goal[2] == pytest.approx(0.02), "the goal is on the table"
    assert np.linalg.norm(cube[:2] - goal[:2]) >= 0.12


@pytest.mark.parametrize("seed", range(5))
def test_pick_cube_marker_floats_above_cube(seed):
    s = first_state("pick-cube", seed)
    cube, goal = s[4:7], s[36:39]
    assert 0.1 <= goal[2] - cube[2] <= 0.2
    assert np.linalg.norm(goal[:2] - cube[:2]) <= 0.05


@pytest.mark.parametrize("task_id", BLOCK_TASKS + ("pnp-cube",))
def test_layout_keeps_objects_apart_on_the_table(task_id):
    for seed in range(10):
        s = first_state(task_id, seed)
        points = [s[4:6], s[36:38]] + ([s[11:13]] if task_id == "stack-blocks" else [])
        for i in range(len(points)):
            assert -0.15 <= points[i][0] <= 0.15 and 0.5 <= points[i][1] <= 0.8
            for j in range(i + 1, len(points)):
                assert np.linalg.norm(points[i] - points[j]) >= 0.1


@pytest.mark.parametrize("task_id", ("pnp-red-block", "pnp-blue-block"))
def test_single_block_scene_has_one_block(task_id):
    env = ccdata.make_env(task_id, seed=0, render=False)
    colour = task_id.split("-")[1]
    other = "blue" if colour == "red" else "red"
    names = {env.scene.model.body(i).name for i in range(env.scene.model.nbody)}
    assert f"{colour}_block" in names and f"{other}_block" not in names
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs["state"][11:18], 0.0)
    env.close()


def test_stack_rewards_are_staged():
    env = ccdata.make_env("stack-blocks", seed=1, render=False)
    oracle = get_task("stack-blocks").oracle()
    obs, _ = env.reset()
    oracle.reset()
    raw, stages = [], []
    terminated = truncated = False
    while not (terminated or truncated):
        obs, _, terminated, truncated, info = env.step(oracle.act(obs))
        raw.append(info["raw_reward"])
        stages.append(env.scene.evaluate_state(obs["state"], np.zeros(4))[1]["stage"])
    env.close()
    raw, stages = np.array(raw), np.array(stages)
    assert terminated
    before = raw[:-1][stages[:-1] == 1]
    after = raw[:-1][stages[:-1] == 2]
    assert len(before) and len(after), "both stages are visited"
    assert before.max() <= 5.0 <= after.min()


def test_bad_scene_arguments_are_rejected():
    with pytest.raises(ValueError, match="pick"):
        GraspScene("grab")
    with pytest.raises(ValueError, match="red"):
        BlockScene(("green",))
    with pytest.raises(ValueError, match="stacking"):
        BlockScene(("blue", "red"), stack=True)


@pytest.mark.slow
@pytest.mark.parametrize("task_id", TASKS)
def test_oracle_succeeds_on_held_out_seeds(task_id):
    successes = sum(run_oracle(task_id, seed)["success"] for seed in range(1000, 1100))
    assert successes >= 95
