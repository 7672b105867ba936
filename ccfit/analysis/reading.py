"""What a TD-MPC2-style world model (`encode`, `next`, `reward`, `Q`, `pi`) reads along recorded
episodes: the reward head's error per step, its Q at the episode's actions against the
discounted return the episode obtained, its Q at the policy's mean actions in the same states
(above the episode's where the value rates the policy's own choice higher), the latent
dynamics' one-step error and the policy's mean action against the episode's. Oracle,
noisy-oracle and random episodes of a suite's dataset give the contrast: a model that knows
its task values the oracle's states above the random ones as their returns are ordered, and
predicts their rewards. `acting` then says whether it acts on that knowledge: its task's
normalised return through MPPI and through the policy's mean alone."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import numpy as np
import torch

from ccfit.replay_prefill import episode_to_replay


def discounted_returns(rewards: np.ndarray, discount: float) -> np.ndarray:
    """The discounted return from every step of an episode's `rewards`."""
    g = np.zeros(len(rewards) + 1)
    for t in reversed(range(len(rewards))):
        g[t] = rewards[t] + discount * g[t + 1]
    return g[:-1]


def episode_reading(model, heads, episodes: list[dict[str, np.ndarray]],
                    view: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext
                    ) -> dict:  # fmt: skip
    """Means over `episodes` (state observations, `load_episodes(..., images=False)`) of what
    the module docstring lists, read through `heads` inside `view()` (a continual method's
    view of an earlier task, e.g. `method.evaluating(i, backbone)`)."""
    keys = ("reward", "q", "q_pi", "ret", "dyn", "act")
    errors: dict[str, list[float]] = {k: [] for k in keys}
    for episode in episodes:
        rows = episode_to_replay(episode, "state")
        obs = {k: torch.as_tensor(v).float() for k, v in rows["obs"].items()}
        actions = torch.as_tensor(rows["action"]).float()
        rewards = np.asarray(rows["reward"], dtype=np.float64).reshape(-1)
        with torch.no_grad(), view():
            z = model.encode(obs)
            reward = model.two_hot.logits_to_scalar(model.reward(z[:-1], actions, heads))[:, 0]
            q = model.Q(z[:-1], actions, heads, return_type="avg")[:, 0]
            step = ((model.next(z[:-1], actions) - z[1:]) ** 2).sum(-1) / (z[1:] ** 2).sum(-1)
            _, info = model.pi(z[:-1], heads)
            q_pi = model.Q(z[:-1], info["mean"], heads, return_type="avg")[:, 0]
        errors["reward"].append(np.abs(reward.numpy() - rewards).mean())
        errors["q"].append(q.numpy().mean())
        errors["q_pi"].append(q_pi.numpy().mean())
        errors["ret"].append(discounted_returns(rewards, model.cfg.discount).mean())
        errors["dyn"].append(step.numpy().mean())
        errors["act"].append(np.abs(info["mean"].numpy() - rows["action"]).mean())
    mean = {k: float(np.mean(v)) for k, v in errors.items()}
    return {"reward_abs_err": round(mean["reward"], 4), "Q_mean": round(mean["q"], 2),
            "Q_pi_mean": round(mean["q_pi"], 2), "return_mean": round(mean["ret"], 2),
            "dynamics_rel_err": round(mean["dyn"], 4),
            "pi_vs_episode_action": round(mean["act"], 3)}  # fmt: skip


View = Callable[[int], contextlib.AbstractContextManager]
"""Task index -> a continual method's view of that task (`Evaluator`'s `view`)."""


def acting(model, heads, index: int, task: str, view: View | None = None, *,
           episode_steps: int) -> dict:  # fmt: skip
    """Task `task` (index `index` of its run) played as evaluation plays it, on 10 layouts x 3
    noise seeds, through MPPI and through the policy's mean action alone: the normalised
    return per noise seed for each. `view`: as `Evaluator`'s; `episode_steps`: the run's."""
    from ccfit.train.evaluate import Evaluator

    evaluator = Evaluator(model, {index: task}, seed=0, obs_mode="state", image_size=64,
                          episodes=10, episode_steps=episode_steps, view=view)  # fmt: skip
    evaluator.heads[index] = heads
    out = {}
    for mode, acts_alone in (("mppi", False), ("policy_mean", True)):
        with policy_alone(model, acts_alone):
            records = [evaluator.evaluate([index], stage=99, global_step=noise, task_step=None)[0]
                       for noise in (1, 2, 3)]  # fmt: skip
        out[mode] = [round(r["normalized_return"], 1) for r in records]
    return out


@contextlib.contextmanager
def policy_alone(model, on: bool = True) -> Iterator[None]:
    """Inside: a TD-MPC2-style `model` acts by its policy's mean action alone instead of
    planning (its `plan` replaced; `on=False`: unchanged)."""
    if not on:
        yield
        return
    mppi = model.plan

    def policy_mean(z, heads, prev_mean, *, eval_mode):
        _, info = model.pi(z, heads)
        return info["mean"], prev_mean

    model.plan = policy_mean
    try:
        yield
    finally:
        model.plan = mppi
