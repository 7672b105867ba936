"""Building a run's collaborators from its config, and one task trained from scratch.

The curriculum (Algorithm 1), `ccfit train` and a curriculum's from-scratch reference build
model, replay, env and evaluator the same way: `build_model`, `make_replay`,
`resolved_config` and `train_task` are that one way.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from ccdata.errors import InputError
from ccdata.render import RenderSettings
from ccfit.config import BaseRunConfig, RunConfig, TaskRunConfig, with_encoder
from ccfit.config_base import (
    COMPILE_REASON,
    DATASET_RECORDS,
    ENCODER_RECORD,
    ConfigError,
    identity,
)
from ccfit.config_parse import flatten
from ccfit.data import dataset_meta
from ccfit.io import atomic_write_json, derived_seed, seed_everything
from ccfit.models.base import WorldModel
from ccfit.models.registry import make_model, model_class
from ccfit.replay import ReplayBuffer
from ccfit.replay_prefill import DEMO_POLICY, demonstration_rows, seed_buffer
from ccfit.run_files import CONFIG, task_run_name
from ccfit.settings import Execution, resolve_execution
from ccfit.train.compiled import compile_choice, compile_hot_paths, compiled_paths
from ccfit.train.cost import RunCost
from ccfit.train.env_workers import resolve_env_workers
from ccfit.train.eval_worker import AsyncEvaluator, WorkerSpec, has_view, parallel_on
from ccfit.train.evaluate import REPLAY_TAG, Evaluator
from ccfit.train.loop import CHECKPOINT, Trainer
from ccfit.train.records import RunLogger
from ccfit.train.resources import ReplayPlan, check_disk, plan_replay


def render_settings(cfg: BaseRunConfig) -> RenderSettings:
    """How the run's camera images are rendered (ccdata's defaults at the run's size)."""
    return RenderSettings(image_size=cfg.image_size)


def resolved_config(cfg: RunConfig, suite: str | None, execution: Execution | None = None, *,
                    record_dataset: bool = True) -> dict:  # fmt: skip
    """config.json of a run: the config, plus what it resolved to where it runs: the seed
    dataset ('auto') and what it holds, how it executes (`execution`, the run's: its device
    and precision; None: resolved here from `cfg.train`), the compiled methods and the render
    settings. `record_dataset=False` leaves out what the dataset holds (None): it is no part
    of the identity, and reading it may download a Hub dataset."""
    execution = execution or resolve_execution(cfg.train)
    device, ran = execution.device, execution.records()
    source = dataset_source(cfg, suite)
    if cfg.train.demo_fraction > 0 and source is None:
        raise ConfigError(f"train.demo_fraction {cfg.train.demo_fraction} (given, or the "
                          f"model's budget for the suite) needs the seed dataset's "
                          f"demonstrations, but --seed_dataset auto found no local dataset of "
                          f"suite {suite} (`ccdata generate --suite {suite}`, name one, or "
                          f"--train.demo_fraction=0)")  # fmt: skip
    meta = dataset_meta(source, cfg.dataset_endpoint) if source and record_dataset else None
    compiled, why = compile_choice(model_class(cfg.model.type), cfg.train.compile, device,
                                   cfg.train.steps)  # fmt: skip
    return {
        **cfg.to_dict(),
        "resolved_seed_dataset": source,
        "resolved_seed_dataset_meta": meta,
        "resolved_device": ran["resolved_device"],
        "resolved_compile": compiled,
        COMPILE_REASON: why,
        "resolved_autocast": ran["resolved_autocast"],
        "render": render_settings(cfg).to_dict(),
        **encoder_record(cfg),
    }


def encoder_record(cfg: BaseRunConfig) -> dict:
    """What config.json records of a frozen encoder: its file's SHA-256 (`ENCODER_RECORD`);
    nothing without one."""
    if cfg.encoder_path is None:
        return {}
    from ccfit.models.encoders import weights_sha256

    return {ENCODER_RECORD: weights_sha256(cfg.encoder_path)}


def build_model(cfg: RunConfig, device: torch.device, compiled: list[str] | None = None
                ) -> WorldModel:  # fmt: skip
    """The run's world model (`load_model`), its hot paths `compiled` (None: those
    `cfg.train.compile` chooses for the run, `compile_choice`) compiled."""
    model = load_model(cfg, device)
    if compiled is None:
        compiled = compiled_paths(type(model), cfg.train.compile, device, cfg.train.steps)
    compile_hot_paths(model, cfg.train.compile, paths=compiled)
    return model


