"""The typed config tree of a run, on draccus (LeRobot's config library).

    ccfit run --suite Reach --preset cpu --method.type=ewc --method.lam=5000 \
        --train.steps=6000 [--model.type=NAME --model.FIELD=VALUE ...]

A run config has top-level fields (suite or task, obs, seed, preset, out, ...) and three
sub-configs chosen by registered type: `model` (`ccfit.models.registry.ModelConfig`),
`method` (`ccfit.continual.base.MethodConfig`) and `train` (`TrainConfig`). A preset fills the
defaults of all three, flags override them, `__post_init__` validates, and the resolved config
is saved as `config.json` beside every output; `--config_path config.json` reads one back
(`ccfit.config_parse`: from the command line, from plain data, from a saved config).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import draccus

from ccdata.env import DEFAULT_EPISODE_STEPS
from ccfit.config_base import (
    DEFAULTS,
    PRESETS,
    ConfigError,
    Presets,
    check,
    check_types,
    suite_tasks,
)
from ccfit.continual.base import MethodConfig, method_config_class
from ccfit.io import out_dir
from ccfit.models import DEFAULT_MODEL
from ccfit.models.registry import ModelConfig, config_class, model_class
from ccfit.obs import OBS_MODES
from ccfit.settings import check_device_name


@dataclass
class TrainConfig(Presets):
    """The online loop on one task (Algorithm 1's inner loop). Batch size, sequence length,
    update ratio and optimisers are the model's recipe (`--model.*`)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "smoke": dict(steps=600, seed_steps=300, eval_interval=300, eval_episodes=1,
                      checkpoint_interval=300, buffer_capacity=5_000, compile="off",
                      parallel="off"),
        "cpu": dict(steps=6_000, seed_steps=1_000, eval_interval=1_000, eval_episodes=5,
                    end_eval_episodes=40, checkpoint_interval=1_000, buffer_capacity=50_000),
        "paper": dict(steps=1_000_000, seed_steps=5_000, eval_interval=10_000, eval_episodes=10,
                      end_eval_episodes=40, checkpoint_interval=50_000, buffer_capacity=1_000_000,
                      torch_threads=0, autocast="auto", keep_backbone_optimizer=True),
    }  # fmt: skip

    steps: int = 100_000
    """Environment (agent) steps on each task."""
    episode_steps: int = DEFAULT_EPISODE_STEPS
    """Agent steps after which an unsolved episode ends, in training and evaluation (the
    benchmark's 250, at which the oracle references are measured; tests shorten it).
    TD-MPC2's discount heuristic reads it unless `--model.episode_length` is given."""
    seed_steps: int = 5_000
    """Initial steps with uniformly random actions (the model observes them). Updates start
    after them, once replay holds a full window."""
    eval_interval: int = 10_000
    """Evaluate every this many task steps (and at step 0 and at the end)."""
    eval_episodes: int = 10
    """Episodes per evaluation, on a fixed set of layouts (the same at every evaluation)."""
    end_eval_episodes: int | None = None
    """Episodes of the evaluation at each task's end, after the method closes the task (every
    task evaluated there; the task's own is its end-of-task score C_i, one point where the
    curves' other points are integrated): more episodes make C_i steadier. Its first
    `eval_episodes` layouts are the other evaluations'. None: `eval_episodes`. The `cpu` and
    `paper` presets' 40 hold each C_i's standard error near or under 5 normalised points
    (per-episode spread measured in docs/continual.md) for about a quarter more of a Reach
    run's cost."""
    checkpoint_interval: int = 50_000
    """Write a resumable checkpoint every this many task steps (and at the end). One within the
    run's first `seed_steps` that would wait for an evaluation still running in a worker is
    written at the first episode end after it is done instead (or at the next one)."""
    checkpoint_minutes: float = 10.0
    """Also checkpoint at the first episode end after this many minutes of wall clock since
    the last checkpoint, so a killed job loses minutes at most (0 disables). Episode ends are
    natural cut points, so these checkpoints never change what the run computes."""
    buffer_capacity: int = 1_000_000
    """Replay capacity in rows (one per observation: T+1 per episode of T steps)."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N' (resolved when the
    run starts: `ccfit.settings.resolve_execution`)."""
    torch_threads: int = 1
    """CPU threads for torch (0: torch's default). One is fastest for small models on a shared
    CPU and fixes the reduction order, which keeps runs reproducible."""
    parallel: str = "auto"
    """'on': evaluation runs in a worker process beside training (and a curriculum's
    from-scratch reference in another), on cores training does not use; 'off': all in the
    training process; 'auto': on when this process may use 2 or more cores. The records are
    the same either way (evaluating is a function of the weights); not part of a run's
    identity."""
    env_workers: str = "auto"
    """Processes the evaluation environments step and render in, so the episodes of an
    evaluation render side by side (`ccfit.train.env_workers`): a count (0: in the evaluating
    process), or 'auto': with pixel observations and `parallel` on, one per core the run leaves
    free, at most `eval_episodes`; otherwise 0. The records are the same either way; not part
    of a run's identity."""
    autocast: str = "off"
    """'bf16': the model's updates and acting run under bfloat16 autocast (matmuls in bf16,
    parameters, optimiser state and reductions in float32); 'off': float32; 'auto': bf16
    where the hardware multiplies in bf16 (a CUDA GPU of compute capability 8.0+, a CPU with
    AVX512-BF16 or AMX), else float32 (`ccfit.settings.resolve_autocast`). fp16 is not
    offered: `head_update` steps its own optimisers inside the model, where a loss scaler
    cannot reach, and bf16 needs none. Changes the numbers: config.json records what it
    resolved to (`resolved_autocast`)."""
    compile: str = "auto"
    """'off' (eager), 'on' (every hot path of the model through torch.compile), 'graphs' (every
    hot path compiled and replayed as CUDA graphs; CUDA only) or 'auto' (the hot paths
    measured faster compiled on this device type); see `ccfit.train.compiled`. The paths
    compiled are recorded in config.json."""
    demo_fraction: float = 0.0
    """Fraction of each update's replay windows that start on the task's demonstrations (the
    seed dataset's oracle episodes of the task) instead of anywhere in replay: oversampling
    demonstrations, as MoDem (Hansen et al. 2023) does, for tasks that the uniform mix learns
    too slowly. Needs a seed dataset. 0: off (every preset's default, the paper's setting)."""
    stop_score: float | None = None
    """Single-task runs (`ccfit train`) only: end the task early, at an evaluation step, once
    its last `stop_evals` evaluations all scored at least this normalised return, so that a
    learnability run spends only the steps the task needs. None: train all `steps` (a
    curriculum always does: task ends are the paper's b_i)."""
    stop_evals: int = 3
    """Consecutive evaluations `stop_score` asks for (one evaluation of a few episodes is
    noisy)."""
    keep_backbone_optimizer: bool = False
    """Curricula only: each task's world-model optimiser starts from the backbone's optimiser
    state where the previous task left it (Adam's step counts and moments), as the paper's
    authors' code did; heads' optimisers start fresh either way. False: every task starts
    fresh optimisers (Adam's moments and bias correction restart at each task switch). On in
    the `paper` preset; the `cpu` preset's published runs were made without it."""

    def __post_init__(self) -> None:
        if isinstance(self.env_workers, int) and not isinstance(self.env_workers, bool):
            self.env_workers = str(self.env_workers)  # a count given from Python
        for name in ("parallel", "compile", "autocast"):
            # draccus reads `--train.parallel=on` as YAML, where on/off are booleans, and
            # hands a str field their str(): the switch's own words again.
            value = getattr(self, name)
            if value in (True, False, "True", "False"):
                setattr(self, name, "on" if value in (True, "True") else "off")
        check_types(self)
        for name in ("steps", "episode_steps", "eval_interval", "eval_episodes",
                     "checkpoint_interval"):  # fmt: skip
            value = getattr(self, name)
            check(value >= 1, f"train.{name} must be >= 1, got {value}")
        check(self.seed_steps >= 0, f"train.seed_steps must be >= 0, got {self.seed_steps}")
        check(self.torch_threads >= 0, f"train.torch_threads must be >= 0, got "
                                       f"{self.torch_threads}")  # fmt: skip
        check(self.checkpoint_minutes >= 0, "train.checkpoint_minutes must be >= 0")
        check(self.stop_evals >= 1, f"train.stop_evals must be >= 1, got {self.stop_evals}")
        check(self.end_eval_episodes is None or self.end_eval_episodes >= 1,
              f"train.end_eval_episodes must be >= 1 (or null), got "
              f"{self.end_eval_episodes}")  # fmt: skip
        check(0.0 <= self.demo_fraction < 1.0,
              f"train.demo_fraction must be in [0, 1), got {self.demo_fraction}")  # fmt: skip
        check_device_name(self.device, "train.device")
        check(self.parallel in ("auto", "on", "off"),
              f"train.parallel must be auto, on or off, got {self.parallel!r}")  # fmt: skip
        check(self.env_workers == "auto" or self.env_workers.isdigit(),
              f"train.env_workers must be 'auto' or a count >= 0, got "
              f"{self.env_workers!r}")  # fmt: skip
        check(
            self.autocast in AUTOCAST_SETTINGS,
            f"train.autocast must be one of {AUTOCAST_SETTINGS}, got {self.autocast!r}",
        )
        check(self.compile in COMPILE_SETTINGS,
              f"train.compile must be one of {COMPILE_SETTINGS}, got {self.compile!r}")  # fmt: skip
        # One full episode (T+1 rows) must fit, or the buffer could never store it.
        check(self.buffer_capacity >= self.episode_steps + 1,
              f"train.buffer_capacity must be >= {self.episode_steps + 1} (one episode of "
              f"train.episode_steps), got {self.buffer_capacity}")  # fmt: skip


