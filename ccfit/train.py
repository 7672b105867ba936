"""The shared online training loop (one loop for every world model and continual method).

`Trainer` is handed its collaborators (env, model, heads, replay buffer, config, logger,
optional continual method) and runs Algorithm 1's inner loop on one task: random actions for
the seed steps, then `updates_per_step` updates per env step, evaluation at a fixed interval,
atomic checkpoints, and resume.

Determinism: every episode's layout seed is derived from (seed, episode index), evaluation uses
a fixed set of layouts, and the checkpoint stores the RNG states of torch, numpy, Python and the
random-action generator. The training episode in progress is cut (stored as truncated) at every
evaluation and checkpoint step, so a checkpoint never holds a half-played episode and a resumed
run continues exactly as an uninterrupted one. Evaluation plays on the training env itself
(after that cut), so one process renders with one MuJoCo context.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import tempfile
from collections import defaultdict
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from ccdata.scoring import GAMMA, discounted_return, normalize
from ccfit.config import RunConfig, TrainConfig
from ccfit.data import seed_buffer  # noqa: F401 - moved to ccfit.data; old imports still work
from ccfit.models.base import WorldModel
from ccfit.obs import obs_to_arrays
from ccfit.replay import ReplayBuffer

CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.jsonl"
CONFIG = "config.json"
TENSORBOARD = "tb"
TRAIN_LOG_EVERY = 250
"""Env steps between TensorBoard points of the averaged training losses."""
_TRAIN_TAG, _EVAL_TAG, _ACTION_TAG, _REPLAY_TAG = 0, 1, 2, 3  # independent seed streams
CHECKPOINT_VERSION = 1


# ====================================================================== small utilities


def atomic_write_text(path: Path, text: str) -> None:
    """Write `text` to `path` via a temp file in the same directory and os.replace."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, 0o644)  # mkstemp files are private; outputs are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_torch_save(obj: Any, path: Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(obj, tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available; use 'cpu' or 'auto'")
    return torch.device(name)


def resolve_horizon(train: TrainConfig, model_config) -> int:
    """The subsequence length: TrainConfig.horizon, else the model config's `horizon`."""
    model_h = getattr(model_config, "horizon", None)
    if train.horizon is not None and model_h is not None and train.horizon != model_h:
        raise ValueError(
            f"TrainConfig.horizon={train.horizon} differs from the model's horizon={model_h}"
        )
    h = train.horizon if train.horizon is not None else model_h
    if h is None:
        raise ValueError("no horizon: set TrainConfig.horizon (the model config has none)")
    return int(h)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def derived_seed(seed: int, tag: int, index: int, task_index: int = 0) -> int:
    """A 31-bit seed for item `index` of stream `tag` (train / eval / ...) of a curriculum's
    task `task_index`, independent of every other (seed, tag, task, index)."""
    entropy = [seed, tag, task_index, index]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] >> 1)


def eval_seeds(seed: int, task_index: int, episodes: int) -> list[int]:
    """The fixed evaluation layouts of curriculum task `task_index` (the same at every eval)."""
    return [derived_seed(seed, _EVAL_TAG, j, task_index) for j in range(episodes)]


def _rng_state(action_rng: np.random.Generator) -> dict:
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
        "actions": action_rng.bit_generator.state,
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict, action_rng: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    action_rng.bit_generator.state = state["actions"]
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ============================================================================== logging


