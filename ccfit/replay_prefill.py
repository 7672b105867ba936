"""A task's replay seeded from the suite dataset's episodes of that task.

`episode_to_replay` turns one episode (`ccfit.data.load_episodes`) into replay-buffer arrays
through `ccfit.obs`, the same function live observations go through, and `seed_buffer`
preloads a replay buffer with a task's episodes (`replay_items`: each as replay arrays).

The observation after an episode's last action (for a successful episode: the success state,
which every terminal transition leads to) is recorded by ccdata datasets of format 2 as the
episode's last frame (`is_final_observation`), so every transition of every episode, the
terminal successes included, reaches the buffer in every observation mode. Datasets of format 1
lack that frame: their successful episodes get it back by replaying their actions without
rendering (state mode only; in pixel mode their last transition is dropped).
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np

from ccdata.dataset_format import CCDATA_META, FINAL_KEY
from ccdata.errors import InputError
from ccdata.render import RenderSettings
from ccfit.data import (
    ACTION_KEY,
    CAMERA_KEYS,
    EPISODE_SEED_KEY,
    PROPRIO_KEY,
    REWARD_KEY,
    STATE_KEY,
    SUCCESS_KEY,
    episode_lengths,
    load_episodes,
    resolve_source,
)
from ccfit.obs import obs_to_arrays

DEMO_POLICY = "oracle"
"""The dataset policy whose episodes are demonstrations (`--train.demo_fraction`)."""


def final_observation(episode: dict[str, np.ndarray], task_id: str) -> dict[str, np.ndarray]:
    """The env observation after the episode's last action (LeRobot does not store it).

    Replays the recorded actions from the recorded `episode_seed` without rendering (so the
    result has 'state' and 'proprio' but no images) and checks that the replay reproduces
    every recorded state; a mismatch raises ValueError.
    """
    from ccdata.env import make_env

    if EPISODE_SEED_KEY not in episode:
        raise InputError(f"episode lacks {EPISODE_SEED_KEY!r}: cannot replay it")
    states, actions = _stack(episode[STATE_KEY]), _stack(episode[ACTION_KEY])
    # Long enough for every recorded action, whatever episode length the dataset was made with.
    env = make_env(task_id, render=False, episode_steps=max(1, len(actions)))
    try:
        obs, _ = env.reset(seed=int(np.asarray(episode[EPISODE_SEED_KEY]).reshape(-1)[0]))
        for t, action in enumerate(actions):
            if not np.allclose(obs["state"], states[t], atol=1e-5):
                raise InputError(
                    f"episode {episode.get('episode_index')}: replay departs from the recorded "
                    f"states at step {t} (another task, or another simulator version?)"
                )
            obs, *_ = env.step(action)
    finally:
        env.close()
    return obs


def has_final_observation(episode: dict[str, np.ndarray]) -> bool:
    """Whether the episode's last frame is its recorded final observation (format 2)."""
    if FINAL_KEY not in episode:
        return False
    final = np.asarray(episode[FINAL_KEY]).reshape(-1).astype(bool)
    if final[:-1].any():
        raise InputError(
            f"episode {episode.get('episode_index')}: {FINAL_KEY} is set before its last frame"
        )
    return bool(final[-1])


def episode_to_replay(
    episode: dict[str, np.ndarray], mode: str, final_obs: dict[str, np.ndarray] | None = None
) -> dict:
    """One loaded episode -> `ReplayBuffer.add_episode` keyword arguments: obs (T+1, ...),
    action (T, 4), reward (T,), terminated (T,) (the success that ended the episode).

    Frames are (observation t, action t, next.reward t, next.success t). A format-2 episode ends
    with its final observation (`FINAL_KEY`), so all T transitions are kept. For a format-1
    episode, the final observation may be given as `final_obs` (state mode, e.g. from
    `final_observation`); without it the last transition is dropped (T observations, T-1
    transitions).
    """
    recorded = has_final_observation(episode)
    if recorded and final_obs is not None:
        raise ValueError("the episode records its final observation: pass no final_obs")
    frames = len(episode[ACTION_KEY])
    length = frames - 1 if recorded else frames  # transitions stored
    if length < 1 or (length < 2 and final_obs is None and not recorded):
        raise ValueError(f"episode {episode.get('episode_index')} holds no transition")
    obs = {"state": _stack(episode[STATE_KEY]), "proprio": _stack(episode[PROPRIO_KEY])}
    if mode == "pixels":
        if final_obs is not None:
            raise ValueError("final_obs is for state mode (it carries no camera images)")
        for cam, key in CAMERA_KEYS.items():
            if key not in episode:
                raise ValueError(f"episode lacks {key!r} (load with images=True)")
            obs[cam] = episode[key]
    arrays = obs_to_arrays(obs, mode)
    keep = length
    if final_obs is not None:
        last = obs_to_arrays(final_obs, mode)
        arrays = {k: np.concatenate([v, last[k][None]]) for k, v in arrays.items()}
    elif not recorded:
        keep = length - 1
    success = np.asarray(episode[SUCCESS_KEY], dtype=np.float32).reshape(-1)
    return {
        "obs": arrays,
        "action": _stack(episode[ACTION_KEY])[:keep],
        "reward": np.asarray(episode[REWARD_KEY], dtype=np.float32).reshape(-1)[:keep],
        "terminated": success[:keep],
    }