COMPILE_SETTINGS: tuple[str, ...] = ("auto", "on", "off", "graphs")
"""`--train.compile` values (`ccfit.train.compiled`)."""
AUTOCAST_SETTINGS: tuple[str, ...] = ("off", "bf16", "auto")
"""`--train.autocast` values (`ccfit.settings.resolve_autocast`)."""
WANDB_MODES: tuple[str, ...] = ("online", "offline")


def stop_reached(scores: list[float | None], stop_score: float | None, stop_evals: int) -> bool:
    """Whether evaluations scoring `scores` (normalised returns, in order) end a single-task
    run early (`TrainConfig.stop_score`)."""
    last = scores[-stop_evals:]
    return (stop_score is not None and len(last) == stop_evals
            and all(x is not None and x >= stop_score for x in last))  # fmt: skip


@dataclass
class LogConfig:
    """Where a run's scalars go besides metrics.jsonl (which always holds every evaluation).
    Not part of a run's identity: a run may be resumed with other logging settings."""

    tensorboard: bool = True
    """TensorBoard event files in the run directory (`tb/`)."""
    wandb: bool = False
    """Also log to Weights & Biases (needs the `wandb` package: `pip install wandb`)."""
    wandb_project: str = "ccbench"
    """W&B project."""
    wandb_entity: str | None = None
    """W&B entity (team or user); None: your default entity."""
    wandb_group: str | None = None
    """W&B group, e.g. a sweep's name (None: none)."""
    wandb_mode: str = "online"
    """'online', or 'offline' (written under the run directory's `wandb/`, for `wandb sync`
    later; what a cluster node without network needs)."""

    def __post_init__(self) -> None:
        check_types(self)
        check(self.wandb_mode in WANDB_MODES,
              f"log.wandb_mode must be one of {WANDB_MODES}, got {self.wandb_mode!r}")  # fmt: skip
        if self.wandb:
            import importlib.util

            check(importlib.util.find_spec("wandb") is not None,
                  "log.wandb needs the wandb package: pip install wandb")  # fmt: skip


