"""The BinPnP family: four colourings of one bin-to-bin transfer, and its oracle."""

from __future__ import annotations

import numpy as np
import pytest

import ccdata
from ccdata.policies.base import State
from ccdata.tasks import get_task
from ccdata.tasks.base import CUBE_RGBA
from ccdata.tasks.bins import BIN_RGBA, SUCCESS_RADIUS, BinScene

TASK_IDS = ("bin-red-blue", "bin-yellow-blue", "bin-red-purple", "bin-yellow-purple")
BIN_HALF_INNER = 0.09
"""Inner half-width of a bin (walls at +-0.095, 5 mm thick)."""


def run_oracle(task_id: str, seed: int) -> tuple[bool, int, list[float], dict]:
    """(success, agent steps, rewards, last step's obs) of one oracle episode."""
    env = ccdata.make_env(task_id, render=False)
    oracle = get_task(task_id).oracle()
    obs, _ = env.reset(seed=seed)
    oracle.reset()
    rewards = []
    for _ in range(ccdata.env.DEFAULT_EPISODE_STEPS):
        obs, reward, terminated, truncated, info = env.step(oracle.act(obs))
        rewards.append(reward)
        if terminated or truncated:
            break
    env.close()
    return info["success"], len(rewards), rewards, obs


def topview(task_id: str, seed: int = 3) -> np.ndarray:
    env = ccdata.make_env(task_id, image_size=64)
    obs, _ = env.reset(seed=seed)
    env.close()
    return obs["topview"].astype(int)


def test_registered_in_curriculum_order_with_components():
    assert [t for t in ccdata.TASKS if t.startswith("bin-")] == list(TASK_IDS)
    spec = get_task("bin-yellow-purple")
    assert spec.components["perception"] == ("yellow-bin", "purple-bin")
    assert spec.components["action"] == ("reach-object", "grasp", "lift", "transport", "release")
    assert spec.instruction == "Move the green cube from the yellow bin to the purple bin."
    assert get_task("bin-red-blue").components["perception"] == ("red-bin", "blue-bin")


def test_unknown_colour_is_rejected_with_choices():
    with pytest.raises(ValueError, match="red.*yellow.*blue.*purple"):
        BinScene("green", "blue")


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_oracle_succeeds_on_first_seeds(task_id):
    for seed in range(5):
        success, steps, rewards, obs = run_oracle(task_id, seed)
        assert success, f"{task_id} seed {seed} failed after {steps} steps"
        state = State.parse(obs["state"])
        assert np.linalg.norm(state.obj1 - state.goal) <= SUCCESS_RADIUS + 1e-6
        # Shaped reward: in range, and better while carrying than at the start.
        assert all(-1.0 <= r <= 0.0 for r in rewards)
        assert rewards[-1] == 0.0 and max(rewards[-10:-1]) > rewards[0] + 0.3


def test_success_terminates_and_episode_is_absorbing():
    env = ccdata.make_env("bin-red-blue", render=False)
    oracle = get_task("bin-red-blue").oracle()
    obs, _ = env.reset(seed=1)
    for _ in range(ccdata.env.DEFAULT_EPISODE_STEPS):
        obs, reward, terminated, truncated, info = env.step(oracle.act(obs))
        assert terminated == info["success"]
        if terminated:
            break
    assert terminated and not truncated and reward == 0.0
    with pytest.raises(RuntimeError):
        env.step(np.zeros(4, np.float32))


def test_rewards_stay_in_range_under_random_actions():
    env = ccdata.make_env("bin-yellow-blue", render=False)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    rewards = []
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 4))
        rewards.append(reward)
        assert 0.0 <= info["raw_reward"] <= 10.0
        if terminated or truncated:
            break
    assert all(-1.0 <= r <= 0.0 for r in rewards)
    assert max(rewards) < 0.0, "random flailing should not finish the task"


def test_reset_randomises_the_cube_inside_the_source_bin():
    env = ccdata.make_env("bin-red-blue", render=False)
    starts = [State.parse(env.reset(seed=s)[0]["state"]) for s in range(20)]
    cubes = np.array([s.obj1 for s in starts])
    assert len({tuple(c.round(4)) for c in cubes}) == 20
    assert np.ptp(cubes[:, 0]) > 0.05 and np.ptp(cubes[:, 1]) > 0.02
    # Fully inside the source bin (centre (-0.12, 0.7)), resting on its floor.
    assert np.all(np.abs(cubes[:, 0] + 0.12) + 0.02 < BIN_HALF_INNER)
    assert np.all(np.abs(cubes[:, 1] - 0.7) + 0.02 < BIN_HALF_INNER)
    np.testing.assert_allclose(cubes[:, 2], 0.03, atol=1e-3)
    for s in starts:
        np.testing.assert_allclose(s.goal, [0.12, 0.7, 0.0], atol=1e-6)
        np.testing.assert_allclose(s.obj2, 0.0)
        np.testing.assert_allclose(s.obj2_quat, [0.0, 0.0, 0.0, 1.0])
    again = State.parse(env.reset(seed=7)[0]["state"])
    np.testing.assert_array_equal(again.obj1, starts[7].obj1)


def test_bins_take_their_task_colours_and_the_cube_stays_green():
    for task_id in TASK_IDS:
        _, source, target = task_id.split("-")
        scene = get_task(task_id).scene()
        model = scene.model
        for body, colour in (("binA", source), ("binB", target)):
            geoms = np.flatnonzero(model.geom_bodyid == model.body(body).id)
            assert len(geoms) == 6
            np.testing.assert_allclose(model.geom_rgba[geoms], [BIN_RGBA[colour]] * 6, atol=1e-6)
        np.testing.assert_allclose(model.geom("cubeGeom").rgba, CUBE_RGBA, atol=1e-6)
        scene.close()


def test_first_frames_differ_in_colour_exactly_where_the_bins_are():
    images = {t: topview(t) for t in TASK_IDS}

    def changed(a: str, b: str) -> np.ndarray:
        return np.abs(images[a] - images[b]).max(axis=-1) > 40

    source = changed("bin-red-blue", "bin-yellow-blue")
    target = changed("bin-red-blue", "bin-red-purple")
    assert source.sum() > 30 and target.sum() > 30
    assert not (source & target).any()
    # The source bin (x = -0.12) and the target bin (x = +0.12) are side by side in the image.
    assert np.nonzero(source)[1].mean() + 5 < np.nonzero(target)[1].mean()
    # Same layout elsewhere: only the bins' colours change between tasks.
    assert not (changed("bin-yellow-blue", "bin-yellow-purple") & source).any()

    def mean_rgb(task_id: str, mask: np.ndarray) -> np.ndarray:
        return images[task_id][mask].mean(axis=0)

    red, yellow = mean_rgb("bin-red-blue", source), mean_rgb("bin-yellow-purple", source)
    assert red[0] > 2 * red[1] and red[0] > 2 * red[2]
    assert yellow[1] > 2 * red[1] and yellow[0] > 2 * yellow[2]
    blue, purple = mean_rgb("bin-yellow-blue", target), mean_rgb("bin-red-purple", target)
    assert blue[2] > 2 * blue[0] and blue[2] > blue[1] + 50
    assert purple[0] > 2 * blue[0] and purple[2] > 2 * purple[1]


@pytest.mark.slow
@pytest.mark.parametrize("task_id", TASK_IDS)
def test_oracle_succeeds_on_95_of_100_held_out_seeds(task_id):
    results = [run_oracle(task_id, seed) for seed in range(1000, 1100)]
    successes = sum(success for success, *_ in results)
    assert successes >= 95, f"{task_id}: {successes}/100"
