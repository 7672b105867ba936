"""Reference measurements per task, stored as package data (`references.json`).

Regenerate with `ccdata references`. Each task's reference is the oracle's mean discounted
return over a fixed block of seeds that no other part of the toolkit uses (the '100' of the
normalised score), and, on the same layouts, the noisy oracle's success rate with the task's
calibrated exploration noise (what the dataset cards quote).
"""

from __future__ import annotations

import json
import os
import tempfile
from importlib import metadata
from pathlib import Path

import numpy as np

from ccdata.calibration import noisy_oracle_rollouts
from ccdata.env import DEFAULT_EPISODE_STEPS, make_env
from ccdata.errors import InputError
from ccdata.policies import make_policy
from ccdata.scoring import GAMMA, REFERENCE_FILE, discounted_return, references
from ccdata.tasks import TASKS, get_task

REFERENCE_SEED_BASE = 900_000
"""Reference episodes use seeds REFERENCE_SEED_BASE + i."""
NOISY_POLICY_SEED_OFFSET = 10**6
"""The noisy oracle's own seed on reference layout s is s + NOISY_POLICY_SEED_OFFSET."""


def oracle_rollouts(task_id: str, seeds) -> dict:
    """Discounted return, success and length of the oracle on each seed (state only), on the
    benchmark's episodes (the score's 100 is defined on them)."""
    env = make_env(task_id, render=False, episode_steps=DEFAULT_EPISODE_STEPS)
    policy = make_policy("oracle", task_id)
    returns, successes, lengths = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        policy.reset()
        rewards = []
        for _ in range(DEFAULT_EPISODE_STEPS):
            obs, reward, terminated, truncated, info = env.step(policy.act(obs))
            rewards.append(reward)
            if terminated or truncated:
                break
        returns.append(discounted_return(rewards))
        successes.append(bool(info["success"]))
        lengths.append(len(rewards))
    env.close()
    return {"returns": returns, "successes": successes, "lengths": lengths}


def _versions() -> dict:
    out = {}
    for pkg in ("ccbench", "metaworld", "mujoco", "gymnasium", "numpy"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _existing(path: Path) -> dict:
    """The references already at `path`, which the new ones are added to (checked before any
    rollout: a path that cannot take them fails at once)."""
    if path.is_dir() or not path.parent.is_dir():
        raise InputError(
            f"cannot write references to {path}: "
            f"{'a folder' if path.is_dir() else 'no folder ' + str(path.parent)}"
        )
    if not path.exists():
        return {"tasks": {}}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(f"{path} holds no references to add to ({err})") from None
    if not isinstance(data, dict) or not isinstance(data.get("tasks"), dict):
        raise InputError(f"{path} holds no references to add to (no 'tasks' object)")
    return data


def write_references(tasks=None, episodes: int = 50, path: Path | None = None) -> Path:
    """Roll out the oracle on `episodes` fixed seeds per task and store the mean returns."""
    task_ids = list(tasks) if tasks else list(TASKS)
    for t in task_ids:
        get_task(t)
    if episodes < 1:
        raise InputError("episodes must be >= 1")
    path = path or Path(__file__).with_name(REFERENCE_FILE)
    data = _existing(path)
    seeds = [REFERENCE_SEED_BASE + i for i in range(episodes)]
    for task_id in task_ids:
        r = oracle_rollouts(task_id, seeds)
        noise = get_task(task_id).exploration
        noisy = noisy_oracle_rollouts(
            task_id, noise, [(s, s + NOISY_POLICY_SEED_OFFSET) for s in seeds]
        )
        data["tasks"][task_id] = {
            "mean_discounted_return": float(np.mean(r["returns"])),
            "std_discounted_return": float(np.std(r["returns"])),
            "success_rate": float(np.mean(r["successes"])),
            "median_length": float(np.median(r["lengths"])),
            "episodes": episodes,
            "noisy_oracle_success_rate": float(np.mean(noisy["successes"])),
            "noisy_oracle_mean_discounted_return": float(np.mean(noisy["returns"])),
            "noisy_oracle": noise.to_dict(),
        }
    data["tasks"] = dict(sorted(data["tasks"].items()))
    data.update(
        gamma=GAMMA,
        episode_steps=DEFAULT_EPISODE_STEPS,
        seeds=f"{REFERENCE_SEED_BASE} + range(episodes)",
        policy="oracle; noisy-oracle with each task's calibrated noise",
        versions=_versions(),
    )
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")
    os.chmod(tmp, 0o644)  # mkstemp makes it private; this is package data
    os.replace(tmp, path)
    references.cache_clear()
    return path