def _default_model() -> ModelConfig:
    return config_class(DEFAULT_MODEL)()


def _default_method() -> MethodConfig:
    return method_config_class(DEFAULTS["method"])()


@dataclass
class BaseRunConfig:
    """What every run has, online (`RunConfig`) or offline (`ccfit.offline.OfflineConfig`)."""

    obs: str = DEFAULTS["obs"]
    """Observation mode: 'state' (39-D privileged state) or 'pixels' (the paper: three
    cameras channel-stacked to 9 channels plus the 7-D proprio)."""
    seed: int = 0
    """Seeds everything: model init, replay sampling, episode and evaluation layouts."""
    preset: str = DEFAULTS["preset"]
    """Size preset filling the defaults of model, method and train: smoke (seconds), cpu
    (2 CPU cores), paper (the paper's scale, for a GPU). Flags override it."""
    out: str | None = None
    """Run directory (None: a name made from the config under runs/)."""
    image_size: int = DEFAULTS["image_size"]
    """Camera image side in pixel mode (the other render settings are ccdata's defaults,
    `ccdata.RenderSettings`, recorded in config.json)."""
    encoder: str | None = None
    """'frozen:PATH': a pretrained encoder (`ccfit pretrain-encoder`), frozen for the run."""
    dataset_endpoint: str | None = None
    """Hub endpoint a repo-id dataset is downloaded from when it is not in LeRobot's local
    cache (as `ccdata push --endpoint`); None: HF_ENDPOINT or the hub."""
    model: ModelConfig = field(default_factory=_default_model)
    """The world model (`--model.type`: a registered model) and its hyperparameters."""
    log: LogConfig = field(default_factory=LogConfig)
    """Where scalars are logged (TensorBoard, Weights & Biases)."""

    def __post_init__(self) -> None:
        check_types(self)
        check(self.obs in OBS_MODES, f"unknown obs mode {self.obs!r}; valid: {OBS_MODES}")
        check(self.preset in PRESETS, f"unknown preset {self.preset!r}; valid: "
                                      f"{', '.join(PRESETS)}")  # fmt: skip
        check(self.image_size >= 32, f"image_size must be >= 32, got {self.image_size}")
        check(0 <= self.seed < 2**31, f"seed must be in [0, 2**31), got {self.seed}")
        if self.out is not None:
            out_dir(self.out)  # a file in its place is refused
        # The observation mode and image size are the run's: the model's config holds a copy
        # (what config.json has always recorded, so runs keep their identity), derived here
        # and never read as an input of its own (`ccfit.config_parse` drops a given one).
        if (self.model.obs_mode, self.model.image_size) != (self.obs, self.image_size):
            self.model = dataclasses.replace(self.model, obs_mode=self.obs,
                                             image_size=self.image_size)  # fmt: skip
        self.model = model_for_episodes(self.model, self.episode_steps)
        if self.encoder is not None:
            check(
                self.encoder.startswith("frozen:"),
                f"encoder must be 'frozen:PATH', got {self.encoder!r}",
            )
            check(self.obs == "pixels", "a frozen pretrained encoder needs --obs pixels")
            # The file itself is read when the run starts (`with_encoder`): validation does
            # no I/O.

    @property
    def episode_steps(self) -> int:
        """Agent steps per episode of the environments the run plays (an offline run plays
        none: the benchmark's)."""
        return DEFAULT_EPISODE_STEPS

    @property
    def encoder_path(self) -> str | None:
        return self.encoder.split(":", 1)[1] if self.encoder else None

    def to_dict(self) -> dict:
        """The resolved config as plain data (what config.json holds)."""
        return draccus.encode(self)

    def save(self, path: str | Path) -> None:
        from ccfit.io import atomic_write_json

        atomic_write_json(path, self.to_dict())


