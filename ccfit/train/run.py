"""Building a run's collaborators from its config, and one task trained from scratch.

The curriculum (Algorithm 1) and `ccfit train` build model, replay and env the same way:
`build_model`, `make_replay` and `dataset_source` are that one way.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ccfit.config import RunConfig, TaskRunConfig, flatten
from ccfit.data import seed_buffer
from ccfit.io import derived_seed, seed_everything
from ccfit.models.base import WorldModel
from ccfit.models.registry import ConfigError, make_model
from ccfit.replay import ReplayBuffer
from ccfit.train.evaluate import REPLAY_TAG
from ccfit.train.loop import CHECKPOINT, Trainer
from ccfit.train.records import RunLogger

CONFIG = "config.json"


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but CUDA is not available; use 'cpu' or 'auto'")
    return torch.device(name)


def build_model(cfg: RunConfig, device: torch.device) -> WorldModel:
    """The run's world model, with its frozen pretrained encoder when `cfg.encoder` names one."""
    encoder = None
    if cfg.encoder_path is not None:
        from ccfit.models.encoders import load_frozen_encoder

        encoder, _ = load_frozen_encoder(cfg.encoder_path, device=device)
    return make_model(cfg.model, device, encoder=encoder)


def suite_of(task_id: str) -> str | None:
    """The first suite holding `task_id` (whose dataset seeds a single-task run)."""
    from ccdata import SUITES

    return next((s.name for s in SUITES.values() if task_id in s.task_ids), None)


def dataset_source(cfg: RunConfig, suite: str | None) -> str | None:
    """The seed dataset: `cfg.seed_dataset`, or for 'auto' the suite's local dataset if any."""
    if cfg.seed_dataset != "auto":
        return cfg.seed_dataset
    if suite is None:
        return None
    from ccdata.settings import suite_dataset_root

    root = suite_dataset_root(suite)
    return str(root) if (root / "meta" / "info.json").is_file() else None


def make_replay(cfg: RunConfig, model: WorldModel, task_id: str, task_index: int,
                source: str | None) -> ReplayBuffer:  # fmt: skip
    """Task `task_index`'s replay, preloaded with that task's own episodes of `source` (later
    tasks' data never leaks into earlier ones)."""
    buffer = ReplayBuffer(cfg.train.buffer_capacity,
                          seed=derived_seed(cfg.seed, REPLAY_TAG, 0, task_index),
                          obs_transform=model.replay_obs)  # fmt: skip
    if source is not None:
        seed_buffer(buffer, source, task_id, cfg.obs, cfg.image_size, task_index=task_index,
                    endpoint=cfg.dataset_endpoint)  # fmt: skip
    return buffer


def check_saved_config(out: Path, resolved: dict) -> None:
    """A run directory belongs to one config: refuse another one, write it if new."""
    from ccfit.io import atomic_write_json

    saved = out / CONFIG
    if saved.exists():
        old, new = json.loads(saved.read_text()), json.loads(json.dumps(resolved))
        if old != new:
            a, b = flatten(old), flatten(new)
            differ = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
            raise ConfigError(f"{out} holds a run with a different config (differs in "
                              f"{', '.join(differ) or 'empty option groups'}); use another "
                              "--out or delete it")  # fmt: skip
        return
    atomic_write_json(saved, resolved)


def default_out(cfg: TaskRunConfig) -> Path:
    return Path("runs") / f"{cfg.task}-{cfg.model.type}-{cfg.obs}-{cfg.preset}-s{cfg.seed}"


def train_task(cfg: TaskRunConfig, *, progress: bool = True) -> dict:
    """Train `cfg.model` on `cfg.task` from scratch into `cfg.out`, resuming if it holds a
    checkpoint of the same config. Returns the last evaluation record."""
    from ccdata.env import make_env

    out = Path(cfg.out) if cfg.out else default_out(cfg)
    source = dataset_source(cfg, suite_of(cfg.task))
    resolved = {**cfg.to_dict(), "resolved_seed_dataset": source}
    if (out / CONFIG).exists():
        check_saved_config(out, resolved)
    if cfg.train.torch_threads > 0:
        torch.set_num_threads(cfg.train.torch_threads)
    device = resolve_device(cfg.train.device)
    seed_everything(cfg.seed)
    model = build_model(cfg, device)
    resumed = (out / CHECKPOINT).exists()
    # Seed data is read before anything is written: a bad dataset leaves no run directory.
    buffer = make_replay(cfg, model, cfg.task, 0, None if resumed else source)
    check_saved_config(out, resolved)
    env = make_env(cfg.task, render=cfg.obs == "pixels", image_size=cfg.image_size)
    model.begin_task(0, cfg.train.steps)
    heads = model.new_heads()
    logger = RunLogger(out)
    trainer = Trainer(
        env=env, model=model, heads=heads, buffer=buffer, config=cfg.train, seed=cfg.seed,
        obs_mode=cfg.obs, task_id=cfg.task, logger=logger, run_dir=out, progress=progress,
    )  # fmt: skip
    try:
        return trainer.run()
    finally:
        logger.close()
        env.close()