class RunLogger:
    """Evaluation records to JSONL (one line per evaluation) and scalars to TensorBoard."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = self.run_dir / METRICS
        self._tb_enabled = tensorboard
        self._tb = None

    def _writer(self, purge_step: int | None = None):
        if self._tb is None and self._tb_enabled:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.run_dir / TENSORBOARD), purge_step=purge_step)
        return self._tb

    def rewind(self, global_step: int) -> None:
        """Forget what was logged after `global_step` (a resumed run redoes those steps)."""
        if self.jsonl.exists():
            keep = [
                line
                for line in self.jsonl.read_text().splitlines()
                if line.strip() and json.loads(line)["global_step"] <= global_step
            ]
            atomic_write_text(self.jsonl, "".join(line + "\n" for line in keep))
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        self._writer(purge_step=global_step + 1)

    def log_eval(self, record: dict) -> None:
        with self.jsonl.open("a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")
        tag = record["task"]
        scalars = {
            f"eval/{tag}/discounted_return": record["discounted_return"],
            f"eval/{tag}/success_rate": record["success_rate"],
        }
        if record["normalized_return"] is not None:
            scalars[f"eval/{tag}/normalized_return"] = record["normalized_return"]
        self.log_scalars(scalars, record["global_step"])

    def log_scalars(self, scalars: dict[str, float], step: int) -> None:
        writer = self._writer()
        if writer is not None:
            for k, v in scalars.items():
                writer.add_scalar(k, v, step)

    def read_evals(self) -> list[dict]:
        if not self.jsonl.exists():
            return []
        return [json.loads(x) for x in self.jsonl.read_text().splitlines() if x.strip()]

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None


# =========================================================================== evaluation


@dataclass
class EvalResult:
    returns: list[float]
    """Discounted return (gamma = ccdata.scoring.GAMMA) of each episode."""
    successes: list[bool]
    lengths: list[int]

    @property
    def discounted_return(self) -> float:
        return float(np.mean(self.returns))

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes))


def normalized_or_none(task_id: str, ret: float) -> float | None:
    """Normalised return, or None when the oracle reference is not available yet."""
    try:
        return float(normalize(task_id, ret))
    except ValueError:
        return None


def _to_device(obs: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device) for k, v in obs.items()}


@torch.no_grad()
def evaluate(
    env,
    model: WorldModel,
    heads: nn.Module,
    *,
    obs_mode: str,
    seeds: list[int],
    device: torch.device,
) -> EvalResult:
    """Play one episode per layout seed with `eval_mode=True`."""
    returns, successes, lengths = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        rewards, success, t = [], False, 0
        done = False
        while not done:
            x = {k: torch.from_numpy(v) for k, v in obs_to_arrays(obs, obs_mode).items()}
            action = model.act(_to_device(x, device), heads, t0=t == 0, eval_mode=True)
            obs, reward, terminated, truncated, info = env.step(np.asarray(action, np.float32))
            rewards.append(reward)
            success = success or bool(info["success"])
            done = terminated or truncated
            t += 1
        returns.append(discounted_return(rewards, GAMMA))
        successes.append(success)
        lengths.append(t)
    return EvalResult(returns, successes, lengths)


# ============================================================================== trainer


class ContinualMethod(Protocol):
    """What the loop calls on a continual method: `penalty` is added to every update's loss,
    `after_step` runs after every optimiser step; `state_dict` / `load_state_dict`, when the
    method has them, go into and come back from the checkpoint."""

    def penalty(self, backbone: nn.Module, backbone_loss) -> torch.Tensor: ...

    def after_step(self, backbone: nn.Module) -> None: ...


class Trainer:
    """Online model-based RL on one task; `run()` trains (resuming if a checkpoint exists).

    env: the task's env (its obs must carry what `config.obs` needs; pixels need rendering).
    model, heads: a `WorldModel` and this task's heads; `model.cfg` must give `lr`,
        `grad_clip_norm` and (unless `config.horizon` is set) `horizon`.
    buffer: replay, possibly preloaded; episodes are added as `task_index`.
    logger: evaluation records and scalars (None: keep them in `self.evals` only).
    method: optional continual method (see `ContinualMethod`).
    run_dir: where `checkpoint.pt` goes (None: no checkpoints, no resume).
    global_offset: global step at which this task starts in a curriculum.
    extra_eval: called at every evaluation point with the global step; returns more records
        to log beside this task's (a curriculum evaluates the earlier tasks there).
    """

    def __init__(
        self,
        *,
        env,
        model: WorldModel,
        heads: nn.Module,
        buffer: ReplayBuffer,
        config: TrainConfig,
        task_id: str,
        task_index: int = 0,
        logger: RunLogger | None = None,
        method: ContinualMethod | None = None,
        run_dir: str | Path | None = None,
        global_offset: int = 0,
        progress: bool = True,
        extra_eval: Callable[[int], list[dict]] | None = None,
    ) -> None:
        self.env = env
        self.model = model
        self.heads = heads
        self.buffer = buffer
        self.cfg = config
        self.task_id = task_id
        self.task_index = task_index
        self.logger = logger
        self.method = method
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.global_offset = global_offset
        self.progress = progress
        self.extra_eval = extra_eval
        self.device = next(model.parameters()).device

        # Optimisation hyperparameters belong to the model (its recipe): lr, grad_clip_norm.
        mcfg = model.cfg
        self.horizon = resolve_horizon(config, mcfg)
        self.grad_clip = float(mcfg.grad_clip_norm)
        self.optim = torch.optim.Adam(model.param_groups(heads), lr=mcfg.lr)
        self._clip_params = [p for g in self.optim.param_groups for p in g["params"]]
        if hasattr(model, "make_policy_optimizer"):
            self.policy_optim = model.make_policy_optimizer(heads)
        else:
            self.policy_optim = torch.optim.Adam(model.policy_parameters(heads), lr=mcfg.lr)
        self.action_rng = np.random.default_rng(
            derived_seed(config.seed, _ACTION_TAG, 0, task_index)
        )

        self.task_step = 0
        self.updates = 0
        self.episode_index = 0
        self.last_eval = -1
        self.last_checkpoint = -1
        self.evals: list[dict] = []
        self._episode: dict | None = None
        self._train_logs: dict[str, list[float]] = defaultdict(list)

    @property
    def global_step(self) -> int:
        return self.global_offset + self.task_step

    # -------------------------------------------------------------------------- main loop

    def run(self) -> dict:
        """Train to `config.steps` task steps; returns the last evaluation record."""
        from tqdm.auto import tqdm

        cfg = self.cfg
        if self.run_dir is not None and (self.run_dir / CHECKPOINT).exists():
            self.load_checkpoint(self.run_dir / CHECKPOINT)
            if self.logger is not None:
                self.logger.rewind(self.global_step)
        bar = tqdm(
            total=cfg.steps,
            initial=self.task_step,
            desc=self.task_id,
            unit="step",
            disable=not self.progress,
            dynamic_ncols=True,
            mininterval=1.0,
        )
        try:
            while True:
                at_end = self.task_step >= cfg.steps
                if (self.task_step % cfg.eval_interval == 0 or at_end) and (
                    self.last_eval != self.task_step
                ):
                    self._cut_episode()
                    rec = self._evaluate()
                    bar.set_postfix(ret=f"{rec['discounted_return']:.1f}",
                                    succ=f"{rec['success_rate']:.2f}")  # fmt: skip
                if (
                    (self.task_step % cfg.checkpoint_interval == 0 and self.task_step > 0) or at_end
                ) and self.last_checkpoint != self.task_step:
                    self._cut_episode()
                    self.last_checkpoint = self.task_step
                    if self.run_dir is not None:
                        self.save_checkpoint(self.run_dir / CHECKPOINT)
                if at_end:
                    break
                self._env_step()
                if self.task_step >= cfg.seed_steps and self.buffer.can_sample(self.horizon):
                    for _ in range(cfg.updates_per_step):
                        self._update()
                self.task_step += 1
                bar.update(1)
                if self.task_step % TRAIN_LOG_EVERY == 0:
                    self._flush_train_logs()
        finally:
            bar.close()
        return self.evals[-1]

    def _env_step(self) -> None:
        if self._episode is None:
            seed = derived_seed(self.cfg.seed, _TRAIN_TAG, self.episode_index, self.task_index)
            obs, _ = self.env.reset(seed=seed)
            self._episode = {"obs": [obs_to_arrays(obs, self.cfg.obs)], "action": [],
                             "reward": [], "terminated": []}  # fmt: skip
        ep = self._episode
        if self.task_step < self.cfg.seed_steps:
            action = self.action_rng.uniform(-1.0, 1.0, 4).astype(np.float32)
        else:
            last = {k: torch.from_numpy(v) for k, v in ep["obs"][-1].items()}
            with torch.no_grad():
                action = self.model.act(
                    _to_device(last, self.device), self.heads,
                    t0=len(ep["action"]) == 0, eval_mode=False,
                )  # fmt: skip
            action = np.asarray(action, dtype=np.float32)
        obs, reward, terminated, truncated, _ = self.env.step(action)
        ep["obs"].append(obs_to_arrays(obs, self.cfg.obs))
        ep["action"].append(action)
        ep["reward"].append(reward)
        ep["terminated"].append(bool(terminated))
        if terminated or truncated:
            self._cut_episode()

    def _cut_episode(self) -> None:
        """Store the episode in progress (as it stands) and start a fresh one next step."""
        ep, self._episode = self._episode, None
        if ep is None or not ep["action"]:
            return
        obs = {k: np.stack([o[k] for o in ep["obs"]]) for k in ep["obs"][0]}
        self.buffer.add_episode(
            obs,
            np.stack(ep["action"]),
            np.asarray(ep["reward"], np.float32),
            np.asarray(ep["terminated"], np.float32),
            task=self.task_index,
        )
        self.episode_index += 1
        self._train_logs["train/episode_return"].append(discounted_return(ep["reward"]))
        self._train_logs["train/episode_success"].append(float(ep["terminated"][-1]))

    def extra_updates(self, n: int) -> None:
        """`n` updates from replay with no environment steps (e.g. PackNet's retraining)."""
        for _ in range(n):
            self._update()

    def _update(self) -> None:
        batch = self.buffer.sample(self.cfg.batch_size, self.horizon).to(self.device)
        self.model.train()
        out = self.model.loss(batch, self.heads)
        total = out.total
        if self.method is not None:
            total = total + self.method.penalty(self.model.backbone, self.model.backbone_loss)
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self._clip_params, self.grad_clip)
        self.optim.step()
        if self.method is not None:
            self.method.after_step(self.model.backbone)
        head_logs = self.model.head_update(batch, self.heads, out, self.policy_optim)
        self.updates += 1
        logs = {**out.logs, **head_logs, "total": float(total.detach()),
                "grad_norm": float(grad_norm)}  # fmt: skip
        for k, v in logs.items():
            self._train_logs[f"train/{k}"].append(float(v))

    def _flush_train_logs(self) -> None:
        if self.logger is not None and self._train_logs:
            means = {k: float(np.mean(v)) for k, v in self._train_logs.items() if v}
            self.logger.log_scalars(means, self.global_step)
        self._train_logs.clear()

    def _evaluate(self) -> dict:
        self.model.eval()
        seeds = eval_seeds(self.cfg.seed, self.task_index, self.cfg.eval_episodes)
        evaluating = getattr(self.method, "evaluating", None)
        view = evaluating(self.task_index, self.model.backbone) if evaluating else nullcontext()
        with view:
            res = evaluate(
                self.env, self.model, self.heads, obs_mode=self.cfg.obs, seeds=seeds,
                device=self.device,
            )  # fmt: skip
        ret = res.discounted_return
        record = {
            "task": self.task_id,
            "task_index": self.task_index,
            "stage": self.task_index,
            "global_step": self.global_step,
            "task_step": self.task_step,
            "discounted_return": ret,
            "normalized_return": normalized_or_none(self.task_id, ret),
            "success_rate": res.success_rate,
            "episodes": len(seeds),
        }
        self.last_eval = self.task_step
        others = self.extra_eval(self.global_step) if self.extra_eval is not None else []
        for rec in [record, *others]:
            self.evals.append(rec)
            if self.logger is not None:
                self.logger.log_eval(rec)
        self.model.train()
        return record

    # ------------------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict:
        if self._episode is not None:
            raise RuntimeError("checkpoint with an episode in progress (cut it first)")
        state = {
            "version": CHECKPOINT_VERSION,
            "train_config": dataclasses.asdict(self.cfg),
            "task_id": self.task_id,
            "task_index": self.task_index,
            "global_offset": self.global_offset,
            "task_step": self.task_step,
            "updates": self.updates,
            "episode_index": self.episode_index,
            "last_eval": self.last_eval,
            "last_checkpoint": self.last_checkpoint,
            "evals": self.evals,
            "model": self.model.state_dict(),
            "heads": self.heads.state_dict(),
            "optim": self.optim.state_dict(),
            "policy_optim": self.policy_optim.state_dict(),
            "buffer": self.buffer.state_dict(),
            "rng": _rng_state(self.action_rng),
        }
        if self.method is not None and hasattr(self.method, "state_dict"):
            state["method"] = self.method.state_dict()
        return state

    def save_checkpoint(self, path: str | Path) -> None:
        atomic_torch_save(self.state_dict(), Path(path))

    def load_checkpoint(self, path: str | Path) -> None:
        # Our own file: it holds numpy RNG tuples and Python objects, so not weights_only.
        state = torch.load(path, map_location="cpu", weights_only=False)
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: unsupported checkpoint version {state.get('version')}")
        if state["train_config"] != dataclasses.asdict(self.cfg):
            raise ValueError(f"{path} was written with a different training config")
        if (state["task_id"], state["global_offset"]) != (self.task_id, self.global_offset):
            raise ValueError(f"{path} belongs to task {state['task_id']!r}, not {self.task_id!r}")
        self.model.load_state_dict(state["model"])
        self.heads.load_state_dict(state["heads"])
        self.optim.load_state_dict(state["optim"])
        self.policy_optim.load_state_dict(state["policy_optim"])
        self.buffer.load_state_dict(state["buffer"])
        if "method" in state and self.method is not None:
            self.method.load_state_dict(state["method"])
        self.task_step = int(state["task_step"])
        self.updates = int(state["updates"])
        self.episode_index = int(state["episode_index"])
        self.last_eval = int(state["last_eval"])
        self.last_checkpoint = int(state["last_checkpoint"])
        self.evals = list(state["evals"])
        self._episode = None
        _set_rng_state(state["rng"], self.action_rng)