def compile_as_begun(out: Path, resolved: dict) -> dict:
    """`resolved` (a run's config.json) with the compile choice that the run in `out` began
    with, where both chose with `auto`: a run extended (`ccfit train --train.steps`) or resumed
    under code whose rule chooses otherwise goes on compiling what it compiled."""
    saved = out / CONFIG
    if not saved.is_file() or resolved["train"]["compile"] != "auto":
        return resolved
    old = json.loads(saved.read_text())
    if old.get("train", {}).get("compile") != "auto" or "resolved_compile" not in old:
        return resolved
    if old["resolved_compile"] == resolved["resolved_compile"]:
        return resolved
    reason = old.get(COMPILE_REASON, "auto: as chosen when the run began")
    return {**resolved, "resolved_compile": old["resolved_compile"], COMPILE_REASON: reason}


def load_model(cfg: BaseRunConfig, device: torch.device) -> WorldModel:
    """The run's world model, eager, with its frozen pretrained encoder when `cfg.encoder`
    names one."""
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


def note_no_seed_dataset(cfg: RunConfig, suite: str | None, source: str | None) -> None:
    """Say in one line, at a run's start, that `--seed_dataset auto` found no dataset: the
    run then starts from an empty replay, which changes what it computes."""
    if cfg.seed_dataset == "auto" and source is None and suite is not None:
        from ccdata.settings import suite_dataset_root

        print(f"ccfit: note: --seed_dataset auto found no {suite} dataset at "
              f"{suite_dataset_root(suite)} (`ccdata generate --suite {suite}` makes it): replay "
              "starts empty", file=sys.stderr)  # fmt: skip


def check_seed_dataset_as_run(cfg: RunConfig, suite: str | None, saved: dict,
                              path: Path) -> None:  # fmt: skip
    """InputError unless a run made again from the config.json at `path` (read as `saved`)
    seeds from the dataset it was run with: where that run's `--seed_dataset auto` found one,
    the same one is found here, with the same content where the file records it (frames for
    a state run, frames and videos for a pixel run). A rerun without it would part from the
    recorded run at its first update, with no word why."""
    if cfg.seed_dataset != "auto" or saved.get("seed_dataset") != "auto" or suite is None:
        return
    had = saved.get("resolved_seed_dataset")
    if had is None:
        return
    make = (f"make it with `ccdata generate --suite {suite}` and the settings recorded in "
            f"{path} (resolved_seed_dataset_meta.generated_with), or pass --seed_dataset null "
            "to run without it")  # fmt: skip
    source = dataset_source(cfg, suite)
    if source is None:
        raise InputError(f"{path} was run seeded from the {suite} dataset, which is not here "
                         f"(it was at {had}): {make}")  # fmt: skip
    recorded = (saved.get("resolved_seed_dataset_meta") or {}).get("content_sha256")
    if not recorded:
        return
    parts = ("data",) if cfg.obs == "state" else ("data", "videos")
    found = dataset_meta(source, cfg.dataset_endpoint)["content_sha256"]
    differ = [part for part in parts if found.get(part) != recorded.get(part)]
    if differ:
        raise InputError(f"the {suite} dataset at {source} is not the one {path} was run with "
                         f"(its {' and '.join(differ)} differ): {make}")  # fmt: skip


def plan_run_replay(cfg: RunConfig, model: WorldModel, task_ids: list[str],
                    source: str | None) -> ReplayPlan:  # fmt: skip
    """`plan_replay` for a run over `task_ids` seeded from `source`, counting the
    demonstrations its buffers keep when `--train.demo_fraction` is on."""
    demos = cfg.train.demo_fraction > 0 and source is not None
    rows = demonstration_rows(source, task_ids, cfg.dataset_endpoint) if demos else 0
    return plan_replay(cfg, model, rows)