def check_render(source, render: RenderSettings, endpoint: str | None = None) -> None:
    """InputError unless the dataset's images were rendered with `render` (the run's): a
    model trained on frames rendered one way and acting on frames rendered another would be
    measuring the difference."""
    root = resolve_source(source, endpoint)
    path = root / CCDATA_META
    recorded = json.loads(path.read_text()).get("render") if path.is_file() else None
    if recorded is None:
        raise InputError(f"{root} records no render settings ({CCDATA_META}): its images "
                         "cannot seed a pixel run")  # fmt: skip
    wanted = render.to_dict()
    differ = sorted(k for k in wanted.keys() | recorded.keys()
                    if wanted.get(k) != recorded.get(k))  # fmt: skip
    if differ:
        found = ", ".join(f"{k} {recorded.get(k)!r} (run: {wanted.get(k)!r})" for k in differ)
        raise InputError(f"seed dataset {root} was rendered differently: {found}; generate "
                         "it with the run's settings or pass --seed_dataset null")  # fmt: skip


def seed_buffer(
    buffer,
    source,
    task_id: str,
    obs_mode: str,
    render: RenderSettings | None = None,
    task_index: int = 0,
    endpoint: str | None = None,
    demos: bool = True,
) -> dict[str, int]:
    """Preload `task_id`'s episodes of a LeRobot dataset into `buffer` (through
    `buffer.add_episode(obs=(T+1, ...), action=(T, 4), reward=(T,), terminated=(T,), task=,
    demo=)`); returns how many were added per policy. See `replay_items` for what is kept.
    demos: mark the oracle's episodes as demonstrations, which the buffer keeps beside its
    ring for `--train.demo_fraction` (only worth their memory when that is on)."""
    added: dict[str, int] = {}
    for _, policy, item in replay_items(source, task_id, obs_mode, render, endpoint):
        buffer.add_episode(**item, task=task_index, demo=demos and policy == DEMO_POLICY)
        added[policy] = added.get(policy, 0) + 1
    return added


def demonstration_rows(source, task_ids, endpoint: str | None = None) -> int:
    """The most replay rows one of `task_ids` has in demonstrations (the oracle's episodes of
    `source`): what a buffer keeps beside its ring for `--train.demo_fraction`. Counted from
    two index columns, without reading the episodes; an episode stores one row per frame,
    plus its final observation where the dataset does not record it (counted, to be safe)."""
    return max(sum(n + 1 for n in episode_lengths(source, task, DEMO_POLICY, endpoint))
               for task in task_ids)  # fmt: skip


def replay_items(
    source, task_id: str, obs_mode: str, render: RenderSettings | None = None,
    endpoint: str | None = None,
) -> Iterator[tuple[int, str | None, dict]]:  # fmt: skip
    """(episode index, policy name (None if the dataset does not say), `episode_to_replay`
    item) of each of `task_id`'s episodes of a LeRobot dataset, in episode order. In pixel
    mode the dataset must have been rendered with `render` (the run's settings; None: ccdata's
    defaults at the dataset's own size).

    Every transition is kept, the successes that ended episodes included: format-2 datasets
    record each episode's final observation; for format-1 datasets it is replayed for successful
    episodes in state mode (`final_observation`), and dropped otherwise (an episode left with
    no transition is skipped).
    """
    if obs_mode == "pixels" and render is not None:
        check_render(source, render, endpoint)
    episodes = load_episodes(source, task=task_id, images=obs_mode == "pixels", endpoint=endpoint)
    for ep in episodes:
        final = None
        if not has_final_observation(ep):
            if obs_mode == "state" and bool(np.asarray(ep[SUCCESS_KEY]).reshape(-1)[-1]):
                final = final_observation(ep, task_id)
            if final is None and len(ep[ACTION_KEY]) < 2:
                continue  # one frame: no transition once the unobserved last one is dropped
        yield int(ep["episode_index"]), ep.get("policy"), episode_to_replay(ep, obs_mode, final)


def _stack(values) -> np.ndarray:
    return np.asarray(values, dtype=np.float32)
