"""Algorithm 1: a suite's curriculum learnt continually, evaluated on every task seen so far.

For each task t in order: fresh heads; the continual method acts on the backbone only
(`before_task`, `penalty`, `after_step`, `after_task`, `evaluating`); the heads train normally
through the shared `Trainer`; after the task its heads are frozen and stored. At every
evaluation point (a fixed interval of global steps) the current task and every earlier task
(with its stored heads on the current backbone) are evaluated, so each earlier task has a curve
through the rest of the curriculum (the BWT integral needs it). The composition task is also
learnt from scratch with the same budget (the FWT reference), once per
(suite, model, obs, preset, seed, encoder) and shared by every method.

Run directory:
    config.json          the resolved CurriculumConfig and model / train configs
    metrics.jsonl        evaluation records: task, task_index, stage (task being trained),
                         global_step, task_step, discounted/normalised return, success rate
    tasks/<i>-<task>/    the trainer's checkpoint while task i trains (removed when it is done)
    curriculum.pt        state after the last finished task (model, stored heads, method, RNG)
    metrics.json         BWT, FWT and the standard metrics of this run
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import random
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ccdata.env import make_env
from ccdata.suites import get_suite
from ccfit import metrics as M
from ccfit.analysis import record_stage_routing
from ccfit.config import PRESETS, TrainConfig
from ccfit.continual import TaskData, make_method, method_names
from ccfit.obs import check_mode
from ccfit.replay import ReplayBuffer
from ccfit.train import (
    CHECKPOINT,
    CONFIG,
    METRICS,
    RunLogger,
    Trainer,
    atomic_torch_save,
    atomic_write_text,
    build_model,
    check_model,
    derived_seed,
    eval_seeds,
    evaluate,
    model_config,
    normalized_or_none,
    resolve_device,
    seed_buffer,
    seed_everything,
)

STATE = "curriculum.pt"
METRICS_JSON = "metrics.json"
_REPLAY_TAG = 3  # the trainer's replay seed stream
STATE_VERSION = 1


@dataclass
class CurriculumConfig:
    """One continual run: a suite's curriculum with one model, method, preset and seed."""

    suite: str
    """Suite name (`ccdata.SUITES`); its tasks are learnt in order, the composition last."""
    model: str = "tdmpc2"
    """World model (`ccfit.train.MODELS`)."""
    method: str = "ft"
    """Continual method: ft, er, ewc, packnet (experts for PWM)."""
    method_options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of the method (e.g. {'lam': 5000} for EWC, {'fraction': 0.05} for ER)."""
    preset: str = "cpu"
    """Size preset of model and training: smoke, cpu or paper."""
    obs: str = "state"
    """Observation mode: 'state' or 'pixels' (the paper)."""
    seed: int = 0
    """Seeds everything: model init, replay sampling, episode layouts, evaluation layouts."""
    image_size: int = 64
    """Camera image side in pixel mode."""
    encoder: str | None = None
    """'frozen:PATH': a pretrained encoder (ccfit pretrain-encoder), frozen for the run."""
    seed_dataset: str | None = "auto"
    """Each task's replay starts with that task's own episodes of this LeRobot dataset:
    'auto' = the suite's dataset `ccdata/<Suite>` when it exists locally, None = off,
    or a repo id / directory."""
    train_overrides: dict[str, Any] = field(default_factory=dict)
    """TrainConfig fields to override (e.g. {'steps': 5000}); steps = budget per task."""
    model_overrides: dict[str, Any] = field(default_factory=dict)
    """Model config fields to override."""

    def __post_init__(self) -> None:
        get_suite(self.suite)
        check_model(self.model)
        check_mode(self.obs)
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; valid: {', '.join(PRESETS)}")
        if self.method not in method_names():
            raise ValueError(
                f"unknown method {self.method!r}; valid: {', '.join(method_names())}"
            )
        if self.method == "experts" and self.model != "pwm":
            raise ValueError("method 'experts' (progressive experts) needs --model pwm")
        if self.encoder is not None:
            if not self.encoder.startswith("frozen:"):
                raise ValueError(f"--encoder must be 'frozen:PATH', got {self.encoder!r}")
            if self.obs != "pixels":
                raise ValueError("a frozen pretrained encoder needs --obs pixels")
            if not Path(self.encoder_path).is_file():
                raise ValueError(f"encoder checkpoint not found: {self.encoder_path}")
        # Bad method options fail here, before a run directory is written.
        make_method(self.method, num_tasks=len(self.tasks), **self.method_options)
        train = self.train_config()
        if train.steps % train.eval_interval:
            raise ValueError(
                f"steps per task ({train.steps}) must be a multiple of eval_interval "
                f"({train.eval_interval}) so every task is evaluated at its end"
            )

    @property
    def encoder_path(self) -> str | None:
        return self.encoder.split(":", 1)[1] if self.encoder else None

    @property
    def tasks(self) -> list[str]:
        return list(get_suite(self.suite).task_ids)

    def train_config(self) -> TrainConfig:
        overrides = {"obs": self.obs, "seed": self.seed, "image_size": self.image_size}
        return TrainConfig.preset(self.preset, **{**overrides, **self.train_overrides})

    def model_config(self):
        overrides = dict(self.model_overrides)
        if self.encoder_path is not None:
            from ccfit.models.encoders import load_frozen_encoder

            _, spec = load_frozen_encoder(self.encoder_path)
            size = spec.pop("image_size")
            if size != self.image_size:
                raise ValueError(
                    f"the encoder {self.encoder_path} reads {size} px images but "
                    f"the run renders {self.image_size} px (--image-size)"
                )
            spec.pop("obs_mode")  # 'pixels', checked in __post_init__
            overrides.update(spec)
        return model_config(
            self.model, self.preset, self.obs, image_size=self.image_size, **overrides
        )

    def dataset_source(self) -> str | None:
        if self.seed_dataset != "auto":
            return self.seed_dataset
        from ccdata.settings import suite_dataset_root

        root = suite_dataset_root(self.suite)
        return str(root) if (root / "meta" / "info.json").is_file() else None

    def to_dict(self) -> dict:
        return {
            **dataclasses.asdict(self),
            "resolved_seed_dataset": self.dataset_source(),
            "train": dataclasses.asdict(self.train_config()),
            "model_config": dataclasses.asdict(self.model_config()),
        }

    def scratch_key(self) -> str:
        """Runs that share this key share one from-scratch reference curve."""
        parts = [self.suite, self.model, self.obs, self.preset, f"s{self.seed}"]
        extra = {
            "encoder": self.encoder, "train": self.train_overrides, "model": self.model_overrides,
            "data": self.dataset_source(), "image_size": self.image_size,
        }  # fmt: skip
        digest = hashlib.sha1(json.dumps(extra, sort_keys=True).encode()).hexdigest()[:8]
        return "-".join(parts + [digest])


# ===================================================================== building blocks


def _build(cfg: CurriculumConfig, device: torch.device):
    encoder = None
    if cfg.encoder_path is not None:
        from ccfit.models.encoders import load_frozen_encoder

        encoder, _ = load_frozen_encoder(cfg.encoder_path, device=device)
    return build_model(cfg.model, cfg.model_config(), device, encoder=encoder)


def _begin_task(model, task_index: int, task_steps: int) -> None:
    """Models with per-task state (PWM: routing task, temperature hold) learn which task
    starts; new heads then belong to it."""
    if hasattr(model, "begin_task"):
        model.begin_task(task_index, task_steps)


def _global_rng() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
            "python": random.getstate()}  # fmt: skip


def _set_global_rng(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def _replay(cfg: CurriculumConfig, train: TrainConfig, task_id: str, task_index: int, fresh: bool,
            model) -> ReplayBuffer:  # fmt: skip
    buffer = ReplayBuffer(
        train.buffer_capacity, seed=derived_seed(cfg.seed, _REPLAY_TAG, 0, task_index),
        obs_transform=model.replay_obs,
    )
    source = cfg.dataset_source()
    if source is not None and fresh:
        # Only this task's own episodes: later tasks' data never leaks into earlier ones.
        seed_buffer(buffer, source, task_id, cfg.obs, cfg.image_size, task_index=task_index,
                    endpoint=train.dataset_endpoint)  # fmt: skip
    return buffer


def _task_data(task_index: int, buffer: ReplayBuffer, train: TrainConfig, horizon: int,
               model, device) -> TaskData:  # fmt: skip
    return TaskData(
        task_index=task_index,
        sample=lambda: buffer.sample(train.batch_size, horizon).to(device),
        num_transitions=buffer.num_starts(horizon),
        gather=lambda starts: buffer.gather(starts, horizon).to(device),
        backbone_loss=model.backbone_loss,
    )


# ============================================================================ the run


def run_scratch(cfg: CurriculumConfig, out: Path, progress: bool = True) -> list[dict]:
    """The composition task learnt from scratch with the curriculum's per-task budget.

    Shared by every method's run: concurrent runs (a sweep) take a file lock, so the first
    trains it and the others wait and read its records."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f".{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return _train_scratch(cfg, out, progress)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _train_scratch(cfg: CurriculumConfig, out: Path, progress: bool) -> list[dict]:
    train = cfg.train_config()
    n = len(cfg.tasks)
    task_id = cfg.tasks[-1]
    done = out / "done.json"
    if done.is_file():
        return json.loads(done.read_text())
    atomic_write_text(out / CONFIG, json.dumps(cfg.to_dict(), indent=2, sort_keys=True) + "\n")
    if train.torch_threads > 0:
        torch.set_num_threads(train.torch_threads)
    device = resolve_device(train.device)
    resumed = (out / CHECKPOINT).exists()
    if not resumed:  # records of a run killed before its first checkpoint
        (out / METRICS).unlink(missing_ok=True)
    seed_everything(cfg.seed)
    model = _build(cfg, device)
    _begin_task(model, n - 1, train.steps)
    env = make_env(task_id, render=cfg.obs == "pixels", image_size=cfg.image_size)
    trainer = Trainer(
        env=env, model=model, heads=model.new_heads(), config=train, task_id=task_id,
        buffer=_replay(cfg, train, task_id, n - 1, fresh=not resumed, model=model),
        task_index=n - 1, logger=RunLogger(out), run_dir=out, progress=progress,
    )  # fmt: skip
    trainer.run()
    env.close()
    evals = trainer.evals
    atomic_write_text(done, json.dumps(evals))
    (out / CHECKPOINT).unlink(missing_ok=True)
    return evals


class Curriculum:
    """Runs (or resumes) one continual run into `out`."""

    def __init__(self, cfg: CurriculumConfig, out: str | Path, scratch_root: str | Path | None,
                 progress: bool = True) -> None:  # fmt: skip
        self.cfg = cfg
        self.out = Path(out)
        self.scratch_root = Path(scratch_root) if scratch_root else self.out.parent / "scratch"
        self.progress = progress
        self.train = cfg.train_config()
        self.device = resolve_device(self.train.device)

    def _check_config(self) -> None:
        resolved = json.loads(json.dumps(self.cfg.to_dict()))
        saved = self.out / CONFIG
        if saved.exists() and json.loads(saved.read_text()) != resolved:
            raise ValueError(
                f"{self.out} holds a run with a different config; use another --out or delete it"
            )
        atomic_write_text(saved, json.dumps(resolved, indent=2, sort_keys=True) + "\n")

    def run(self) -> dict:
        cfg, train = self.cfg, self.train
        self.out.mkdir(parents=True, exist_ok=True)
        self._check_config()
        if train.torch_threads > 0:
            torch.set_num_threads(train.torch_threads)
        tasks = cfg.tasks
        seed_everything(cfg.seed)
        model = _build(cfg, self.device)
        method = make_method(cfg.method, num_tasks=len(tasks), **cfg.method_options)
        stored: list[torch.nn.Module] = []
        completed = 0
        logger = RunLogger(self.out)
        state_path = self.out / STATE
        if state_path.exists():
            completed = self._restore(state_path, model, method, stored)
        eval_envs: dict[int, Any] = {}

        def evaluate_earlier(global_step: int, stage: int) -> list[dict]:
            records = []
            for j in range(stage):
                if j not in eval_envs:
                    eval_envs[j] = make_env(tasks[j], render=cfg.obs == "pixels",
                                            image_size=cfg.image_size)  # fmt: skip
                with method.evaluating(j, model.backbone):
                    res = evaluate(
                        eval_envs[j], model, stored[j], obs_mode=cfg.obs, device=self.device,
                        seeds=eval_seeds(cfg.seed, j, train.eval_episodes),
                    )  # fmt: skip
                records.append({
                    "task": tasks[j], "task_index": j, "stage": stage,
                    "global_step": global_step, "task_step": None,
                    "discounted_return": res.discounted_return,
                    "normalized_return": normalized_or_none(tasks[j], res.discounted_return),
                    "success_rate": res.success_rate, "episodes": len(res.returns),
                })  # fmt: skip
            return records

        for i in range(completed, len(tasks)):
            task_dir = self.out / "tasks" / f"{i}-{tasks[i]}"
            resumed = (task_dir / CHECKPOINT).exists()
            if not resumed:
                _drop_records(logger, from_stage=i)
            _begin_task(model, i, train.steps)
            method.before_task(i, model.backbone)
            heads = model.new_heads()
            buffer = _replay(cfg, train, tasks[i], i, fresh=not resumed, model=model)
            env = make_env(tasks[i], render=cfg.obs == "pixels", image_size=cfg.image_size)
            trainer = Trainer(
                env=env, model=model, heads=heads, buffer=buffer, config=train,
                task_id=tasks[i], task_index=i, logger=logger, method=method, run_dir=task_dir,
                global_offset=i * train.steps, progress=self.progress,
                extra_eval=lambda step, stage=i: evaluate_earlier(step, stage),
            )  # fmt: skip
            trainer.run()
            env.close()
            method.after_task(
                i, model.backbone, _task_data(i, buffer, train, trainer.horizon, model, self.device)
            )
            if method.wants_retrain_steps:
                trainer.extra_updates(method.wants_retrain_steps)
            heads.requires_grad_(False)
            heads.eval()
            stored.append(heads)
            record_stage_routing(self.out, cfg, model, stored, method, self.device)  # PWM only
            self._save(state_path, i + 1, model, method, stored)
            shutil.rmtree(task_dir, ignore_errors=True)
        for env in eval_envs.values():
            env.close()
        logger.close()
        scratch_dir = (self.scratch_root / cfg.scratch_key()).resolve()
        scratch = run_scratch(cfg, scratch_dir, self.progress)
        result = compute_metrics(logger.read_evals(), scratch, len(tasks), train.steps)
        # Absolute: `ccfit report` may run from another working directory.
        result.update(suite=cfg.suite, model=cfg.model, method=cfg.method, seed=cfg.seed,
                      obs=cfg.obs, preset=cfg.preset, scratch_dir=str(scratch_dir))  # fmt: skip
        atomic_write_text(self.out / METRICS_JSON, json.dumps(result, indent=2) + "\n")
        return result

    def _save(self, path: Path, completed: int, model, method, stored) -> None:
        atomic_torch_save({
            "version": STATE_VERSION,
            "completed": completed,
            "model": model.state_dict(),
            "method": method.state_dict(),
            "heads": [h.state_dict() for h in stored],
            "rng": _global_rng(),
        }, path)  # fmt: skip

    def _restore(self, path: Path, model, method, stored: list) -> int:
        state = torch.load(path, map_location="cpu", weights_only=False)
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"{path}: unsupported curriculum state version")
        completed = int(state["completed"])
        # Model structure never changes shape (PWM allocates its experts up front), so the
        # states load directly; the next task's before_task continues from them.
        model.load_state_dict(state["model"])
        method.load_state_dict(state["method"])
        for heads_state in state["heads"]:
            heads = model.new_heads()
            heads.load_state_dict(heads_state)
            heads.requires_grad_(False)
            heads.eval()
            stored.append(heads)
        _set_global_rng(state["rng"])
        return completed