def make_replay(cfg: RunConfig, model: WorldModel, task_id: str, task_index: int,
                source: str | None, plan: ReplayPlan | None = None) -> ReplayBuffer:  # fmt: skip
    """Task `task_index`'s replay, preloaded with that task's own episodes of `source` (later
    tasks' data never leaks into earlier ones), stored where `plan` says (None: the CPU)."""
    buffer = ReplayBuffer(cfg.train.buffer_capacity,
                          seed=derived_seed(cfg.seed, REPLAY_TAG, 0, task_index),
                          obs_transform=model.replay_obs,
                          storage=plan.storage if plan else "cpu")  # fmt: skip
    if source is not None:
        added = seed_buffer(buffer, source, task_id, cfg.obs, render_settings(cfg),
                            task_index=task_index, endpoint=cfg.dataset_endpoint,
                            demos=cfg.train.demo_fraction > 0)  # fmt: skip
        if cfg.train.demo_fraction > 0 and not added.get(DEMO_POLICY):
            raise InputError(
                f"{source} holds no {DEMO_POLICY} episode of {task_id}: "
                "train.demo_fraction has no demonstrations to oversample"
            )
        seq_len = model.cfg.seq_len
        if cfg.train.demo_fraction > 0 and buffer.num_demo_starts(seq_len) == 0:
            rows = sum(end - first for first, end in buffer.demo_spans)
            raise InputError(
                f"the {DEMO_POLICY} episodes of {task_id} in {source} hold {rows} rows, fewer "
                f"than a training window of {seq_len} (model.seq_len): train.demo_fraction "
                "has no window to oversample; generate more episodes or set it to 0"
            )
    return buffer


def make_evaluator(cfg: RunConfig, model: WorldModel, task_ids: dict[int, str],
                   method=None, compiled: list[str] | None = None,
                   execution: Execution | None = None) -> Evaluator | AsyncEvaluator:  # fmt: skip
    """The run's evaluator: in this process, or in a worker beside training
    (`--train.parallel`); `method`: the continual method, whose view tasks are evaluated in;
    `compiled`: the hot paths the run compiles (None: `build_model`'s choice), which a
    worker compiles too; `execution`: the run's (None: resolved from `cfg.train`)."""
    execution = execution or resolve_execution(cfg.train)
    parallel = parallel_on(cfg.train.parallel)
    env_workers = resolve_env_workers(cfg.train.env_workers, obs_mode=cfg.obs, parallel=parallel,
                                      episodes=cfg.train.eval_episodes)  # fmt: skip
    if parallel:
        spec = WorkerSpec(
            model=cfg.model, encoder_path=cfg.encoder_path, execution=execution,
            compiled=compiled if compiled is not None else compiled_paths(
                type(model), cfg.train.compile, model.device, cfg.train.steps),
            method=cfg.method if has_view(method) else None,
            num_tasks=len(getattr(cfg, "tasks", task_ids)), task_ids=task_ids, seed=cfg.seed,
            obs_mode=cfg.obs, image_size=cfg.image_size, episodes=cfg.train.eval_episodes,
            episode_steps=cfg.train.episode_steps, env_workers=env_workers,
        )  # fmt: skip
        return AsyncEvaluator(spec, model, method)
    view = (lambda i: method.evaluating(i, model.backbone)) if method is not None else None
    return Evaluator(model, task_ids, seed=cfg.seed, obs_mode=cfg.obs,
                     image_size=cfg.image_size, episodes=cfg.train.eval_episodes,
                     episode_steps=cfg.train.episode_steps, view=view,
                     autocast=execution.autocast,
                     env_workers=env_workers)  # fmt: skip


EXTENDABLE = "train.steps"
"""The one setting a finished single-task run may raise on resume (`check_saved_config`), from
a multiple of `train.eval_interval`."""


