"""Evaluation: fixed layouts, the benchmark's discounted return, the due episodes in one batch.

Every evaluation point plays, for each task due, one episode per fixed layout seed; a task's
episodes play together, one batched `model.act` per step for those still running, each from a
fresh acting state (`play_episodes`). Batching changes no episode: a deterministic policy
plays the same episodes batched as one by one (tested); MPPI's sampling noise is drawn per
batch, so a stochastic planner's episodes are reproducible for a given seed and batch, not
equal to one-by-one play. `Evaluator` is the one place evaluation happens: the loop asks it
for the task being trained and, in a curriculum, every task seen so far (with its stored
heads, inside the continual method's `evaluating` view). Each task's evaluation at a global
step draws its random numbers from a stream of its own (`EVAL_NOISE_TAG`), so evaluating
is a function of the weights alone: it never shifts the random numbers training draws, and
the same weights evaluate the same anywhere.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ccdata.scoring import GAMMA, discounted_return, normalize
from ccfit.config_base import check
from ccfit.io import derived_seed, seeded
from ccfit.models.base import WorldModel, select_state
from ccfit.obs import model_input, obs_to_arrays
from ccfit.settings import AUTOCAST_MODES, autocast_context
from ccfit.train.env_workers import EnvWorkers, step_all

TRAIN_TAG, EVAL_TAG, ACTION_TAG, REPLAY_TAG, EVAL_NOISE_TAG = 0, 1, 2, 3, 4
"""Independent seed streams of a run (see `ccfit.io.derived_seed`)."""


@dataclass
class Episode:
    """One episode as played; `obs` and `action` only when recorded."""

    rewards: list[float]
    success: bool
    """Whether the task was solved at some step."""
    obs: dict[str, np.ndarray] | None = None
    """Observation arrays (T + 1, ...), as stored in replay."""
    action: np.ndarray | None = None
    """Actions (T, action_dim)."""

    @property
    def discounted_return(self) -> float:
        return discounted_return(self.rewards, GAMMA)


@dataclass
class EvalResult:
    returns: list[float]
    """Discounted return (gamma = ccdata.scoring.GAMMA) of each episode."""
    successes: list[bool]
    lengths: list[int]

    @classmethod
    def of(cls, episodes: Sequence[Episode]) -> EvalResult:
        return cls([e.discounted_return for e in episodes], [e.success for e in episodes],
                   [len(e.rewards) for e in episodes])  # fmt: skip

    @property
    def discounted_return(self) -> float:
        return float(np.mean(self.returns))

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes))


def eval_seeds(seed: int, task_index: int, episodes: int) -> list[int]:
    """The fixed evaluation layouts of curriculum task `task_index` (the same at every eval)."""
    return [derived_seed(seed, EVAL_TAG, j, task_index) for j in range(episodes)]


def normalized_or_none(task_id: str, ret: float) -> float | None:
    """Normalised return, or None when the oracle reference is not available yet."""
    try:
        return float(normalize(task_id, ret))
    except ValueError:
        return None


@torch.no_grad()
def play_episodes(envs: Sequence, model: WorldModel, heads: nn.Module, *, obs_mode: str,
                  seeds: Sequence[int], record: bool = False) -> list[Episode]:  # fmt: skip
    """One eval-mode episode per layout: `envs[i]` plays `seeds[i]`. All episodes step
    together; each step is one `model.act` on the batch of episodes still running, then one
    `step_all` (environments in worker processes step side by side)."""
    if len(envs) != len(seeds):
        raise ValueError(f"{len(envs)} envs for {len(seeds)} seeds")
    frames = [[obs_to_arrays(env.reset(seed=int(s))[0], obs_mode)] for env, s in zip(
        envs, seeds, strict=True)]  # fmt: skip
    actions: list[list[np.ndarray]] = [[] for _ in envs]
    rewards: list[list[float]] = [[] for _ in envs]
    success = [False] * len(envs)
    running = list(range(len(envs)))
    state = model.initial_state(heads, len(envs))
    while running:
        x = model_input([frames[i][-1] for i in running], model.device)
        batch_actions, state = model.act(x, heads, state, eval_mode=True)
        moves = [np.asarray(batch_actions[row], np.float32) for row in range(len(running))]
        outcomes = step_all([envs[i] for i in running], moves)
        still = []
        for row, (i, a, outcome) in enumerate(zip(running, moves, outcomes, strict=True)):
            obs, reward, terminated, truncated, info = outcome
            frames[i].append(obs_to_arrays(obs, obs_mode))
            actions[i].append(a)
            rewards[i].append(float(reward))
            success[i] = success[i] or bool(info["success"])
            if not (terminated or truncated):
                still.append(row)
        if len(still) < len(running):
            state = select_state(state, torch.tensor(still, dtype=torch.long))
            running = [running[row] for row in still]
    episodes = []
    for i in range(len(envs)):
        ep = Episode(rewards[i], success[i])
        if record:
            ep.obs = {k: np.stack([f[k] for f in frames[i]]) for k in frames[i][0]}
            ep.action = np.stack(actions[i])
        episodes.append(ep)
    return episodes


class EnvPool:
    """Environments per task, made when first needed and kept (episodes of one task play
    side by side, each needs its own). workers: 0, in this process; else in that many
    `EnvWorkers` processes (started when the first environment is needed), a task's j-th
    environment on worker j mod workers, so a task's episodes render in parallel.
    episode_steps: agent steps after which an unsolved episode ends (the run's)."""

    def __init__(self, obs_mode: str, image_size: int, workers: int = 0, *,
                 episode_steps: int) -> None:  # fmt: skip
        self.obs_mode, self.image_size, self.workers = obs_mode, image_size, workers
        self.episode_steps = episode_steps
        self._envs: dict[str, list] = {}
        self._remote: EnvWorkers | None = None

    def get(self, task_id: str, n: int) -> list:
        from ccdata.env import make_env

        render = self.obs_mode == "pixels"
        if self.workers and self._remote is None:
            self._remote = EnvWorkers(self.workers, render=render, image_size=self.image_size,
                                      episode_steps=self.episode_steps)  # fmt: skip
        envs = self._envs.setdefault(task_id, [])
        while len(envs) < n:
            envs.append(self._remote.make(task_id, worker=len(envs)) if self._remote else
                        make_env(task_id, render=render, image_size=self.image_size,
                                 episode_steps=self.episode_steps))  # fmt: skip
        return envs[:n]

    def close(self) -> None:
        for envs in self._envs.values():
            for env in envs:
                env.close()
        self._envs.clear()
        if self._remote is not None:
            self._remote.close()
            self._remote = None


def eval_record(task_id: str, task_index: int, stage: int, global_step: int,
                task_step: int | None, res: EvalResult) -> dict:  # fmt: skip
    """One line of metrics.jsonl: the means over the episodes, and each episode's discounted
    return (`returns`, in layout order), from which a score's spread and standard error
    follow."""
    ret = res.discounted_return
    return {
        "task": task_id, "task_index": task_index, "stage": stage,
        "global_step": global_step, "task_step": task_step, "discounted_return": ret,
        "normalized_return": normalized_or_none(task_id, ret),
        "success_rate": res.success_rate, "episodes": len(res.returns),
        "returns": [float(r) for r in res.returns],
    }  # fmt: skip


def submit_request(evaluator, request: dict) -> None:
    """Submit an evaluation `request` as an evaluator's `pending` lists it (tasks, stage,
    global_step, task_step and, where it names them, episodes): a fresh one, or one a
    checkpoint or a curriculum's state held when the run stopped. Only a request that names
    its episodes passes them on, so an evaluator written to the interface before
    `end_eval_episodes` (a test double) still serves the others."""
    more = {"episodes": request["episodes"]} if request.get("episodes") else {}
    evaluator.submit(request["tasks"], stage=request["stage"], global_step=request["global_step"],
                     task_step=request["task_step"], **more)  # fmt: skip


class Evaluator:
    """Evaluation of a run: the tasks that can be evaluated (their heads), their fixed
    layouts, and the environments they play on. Requests are `submit`ted and their records
    collected with `results`, in submission order; here they are computed at once, in the
    calling process (`ccfit.train.eval_worker.AsyncEvaluator` computes them beside training).

    model: the world model; task_ids: curriculum index -> task id of the tasks it may
    evaluate; seed, obs_mode, image_size, episodes, episode_steps: the run's. view: task
    index -> the context a task is evaluated in (the continual method's `evaluating`, e.g.
    PackNet's masks); None: no view. autocast: the run's precision, resolved ('off' or 'bf16':
    `ccfit.settings.Execution.autocast`). env_workers: processes the
    environments step and render in (`EnvPool`; 0: this process).
    """

    def __init__(self, model: WorldModel, task_ids: Mapping[int, str], *, seed: int,
                 obs_mode: str, image_size: int, episodes: int, episode_steps: int,
                 view: Callable[[int], AbstractContextManager] | None = None,
                 autocast: str = "off", env_workers: int = 0) -> None:  # fmt: skip
        self.model, self.task_ids = model, dict(task_ids)
        self.seed, self.obs_mode, self.episodes = seed, obs_mode, episodes
        check(autocast in AUTOCAST_MODES, f"Evaluator takes a resolved precision "
                                          f"{AUTOCAST_MODES}, got {autocast!r}")  # fmt: skip
        self.autocast = autocast
        self.view = view
        self.heads: dict[int, nn.Module] = {}
        """Heads each evaluable task is evaluated with (stored heads, and the current ones)."""
        self.envs = EnvPool(obs_mode, image_size, env_workers, episode_steps=episode_steps)
        self._done: list[dict] = []

    def submit(self, tasks: Sequence[int], *, stage: int, global_step: int,
               task_step: int | None, episodes: int | None = None) -> None:  # fmt: skip
        """Evaluate `tasks` with the weights as they are now; see `evaluate`."""
        self._done += self.evaluate(tasks, stage=stage, global_step=global_step,
                                    task_step=task_step, episodes=episodes)  # fmt: skip

    def results(self, until: int | None = -1) -> list[dict]:
        """Records of submitted requests not returned yet, in submission order, after waiting
        for the requests submitted before global step `until` (None: all; -1: none)."""
        done, self._done = self._done, []
        return done

    @property
    def pending(self) -> list[dict]:
        """Submitted requests whose records are not computed yet (none here)."""
        return []

    def evaluate(self, tasks: Sequence[int], *, stage: int, global_step: int,
                 task_step: int | None, episodes: int | None = None) -> list[dict]:  # fmt: skip
        """Records (metrics.jsonl lines) of `tasks` at this point; `task_step` is the step of
        the task being trained, set on its own record only; `episodes`: layouts each task
        plays (None: the run's `episodes`; the first layouts are the same for any count)."""
        model = self.model
        was_training = model.training
        model.eval()
        records = []
        try:
            for i in tasks:
                seeds = eval_seeds(self.seed, i, episodes or self.episodes)
                envs = self.envs.get(self.task_ids[i], len(seeds))
                noise = derived_seed(self.seed, EVAL_NOISE_TAG, global_step, i)
                with (
                    self.view(i) if self.view is not None else nullcontext(),
                    seeded(noise, model.device),
                    autocast_context(model.device, self.autocast),
                ):
                    eps = play_episodes(envs, model, self.heads[i], obs_mode=self.obs_mode,
                                        seeds=seeds)  # fmt: skip
                records.append(eval_record(self.task_ids[i], i, stage, global_step,
                                           task_step if i == stage else None,
                                           EvalResult.of(eps)))  # fmt: skip
        finally:
            model.train(was_training)
        return records

    def close(self) -> None:
        self.envs.close()