@dataclass
class RunConfig(BaseRunConfig):
    """What every online run has (one task with `ccfit train`, a curriculum with `ccfit run`)."""

    seed_dataset: str | None = "auto"
    """Replay of each task starts with its own episodes of this LeRobot dataset: 'auto' = the
    suite's dataset when it exists locally, None = off, or a repo id / directory."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """The online training loop."""

    @property
    def episode_steps(self) -> int:
        return self.train.episode_steps

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.train.demo_fraction == 0 or self.seed_dataset is not None,
              f"train.demo_fraction {self.train.demo_fraction} (given, or the model's budget "
              f"for the suite) oversamples the seed dataset's demonstrations: it needs a seed "
              f"dataset (--seed_dataset), or --train.demo_fraction=0")  # fmt: skip
        bc = getattr(self.model, "demo_bc_coef", 0.0)  # the models that clone demonstrations
        check(bc == 0 or self.train.demo_fraction > 0,
              f"model.demo_bc_coef {bc} clones the demonstrations that "
              "--train.demo_fraction puts in each batch; it is 0 here: set it > 0, or "
              "--model.demo_bc_coef=0")  # fmt: skip


def model_for_episodes(model: ModelConfig, episode_steps: int) -> ModelConfig:
    """`model` with the run's episode length where its config reads one (TD-MPC2's
    `episode_length`, for its discount) and was not given, so config.json records the value
    the model used."""
    if getattr(model, "episode_length", 0) is not None:  # given, or the model has none
        return model
    return dataclasses.replace(model, episode_length=episode_steps)


def with_encoder[C: BaseRunConfig](cfg: C) -> C:
    """`cfg` with its frozen encoder's sizes in its model config (those fields the model's
    config has), so the saved config states what the run used; `cfg` itself without one.
    Reads the encoder file: a step of a run's start (the tracks', `ccfit train`'s), not of
    validation. ConfigError, in one line, for a missing or damaged file or one whose image
    size is not the run's."""
    if cfg.encoder_path is None:
        return cfg
    from ccfit.models.encoders import load_frozen_encoder

    path = cfg.encoder_path
    check(Path(path).is_file(), f"encoder checkpoint not found: {path}")
    try:
        _, spec = load_frozen_encoder(path)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    size = spec.pop("image_size")
    check(size == cfg.image_size, f"the encoder {path} reads {size} px images but the run "
                                  f"renders {cfg.image_size} px (--image_size)")  # fmt: skip
    names = {f.name for f in dataclasses.fields(cfg.model)} - {"obs_mode"}
    sizes = {k: v for k, v in spec.items() if k in names}
    if all(getattr(cfg.model, k) == v for k, v in sizes.items()):
        return cfg
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **sizes))