def check_saved_config(out: Path, resolved: dict, *, extends: type[WorldModel] | None = None
                       ) -> None:  # fmt: skip
    """A run directory belongs to one config: refuse another one (settings outside
    `NOT_IDENTITY`, or another frozen encoder file where both record one: `ENCODER_RECORD`),
    write it if new or if only those settings changed. `extends`: the model
    class of a single-task run, which may also raise `train.steps` (an extension) unless its
    training reads the task's step budget (`WorldModel.reads_task_budget`)."""
    saved = out / CONFIG
    new = json.loads(json.dumps(resolved))
    if saved.exists():
        old = json.loads(saved.read_text())
        a, b = flatten(identity(old)), flatten(identity(new))
        differ = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
        if differ == [EXTENDABLE] and extends is not None and b[EXTENDABLE] > a[EXTENDABLE]:
            if extends.reads_task_budget:
                raise ConfigError(f"{out} holds a run of {a[EXTENDABLE]} steps; a "
                                  f"{extends.__name__} run cannot be extended to more, since "
                                  "its training reads the task's step budget: use another "
                                  "--out")  # fmt: skip
            interval = b["train.eval_interval"]
            if a[EXTENDABLE] % interval:
                raise ConfigError(f"{out} holds a run of {a[EXTENDABLE]} steps, which evaluated "
                                  "and cut its episode at its last step; a longer run does not "
                                  f"there (train.eval_interval {interval}), so it cannot be "
                                  "extended: use another --out")  # fmt: skip
        elif differ:
            raise ConfigError(f"{out} holds a run with a different config (differs in "
                              f"{', '.join(differ) or 'empty option groups'}); use another "
                              "--out or delete it")  # fmt: skip
        check_same_encoder(out, new.get("encoder"), new.get(ENCODER_RECORD))
        if old == new:
            return
        note = other_data_note(old, new)
        if note:
            print(f"ccfit: note: {out}: {note}", file=sys.stderr)
    atomic_write_json(saved, new)


def other_data_note(old: dict, new: dict) -> str | None:
    """A line for a run resumed where a dataset it recorded (`DATASET_RECORDS`) now holds
    other content (`content_sha256`, recorded both times, as when it was generated again on
    another kind of machine): the run goes on with other data. None otherwise."""
    for key in DATASET_RECORDS:
        was = (old.get(key) or {}).get("content_sha256") or {}
        now = (new.get(key) or {}).get("content_sha256") or {}
        parts = [part for part in now if was.get(part) and now[part] and was[part] != now[part]]
        if parts:
            where = new.get(key.removesuffix("_meta"))
            return (f"the dataset at {where} holds other {' and '.join(parts)} than the run "
                    f"recorded ({key}): where the run reads it again (a later task, the "
                    "offline track) it reads other data")  # fmt: skip
    return None


def check_same_encoder(out: Path, encoder: str | None, sha256: str | None) -> None:
    """Refuse the run in `out` if it recorded a frozen encoder file's hash (`ENCODER_RECORD`)
    and `encoder` (`--encoder`, whose file has `sha256`) is another file at the same path."""
    saved = out / CONFIG
    was = json.loads(saved.read_text()).get(ENCODER_RECORD) if saved.exists() else None
    if was is not None and sha256 is not None and was != sha256:
        raise ConfigError(f"{out} holds a run made through another encoder file: {encoder} "
                          f"has sha256 {sha256[:12]}..., the run's had {was[:12]}...; use "
                          "another --out or the run's encoder")  # fmt: skip


def default_out(cfg: TaskRunConfig) -> Path:
    """Where a `ccfit train` run goes without --out: a name made from its config."""
    return Path("runs") / task_run_name(cfg)


