"""The shared online training loop (Algorithm 1's inner loop), one loop for every world model.

`Trainer` is handed its collaborators (env, model, heads, replay, continual method, evaluator,
logger) and runs Algorithm 1's inner loop on one task: random actions for the seed steps (the
model observes them), then `model.cfg.pretrain_updates` updates at once if the model is fresh
(the run's first task), then `model.cfg.train_ratio` updates per env step (fractions
accumulate), evaluation at a fixed interval, atomic checkpoints, and resume. When the task's
steps are done the continual method closes the task (`after_task`, then the updates it asks
for, e.g. PackNet's retraining), and the task is evaluated once more: its end-of-task score
C_i is that of the backbone the later tasks start from.

Determinism: every episode's layout seed is derived from (seed, episode index), evaluation uses
a fixed set of layouts, and the checkpoint stores every RNG state. The training episode in
progress is cut (stored as truncated) at every evaluation and step-interval checkpoint, so a
checkpoint never holds a half-played episode; wall-clock checkpoints wait for an episode end, and
so does a step-interval checkpoint at the end of the run's first seed phase while an evaluation
from before it still runs in a worker (training goes on instead of waiting for it there).
A resumed run therefore continues exactly as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ccdata.atomic import remove_partial_writes
from ccdata.errors import InputError
from ccdata.scoring import discounted_return
from ccfit.config import TrainConfig, stop_reached
from ccfit.config_base import identity
from ccfit.continual.base import ContinualMethod, close_task
from ccfit.io import atomic_torch_save, derived_seed, load_checkpoint, rng_state, set_rng_state
from ccfit.models.base import Batch, WorldModel
from ccfit.obs import model_input, obs_to_arrays
from ccfit.replay import ReplayBuffer
from ccfit.replay_store import ROWS_DIR, load_rows, save_rows
from ccfit.run_files import CHECKPOINT
from ccfit.settings import Execution, resolve_execution
from ccfit.train.evaluate import ACTION_TAG, TRAIN_TAG, Evaluator, submit_request
from ccfit.train.records import RunLogger
from ccfit.train.update import UpdateStep, load_backbone_optimizer_state

CHECKPOINT_KIND = "ccfit-task"
CHECKPOINT_VERSION = 4
TRAIN_LOG_EVERY = 250
"""Env steps between TensorBoard points of the averaged training losses."""


class Trainer:
    """Online model-based RL on one task; `run()` trains (resuming if a checkpoint exists).

    env: the task's env (its obs must carry what `obs_mode` needs; pixels need rendering).
    model, heads: a `WorldModel` and this task's heads.
    buffer: replay, possibly preloaded; episodes are added as `task_index`.
    evaluator: evaluates this task (its heads are registered there) and, in a curriculum,
        the earlier tasks it holds heads for.
    config: the loop's settings; seed and obs_mode: the run's.
    execution: the run's device, compile mode and precision, resolved (`ccfit.settings`;
        None: resolved from `config` on the model's device).
    logger: evaluation records and scalars (None: keep them in `self.evals` only).
    method: the continual method (None: plain training).
    run_dir: where `checkpoint.pt` goes (None: no checkpoints, no resume).
    global_offset: global step at which this task starts in a curriculum.
    stored_heads_loss: the loss of a batch through an earlier task's stored heads, offered to
        the method's penalty (`ReplayLosses`); a curriculum provides it.
    extendable: a checkpoint of fewer `config.steps` may be resumed (a single-task run
        extended: `ccfit train` where the model's training never reads its step budget); one
        that ran to its budget goes on as the longer run would have from there.
    backbone_optim: the previous task's `backbone_optimizer_state`, which this task's
        world-model optimiser starts from (`keep_backbone_optimizer`; None: fresh).
    stop_before_close: when the task's steps are done, checkpoint and return before the
        method closes the task (`ccfit.first_task`: the part every method shares); a run
        resumed from that checkpoint closes it. Not with `stop_score` (a task it ended early
        would train on when resumed).
    """

    def __init__(
        self, *, env, model: WorldModel, heads: nn.Module, buffer: ReplayBuffer,
        evaluator: Evaluator, config: TrainConfig, seed: int, obs_mode: str, task_id: str,
        execution: Execution | None = None, task_index: int = 0,
        logger: RunLogger | None = None,
        method: ContinualMethod | None = None, run_dir: str | Path | None = None,
        global_offset: int = 0, progress: bool = True,
        stored_heads_loss: Callable[[Batch, int], torch.Tensor] | None = None,
        extendable: bool = False, backbone_optim: dict | None = None,
        stop_before_close: bool = False,
    ) -> None:  # fmt: skip
        if stop_before_close and config.stop_score is not None:
            raise ValueError("stop_before_close with stop_score: a resumed run would train on")
        self.env, self.model, self.heads, self.buffer = env, model, heads, buffer
        self.evaluator = evaluator
        evaluator.heads[task_index] = heads
        self.cfg, self.seed, self.obs_mode = config, seed, obs_mode
        self.task_id, self.task_index = task_id, task_index
        self.logger, self.method = logger, method
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.global_offset, self.progress = global_offset, progress
        self.extendable = extendable
        self.stop_before_close = stop_before_close
        self.device = model.device
        self.execution = execution or resolve_execution(config, model.device)
        self.step = UpdateStep(model, heads, method, stored_heads_loss,
                               self.execution.autocast, graphs=self.execution.graphs)  # fmt: skip
        if backbone_optim is not None:
            load_backbone_optimizer_state(self.step.optim, model.backbone, backbone_optim)
        self.action_rng = np.random.default_rng(derived_seed(seed, ACTION_TAG, 0, task_index))

        self.task_step = 0
        self.updates = 0
        self.update_credit = 0.0
        self.episode_index = 0
        self.last_eval = -1
        self.last_checkpoint = -1
        self.finished = False
        """Whether the task was closed (the method's `after_task` and retraining done)."""
        self.evals: list[dict] = []
        self._episode: dict | None = None
        self._act_state: Any = None
        self._last_save = time.monotonic()
        self._checkpoint_owed = False
        self._train_logs: dict[str, list] = defaultdict(list)
        self._replay_files: list[dict] = []

    @property
    def global_step(self) -> int:
        return self.global_offset + self.task_step

    # -------------------------------------------------------------------------- main loop

    def run(self, wait: bool = True) -> dict | None:
        """Train to `config.steps` task steps and close the task; returns this task's last
        evaluation record. wait=False: return (None) without waiting for the evaluations
        still running, which the evaluator then holds for its next collector (a curriculum's
        next task trains meanwhile)."""
        from tqdm.auto import tqdm

        cfg = self.cfg
        if self.run_dir is not None:  # a killed process may have been writing these
            remove_partial_writes(self.run_dir, CHECKPOINT)
            remove_partial_writes(self.run_dir / ROWS_DIR, "rows-*.pt")
        if self.run_dir is not None and (self.run_dir / CHECKPOINT).exists():
            pending = self.load_checkpoint(self.run_dir / CHECKPOINT)
            if self.logger is not None:
                self.logger.rewind(self.global_step)
                done, pending = self.logger.settle(pending)
                self.evals += done
            for request in pending:  # with the checkpoint's weights, as when submitted
                self._submit(request)
        bar = tqdm(total=cfg.steps, initial=self.task_step, desc=self.task_id, unit="step",
                   disable=not self.progress, dynamic_ncols=True, mininterval=1.0)  # fmt: skip
        try:
            while self.task_step < cfg.steps and not self.finished:
                if self.task_step % cfg.eval_interval == 0 and self.last_eval != self.task_step:
                    self._cut_episode()
                    if self._learnt():
                        break
                    self._evaluate()
                if self._collect() and self._own_records():
                    rec = self._own_records()[-1]
                    bar.set_postfix(ret=f"{rec['discounted_return']:.1f}",
                                    succ=f"{rec['success_rate']:.2f}")  # fmt: skip
                if (self.task_step % cfg.checkpoint_interval == 0 and self.task_step > 0
                        and self.last_checkpoint != self.task_step):  # fmt: skip
                    self._cut_episode()
                    if self._may_put_off_checkpoint():
                        self._checkpoint_owed = True  # written once they are done, below
                    else:
                        self._checkpoint()
                self._env_step()
                if self.task_step >= cfg.seed_steps and self.buffer.can_sample(
                    self.model.cfg.seq_len
                ):
                    if self.updates == 0 and self.global_offset == 0:
                        # The run's first task and no update yet: the model is fresh.
                        self.extra_updates(self.model.cfg.pretrain_updates)
                    self.update_credit += self.model.cfg.train_ratio
                    while self.update_credit >= 1.0:
                        self.update_credit -= 1.0
                        self._update()
                self.task_step += 1
                bar.update(1)
                if self.task_step % TRAIN_LOG_EVERY == 0:
                    self._flush_train_logs()
                # At an episode end (nothing is cut), and not at a step still to be evaluated:
                # a run resumed from there would evaluate and log that step a second time.
                if (self._episode is None and self.task_step % cfg.eval_interval != 0
                        and (self._wall_clock_due() or self._owed_checkpoint_due())):  # fmt: skip
                    self._checkpoint()
            if not self.finished and self.stop_before_close:
                self._cut_episode()
                self._checkpoint()  # waits for every evaluation before this step
                return None
            if not self.finished:
                self._cut_episode()
                self._finish_task()
                self._evaluate(episodes=self.cfg.end_eval_episodes)
                self.finished = True
                self._checkpoint()
            if not wait:
                return None
            self._collect(until=None)
        finally:
            bar.close()
        return self._own_records()[-1]

    def _own_records(self) -> list[dict]:
        return [r for r in self.evals if r["task_index"] == self.task_index]

    def _learnt(self) -> bool:
        """Whether `stop_score` ends the task here. Waits for the evaluations still running,
        so that the step it ends at is the same with evaluation in a worker or in line."""
        if self.cfg.stop_score is None or self.task_step == 0:
            return False
        self._collect(until=self.global_step)
        return self._stop_reached(before=self.global_step)

    def _stop_reached(self, before: int) -> bool:
        """Whether this task's evaluations before global step `before` meet `stop_score`."""
        if self.cfg.stop_score is None:
            return False
        scores = [r["normalized_return"] for r in self._own_records()
                  if r["global_step"] < before]  # fmt: skip
        return stop_reached(scores, self.cfg.stop_score, self.cfg.stop_evals)

    def _finish_task(self) -> None:
        """The method closes the task (`close_task`): its retraining updates are normal
        updates."""
        close_task(self.method, self.task_index, self.model, self.buffer, self.extra_updates)

    def _autocast(self):
        return self.execution.autocast_context()

    def _wall_clock_due(self) -> bool:
        minutes = self.cfg.checkpoint_minutes
        return minutes > 0 and time.monotonic() - self._last_save >= 60.0 * minutes

    def _evaluations_before_now(self) -> bool:
        """Whether evaluations submitted before this step are still running: a checkpoint
        here would wait for them (it holds only this step's weights)."""
        return any(r["global_step"] < self.global_step for r in self.evaluator.pending)

    def _may_put_off_checkpoint(self) -> bool:
        """Whether this step-interval checkpoint is put off instead of waiting for the
        evaluations from before it: in the run's first seed phase only (its steps are random
        actions, seconds to redo), where the worker is still starting and evaluating the
        untrained model while training would otherwise wait for it. It is written at the
        first episode end after they are done (`_owed_checkpoint_due`), or waits at the next
        checkpoint step."""
        return (not self._checkpoint_owed and self.global_step <= self.cfg.seed_steps
                and self._evaluations_before_now())  # fmt: skip

    def _owed_checkpoint_due(self) -> bool:
        """Whether a put-off checkpoint can be written now, at an episode end, with no
        evaluation from before this step left. Episode ends are natural cut points, so where
        a checkpoint is written never changes what the run computes."""
        return self._checkpoint_owed and not self._evaluations_before_now()

    def _checkpoint(self) -> None:
        self._checkpoint_owed = False
        self.last_checkpoint = self.task_step
        self._last_save = time.monotonic()
        # Evaluations submitted at this step may still be running (their weights are the
        # checkpoint's, so a resumed run submits them again); earlier ones are waited for.
        self._collect(until=self.global_step)
        if self.run_dir is not None:
            # Replay's new rows first, then the checkpoint that lists them; files it no longer
            # lists go only once it is written.
            self._replay_files, stale = save_rows(self.buffer, self.run_dir, self._replay_files)
            atomic_torch_save(self.state_dict(), self.run_dir / CHECKPOINT)
            for path in stale:
                path.unlink(missing_ok=True)

    def _env_step(self) -> None:
        model, heads = self.model, self.heads
        if self._episode is None:
            seed = derived_seed(self.seed, TRAIN_TAG, self.episode_index, self.task_index)
            obs, _ = self.env.reset(seed=seed)
            self._episode = {"obs": [obs_to_arrays(obs, self.obs_mode)], "action": [],
                             "reward": [], "terminated": []}  # fmt: skip
            self._act_state = model.initial_state(heads, 1)
        ep = self._episode
        last = model_input(ep["obs"][-1:], self.device)
        with torch.no_grad(), self._autocast():
            if self.task_step < self.cfg.seed_steps:
                action = self.action_rng.uniform(-1.0, 1.0, model.cfg.action_dim)
                action = action.astype(np.float32)
                self._act_state = model.observe(last, action[None], heads, self._act_state)
            else:
                actions, self._act_state = model.act(last, heads, self._act_state,
                                                     eval_mode=False)  # fmt: skip
                action = np.asarray(actions[0], dtype=np.float32)
        obs, reward, terminated, truncated, _ = self.env.step(action)
        ep["obs"].append(obs_to_arrays(obs, self.obs_mode))
        ep["action"].append(action)
        ep["reward"].append(reward)
        ep["terminated"].append(bool(terminated))
        if terminated or truncated:
            self._cut_episode()

    def _cut_episode(self) -> None:
        """Store the episode in progress (as it stands) and start a fresh one next step."""
        ep, self._episode, self._act_state = self._episode, None, None
        if ep is None or not ep["action"]:
            return
        obs = {k: np.stack([o[k] for o in ep["obs"]]) for k in ep["obs"][0]}
        self.buffer.add_episode(
            obs, np.stack(ep["action"]), np.asarray(ep["reward"], np.float32),
            np.asarray(ep["terminated"], np.float32), task=self.task_index,
        )  # fmt: skip
        self.episode_index += 1
        self._train_logs["train/episode_return"].append(discounted_return(ep["reward"]))
        self._train_logs["train/episode_success"].append(float(ep["terminated"][-1]))

    def extra_updates(self, n: int) -> None:
        """`n` updates from replay with no environment steps."""
        for _ in range(n):
            self._update()

    def _update(self) -> None:
        mcfg = self.model.cfg
        batch = self.buffer.sample(mcfg.batch_size, mcfg.seq_len, self.cfg.demo_fraction)
        logs = self.step(batch.to(self.device))
        self.updates += 1
        # Logged values stay tensors until a flush: no host sync inside an update.
        for k, v in logs.items():
            self._train_logs[f"train/{k}"].append(v)

    def _flush_train_logs(self) -> None:
        keys = [k for k, v in self._train_logs.items() if v]
        if self.logger is not None and keys:
            means = torch.stack([
                torch.stack([torch.as_tensor(x, dtype=torch.float32, device=self.device)
                             .reshape(()) for x in self._train_logs[k]]).mean()
                for k in keys
            ]).tolist()  # fmt: skip
            self.logger.log_scalars(dict(zip(keys, means, strict=True)), self.global_step)
        self._train_logs.clear()

    def _evaluate(self, episodes: int | None = None) -> None:
        """Evaluate at this step: at a task's first step only the task itself (every earlier
        task was evaluated at this global step when the previous task ended), else every task
        the evaluator holds heads for; `episodes`: layouts per task (None: the run's)."""
        tasks = [self.task_index] if self.task_step == 0 else sorted(self.evaluator.heads)
        request = {"tasks": tasks, "stage": self.task_index, "global_step": self.global_step,
                   "task_step": self.task_step}  # fmt: skip
        self._submit(request if episodes is None else {**request, "episodes": episodes})
        self.last_eval = self.task_step

    def _submit(self, request: dict) -> None:
        submit_request(self.evaluator, request)

    def _collect(self, until: int | None = -1) -> int:
        """Log the evaluation records that are ready, in order; `until`: first wait for every
        request submitted before that global step (None: for all). Returns how many."""
        records = self.evaluator.results(until=until)
        for rec in records:
            self.evals.append(rec)
            if self.logger is not None:
                self.logger.log_eval(rec)
        return len(records)

    # ------------------------------------------------------------------------- checkpoints

    def _identity(self) -> dict:
        return {"train_config": _train_identity(dataclasses.asdict(self.cfg)),
                "seed": self.seed,
                "task_id": self.task_id, "global_offset": self.global_offset}  # fmt: skip

    def state_dict(self) -> dict:
        if self._episode is not None:
            raise RuntimeError("checkpoint with an episode in progress (cut it first)")
        state = {
            "kind": CHECKPOINT_KIND,
            "version": CHECKPOINT_VERSION,
            **self._identity(),
            "task_step": self.task_step,
            "updates": self.updates,
            "update_credit": self.update_credit,
            "episode_index": self.episode_index,
            "last_eval": self.last_eval,
            "last_checkpoint": self.last_checkpoint,
            "finished": self.finished,
            "evals": self.evals,
            "pending_evals": self.evaluator.pending,
            "model": self.model.state_dict(),
            "heads": self.heads.state_dict(),
            "step": self.step.state_dict(),
            "buffer": self.buffer.meta_state(),
            "replay_files": self._replay_files,
            "rng": rng_state(actions=self.action_rng),
        }
        if self.method is not None:
            state["method"] = self.method.state_dict()
        return state

    def load_checkpoint(self, path: str | Path) -> list[dict]:
        """Restore the checkpoint at `path`; returns the evaluation requests that were in
        flight when it was written (all at its step: earlier ones were waited for)."""
        state = load_checkpoint(path, CHECKPOINT_KIND, CHECKPOINT_VERSION)
        saved = {k: state[k] for k in self._identity()}  # as written, by whichever version
        saved["train_config"] = _train_identity(saved["train_config"])
        budget = saved["train_config"]["steps"]
        if self.extendable and budget < self.cfg.steps:
            saved["train_config"]["steps"] = self.cfg.steps
        if saved != self._identity():
            raise InputError(f"{path} was written by another run (config, seed or task "
                             "differ); use another run directory or delete it")  # fmt: skip
        self.model.load_state_dict(state["model"])
        self.heads.load_state_dict(state["heads"])
        self.step.load_state_dict(state["step"])
        load_rows(self.buffer, Path(path).parent, state["buffer"], state["replay_files"])
        self._replay_files = list(state["replay_files"])
        if "method" in state and self.method is not None:
            self.method.load_state_dict(state["method"])
        for key in ("task_step", "updates", "episode_index", "last_eval", "last_checkpoint"):
            setattr(self, key, int(state[key]))
        self.update_credit = float(state["update_credit"])
        self.finished = bool(state["finished"])
        self.evals = list(state["evals"])
        if self.finished and self.task_step == budget < self.cfg.steps:
            # Ran out of its budget, where the longer run goes on unless stop_score ends it.
            # The longer run evaluates at this step too; its stop test sees the ones before.
            self.finished = self._stop_reached(before=self.global_step)
        self._episode = None
        set_rng_state(state["rng"], actions=self.action_rng)
        return list(state["pending_evals"])


def _train_identity(train_config: dict) -> dict:
    """A checkpoint's training settings as far as they decide what it computes, as a run's
    config.json is judged (`config_base.identity`: without `train.parallel` and the other
    settings a resumed run may change, and those at their legacy values)."""
    return identity({"train": train_config})["train"]
