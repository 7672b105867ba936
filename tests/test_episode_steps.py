"""The episode length is a setting passed where it is used: `make_env(episode_steps=...)`, a
dataset's `episode_steps`, a run's `train.episode_steps` (which reaches TD-MPC2's discount);
the benchmark's 250 is their default and changes no run made before the setting existed."""

from __future__ import annotations

import json

import numpy as np
import pytest

import ccdata
from ccdata.env import DEFAULT_EPISODE_STEPS
from ccdata.errors import InputError
from ccdata.record import GenerateConfig
from ccfit.config import CurriculumConfig, TaskRunConfig
from ccfit.config_base import ConfigError, identity
from ccfit.config_parse import parse_cli, resolve

TINY = dict(suite="Reach", episodes=1, explore_episodes=1, image_size=32)


def _truncated_at(env, steps: int) -> int | None:
    """The step at which `env`'s episode (zero actions) is truncated, within `steps` steps."""
    env.reset(seed=0)
    for t in range(1, steps + 1):
        *_, terminated, truncated, _ = env.step(np.zeros(4, np.float32))
        assert not terminated
        if truncated:
            return t
    return None


def test_an_environment_ends_its_episodes_at_the_length_it_was_given():
    env = ccdata.make_env("reach-xy", render=False, episode_steps=7)
    try:
        assert _truncated_at(env, 10) == 7
    finally:
        env.close()
    default = ccdata.make_env("reach-xy", render=False)
    try:
        assert default.episode_steps == DEFAULT_EPISODE_STEPS == 250
    finally:
        default.close()
    with pytest.raises(ValueError, match="episode_steps must be >= 1"):
        ccdata.make_env("reach-xy", render=False, episode_steps=0)


def test_a_datasets_episode_length_is_a_setting_recorded_with_it():
    from ccdata.dataset_format import ccdata_metadata, check_identity
    from ccdata.episode_plan import plan
    from ccdata.writer import rollout_episode

    short = GenerateConfig(**TINY, episode_steps=5)
    spec = next(s for s in plan(short) if s.policy == "random")  # never succeeds in 5 steps
    env = ccdata.make_env(spec.task_id, render_settings=short.render_settings,
                          episode_steps=short.episode_steps)  # fmt: skip
    try:
        episode = rollout_episode(env, spec, short)
    finally:
        env.close()
    assert len(episode["action"]) == 5 + 1  # five steps, then the final observation's frame
    assert ccdata_metadata(short)["env"]["episode_steps"] == 5
    assert short.to_dict()["episode_steps"] == 5
    # A dataset made before the setting existed holds no episode_steps in its identity: it is
    # the benchmark's length, and a dataset of another length is refused.
    default = GenerateConfig(**TINY)
    assert "episode_steps" not in default.identity() and "episode_steps" in short.identity()
    check_identity(default.identity(), default, ".")
    with pytest.raises(InputError, match="episode_steps: found 250, requested 5"):
        check_identity(default.identity(), short, ".")
    with pytest.raises(InputError, match="episode_steps: found 5, requested 250"):
        check_identity(short.identity(), default, ".")
    with pytest.raises(InputError, match="episode_steps must be >= 1"):
        GenerateConfig(**TINY, episode_steps=0)
    with pytest.raises(InputError, match=r"max_steps must be in \[1, 5\]"):
        GenerateConfig(**TINY, episode_steps=5, max_steps=6)


def test_a_runs_episode_length_is_recorded_and_reaches_td_mpc2():
    base = {"suite": "Reach", "preset": "smoke", "model": {"type": "tdmpc2"}}
    default = resolve(CurriculumConfig, base)
    short = resolve(CurriculumConfig, {**base, "train": {"episode_steps": 25}})
    assert default.train.episode_steps == default.model.episode_length == 250
    assert default.model.discount == pytest.approx(0.98)
    assert short.model.episode_length == 25 and short.model.discount == pytest.approx(0.95)
    assert short.to_dict()["train"]["episode_steps"] == 25  # config.json records it
    assert short.to_dict()["model"]["episode_length"] == 25
    model = {"type": "tdmpc2", "episode_length": 100}
    given = resolve(CurriculumConfig, {**base, "train": {"episode_steps": 25}, "model": model})
    assert given.model.episode_length == 100  # a value given is kept
    # At 250 the setting is no part of a run's identity: runs made before it are the same.
    ident = identity(default.to_dict())
    assert "episode_steps" not in ident["train"]
    assert identity(short.to_dict())["train"]["episode_steps"] == 25
    # A saved config read back is the same run.
    cli = parse_cli(TaskRunConfig, ["--task", "reach-xy", "--preset", "smoke",
                                    "--train.episode_steps=30"])  # fmt: skip
    back = resolve(TaskRunConfig, json.loads(json.dumps(cli.to_dict())))
    assert back == cli and back.train.episode_steps == 30


@pytest.mark.parametrize("steps", [0, -1])
def test_an_episode_length_below_one_is_a_config_error(steps):
    with pytest.raises(ConfigError, match=f"train.episode_steps must be >= 1, got {steps}"):
        resolve(TaskRunConfig, {"task": "reach-xy", "train": {"episode_steps": steps}})


def test_one_episode_must_fit_in_replay():
    with pytest.raises(ConfigError, match=r"buffer_capacity must be >= 1001 \(one episode"):
        train = {"episode_steps": 1000, "buffer_capacity": 1000}
        resolve(TaskRunConfig, {"task": "reach-xy", "train": train})


def test_the_evaluator_plays_the_runs_episode_length():
    """The run's length reaches the evaluator's environments (here and in worker processes,
    test_env_workers), not the benchmark's default."""
    from ccfit.train import EnvPool

    pool = EnvPool("state", 64, episode_steps=4)
    try:
        (env,) = pool.get("reach-xy", 1)
        assert _truncated_at(env, 6) == 4
    finally:
        pool.close()