@contextlib.contextmanager
def training_lock(out: Path) -> Iterator[None]:
    """Hold the lock of run directory `out` (a hidden file beside it) while the block trains
    there: a second process given the same directory stops at once, in one line, instead of
    writing its checkpoints and records over the first's."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f".{out.name}.training.lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(f"{out} is being trained by another process; wait for it to end "
                              "or use another --out") from None  # fmt: skip
        yield


def train_task(cfg: RunConfig, out: Path, *, task_id: str, task_index: int, saved: dict,
               execution: Execution, progress: bool = True,
               extendable: bool = False) -> list[dict]:  # fmt: skip
    """`task_id` learnt online from scratch into `out`, resuming from its checkpoint when it
    holds one of the same config (`saved`, what config.json holds). The task has index
    `task_index` in its curriculum (a curriculum's from-scratch reference of its composition
    task keeps that task's index: the same seeds, routing and evaluation layouts).
    `execution`: the run's (`resolve_execution`, recorded in `saved`).
    `extendable`: a run there of fewer `train.steps` goes on to `cfg.train.steps` where the
    model allows it (`check_saved_config`). One process at a time (`training_lock`). Returns
    every evaluation record."""
    out = Path(out)
    with training_lock(out):
        return _train_task(cfg, out, task_id=task_id, task_index=task_index, saved=saved,
                           execution=execution, progress=progress,
                           extendable=extendable)  # fmt: skip


def _train_task(cfg: RunConfig, out: Path, *, task_id: str, task_index: int, saved: dict,
                execution: Execution, progress: bool, extendable: bool) -> list[dict]:  # fmt: skip
    from ccdata.env import make_env

    extends = model_class(cfg.model.type) if extendable else None
    saved = compile_as_begun(out, saved)
    if (out / CONFIG).exists():
        check_saved_config(out, saved, extends=extends)
    execution.set_threads()
    resumed = (out / CHECKPOINT).exists()
    seed_everything(cfg.seed)
    model = build_model(cfg, execution.device, saved["resolved_compile"])
    model.begin_task(task_index, cfg.train.steps)
    # Seed data is read before anything is written: a bad dataset leaves no run directory. A
    # resumed run reads it no more (its checkpoint holds the replay, demonstrations included).
    source = None if resumed else saved["resolved_seed_dataset"]
    plan = plan_run_replay(cfg, model, [task_id], source)
    check_disk(plan, out)
    buffer = make_replay(cfg, model, task_id, task_index, source, plan)
    check_saved_config(out, saved, extends=extends)
    logger = RunLogger(out, cfg.log, saved)
    if not resumed:  # records of a run killed before its first checkpoint
        logger.keep(lambda r: False)
    env = make_env(
        task_id,
        render=cfg.obs == "pixels",
        image_size=cfg.image_size,
        episode_steps=cfg.train.episode_steps,
    )
    evaluator = make_evaluator(cfg, model, {task_index: task_id},
                               compiled=saved["resolved_compile"], execution=execution)  # fmt: skip
    trainer = Trainer(
        env=env, model=model, heads=model.new_heads(), buffer=buffer, evaluator=evaluator,
        config=cfg.train, execution=execution, seed=cfg.seed, obs_mode=cfg.obs, task_id=task_id,
        task_index=task_index, logger=logger, run_dir=out, progress=progress,
        extendable=extends is not None and not extends.reads_task_budget,
    )  # fmt: skip
    try:
        trainer.run()
    finally:
        evaluator.close()
        env.close()
        logger.close()
    return trainer.evals


@dataclass
class LoadedTaskRun:
    """A `ccfit train` run read back from its directory (config.json + checkpoint.pt)."""

    cfg: TaskRunConfig
    model: WorldModel
    heads: torch.nn.Module
    checkpoint: dict
    """The whole checkpoint: `task_step`, the replay's `buffer` and `replay_files`, ..."""


def load_task_run(run_dir: str | Path, device: torch.device | str | None = None
                  ) -> LoadedTaskRun:  # fmt: skip
    """The model and heads of a `ccfit train` run at its last checkpoint (its end once it
    finished), in eval mode: the single-task twin of `ccfit.curriculum.load_run`."""
    from ccfit.config_parse import saved_config
    from ccfit.io import load_checkpoint
    from ccfit.train.loop import CHECKPOINT_KIND, CHECKPOINT_VERSION

    cfg = saved_config(TaskRunConfig, run_dir, CONFIG)
    model = build_model(cfg, resolve_execution(cfg.train, device).device)
    state = load_checkpoint(Path(run_dir) / CHECKPOINT, CHECKPOINT_KIND, CHECKPOINT_VERSION)
    model.load_state_dict(state["model"])
    heads = model.new_heads()
    heads.load_state_dict(state["heads"])
    model.eval()
    heads.eval()
    return LoadedTaskRun(cfg, model, heads, state)


def train_single(cfg: TaskRunConfig, *, progress: bool = True) -> dict:
    """`ccfit train`: `cfg.task` learnt from scratch into `cfg.out`; its last record. What
    it cost goes to `cost.json`. A run there of fewer `--train.steps` is extended to these
    (`train_task`)."""
    out = Path(cfg.out) if cfg.out else default_out(cfg)
    cfg = with_encoder(cfg)
    execution = resolve_execution(cfg.train)
    resolved = resolved_config(cfg, suite_of(cfg.task), execution)
    note_no_seed_dataset(cfg, suite_of(cfg.task), resolved["resolved_seed_dataset"])
    with RunCost(out):
        evals = train_task(cfg, out, task_id=cfg.task, task_index=0, saved=resolved,
                           execution=execution, progress=progress, extendable=True)  # fmt: skip
    return evals[-1]