def _drop_records(logger: RunLogger, from_stage: int) -> None:
    """Forget evaluation records of stages a killed run had started but not checkpointed."""
    records = logger.read_evals()
    keep = [r for r in records if r.get("stage", r["task_index"]) < from_stage]
    if len(keep) != len(records):
        atomic_write_text(logger.jsonl, "".join(json.dumps(r, sort_keys=True) + "\n" for r in keep))


# ============================================================================ metrics


def task_curves(records: list[dict], num_tasks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per task (steps, normalised returns); of several records at one global step the last
    logged wins (a task's end record is superseded by the next stage's first evaluation,
    which sees e.g. PackNet's pruned and retrained weights)."""
    curves = []
    for t in range(num_tasks):
        by_step: dict[int, float] = {}
        for r in records:
            if r["task_index"] == t and r["normalized_return"] is not None:
                by_step[int(r["global_step"])] = float(r["normalized_return"])
        steps = np.array(sorted(by_step), dtype=np.float64)
        curves.append((steps, np.array([by_step[int(s)] for s in steps])))
    return curves


def compute_metrics(records: list[dict], scratch: list[dict], num_tasks: int,
                    steps_per_task: int) -> dict:  # fmt: skip
    """The paper's BWT and FWT plus Lopez-Paz BWT and Continual World metrics, one run."""
    curves = task_curves(records, num_tasks)
    if any(len(c[0]) == 0 for c in curves):
        raise ValueError("normalised returns missing: run `ccdata references` first")
    ends = [(i + 1) * steps_per_task for i in range(num_tasks)]
    scratch_curve = task_curves(scratch, num_tasks)[-1]
    return metrics_from_curves(curves, ends, scratch_curve, steps_per_task)


def metrics_from_curves(curves, ends, scratch_curve, budget: float) -> dict:
    n = len(curves)
    bwt = M.bwt(curves, ends)
    seq = M.rebase(curves[-1], ends[-1] - budget)
    matrix = M.performance_matrix(curves, ends)
    forgetting = M.cw_forgetting(curves, ends)
    return {
        "bwt": _finite(float(bwt)),
        "bwt_per_task": {str(i): _finite(d) for i, d in bwt.per_task.items()},
        "bwt_excluded": {str(i): why for i, why in bwt.excluded.items()},
        "fwt": _finite(M.fwt(seq, scratch_curve, budget)),
        "final_per_task": [_finite(x) for x in matrix[-1]],
        "end_of_task": [_finite(matrix[i, i]) for i in range(n)],
        "lopez_paz_bwt": _finite(M.lopez_paz_bwt(matrix)),
        "cw_forgetting": _finite(float(forgetting)),
        "cw_forward_transfer": _finite(M.cw_forward_transfer(seq, scratch_curve, budget)),
        "task_ends": list(ends),
        "budget": budget,
    }


def _finite(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None