# ======================================================================= one run, built


MODELS: tuple[str, ...] = ("tdmpc2", "pwm")
"""World models `train_task` can build."""


def check_model(name: str) -> str:
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; valid: {', '.join(MODELS)}")
    return name


def model_config(name: str, preset: str, obs_mode: str, image_size: int = 64, **overrides):
    """The named model's config at `preset` for this observation mode."""
    check_model(name)
    if name == "pwm":
        from ccfit.config import pwm_preset

        return pwm_preset(preset, obs_mode, image_size=image_size, **overrides)
    from ccfit.config import tdmpc2_preset

    return tdmpc2_preset(preset, obs_mode, image_size=image_size, **overrides)


def build_model(name: str, config, device: torch.device, encoder=None) -> WorldModel:
    """`encoder`: a frozen pretrained encoder (`load_frozen_encoder`) to use instead of a
    trainable one."""
    check_model(name)
    if name == "pwm":
        from ccfit.models.pwm import build_pwm

        return build_pwm(config, device, encoder)
    from ccfit.models.tdmpc2 import TDMPC2

    return TDMPC2(config, device=device, encoder=encoder)


def train_task(
    run: RunConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
) -> dict:
    """Train `run.model` on `run.task` from scratch into `out_dir`, resuming if it holds a
    checkpoint of the same config. Returns the last evaluation record."""
    from ccdata.env import make_env

    out = Path(out_dir)
    cfg = run.train
    resolved = run.to_dict()
    saved = out / CONFIG
    if saved.exists() and json.loads(saved.read_text()) != json.loads(json.dumps(resolved)):
        raise ValueError(
            f"{out} holds a run with a different config; use another --out or delete it"
        )
    if cfg.torch_threads > 0:
        torch.set_num_threads(cfg.torch_threads)
    device = resolve_device(cfg.device)
    seed_everything(cfg.seed)
    model = build_model(run.model, run.model_config, device)
    buffer = ReplayBuffer(cfg.buffer_capacity, seed=derived_seed(cfg.seed, _REPLAY_TAG, 0),
                          obs_transform=model.replay_obs)  # fmt: skip
    if cfg.seed_dataset is not None and not (out / CHECKPOINT).exists():
        # Before anything is written: a bad dataset leaves no half-made run directory.
        seed_buffer(buffer, cfg.seed_dataset, run.task, cfg.obs, cfg.image_size,
                    endpoint=cfg.dataset_endpoint)  # fmt: skip
    if not saved.exists():
        run.save(saved)
    env = make_env(run.task, render=cfg.obs == "pixels", image_size=cfg.image_size)
    if hasattr(model, "begin_task"):  # PWM: routing task and temperature hold
        model.begin_task(0, cfg.steps)
    heads = model.new_heads()
    logger = RunLogger(out)
    trainer = Trainer(
        env=env, model=model, heads=heads, buffer=buffer, config=cfg, task_id=run.task,
        logger=logger, run_dir=out, progress=progress,
    )  # fmt: skip
    try:
        return trainer.run()
    finally:
        logger.close()
        env.close()