@dataclass
class TaskRunConfig(RunConfig):
    """One task learnt online from scratch (`ccfit train`)."""

    task: str = "reach-xy"
    """Task id, e.g. 'reach-xy' (`ccdata list`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        from ccdata.tasks import get_task

        try:
            get_task(self.task)
        except ValueError as e:
            raise ConfigError(str(e)) from None


@dataclass
class CurriculumConfig(RunConfig):
    """A suite's curriculum learnt continually with one method (`ccfit run`)."""

    suite: str = "Reach"
    """Suite name (`ccdata list`); its tasks are learnt in order, the composition last."""
    method: MethodConfig = field(default_factory=_default_method)
    """The continual method (`--method.type`: ft, er, ewc, packnet, experts)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        suite_tasks(self.suite)
        # Everything that would fail once the run is under way fails here, before it starts.
        check_pairing(self.model, self.method, len(self.tasks))
        check_references(self.tasks)
        check(self.train.stop_score is None,
              "train.stop_score ends single-task runs early (`ccfit train`); a curriculum "
              "trains every task for its steps")  # fmt: skip
        check(self.train.steps % self.train.eval_interval == 0,
              f"steps per task ({self.train.steps}) must be a multiple of eval_interval "
              f"({self.train.eval_interval}) so every task is evaluated at its end")  # fmt: skip

    @property
    def tasks(self) -> list[str]:
        return suite_tasks(self.suite)


def check_pairing(model: ModelConfig, method: MethodConfig, num_tasks: int) -> None:
    """ConfigError unless the model offers what the method needs and both can learn a
    curriculum of `num_tasks` tasks."""
    missing = method.REQUIRES - model_class(model.type).capabilities
    offering = ", ".join(models_offering(method.REQUIRES)) or "none"
    check(not missing, f"method {method.type!r} needs a model offering "
                       f"{', '.join(sorted(missing))}; models that do: {offering}")  # fmt: skip
    model.check_curriculum(num_tasks)
    method.check_curriculum(num_tasks)


def models_offering(capabilities: frozenset[str]) -> list[str]:
    """Registered models declaring every one of `capabilities`."""
    from ccfit.models.registry import MODELS

    return sorted(n for n, cls in MODELS.items() if capabilities <= cls.capabilities)


def check_references(tasks: list[str]) -> None:
    """ConfigError unless every task has its oracle reference (normalised returns, hence
    BWT and FWT, need it): found before a run starts, not after it."""
    from ccdata.scoring import oracle_reference

    for task in tasks:
        try:
            oracle_reference(task)
        except ValueError as e:
            raise ConfigError(str(e)) from None
