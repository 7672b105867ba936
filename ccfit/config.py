"""Typed, validated configs with presets `smoke` (seconds), `cpu` (minutes) and `paper` (GPU).

A run's resolved `RunConfig` (task, model name, model config, train config) is saved as JSON
in its run directory.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

PRESETS: tuple[str, ...] = ("smoke", "cpu", "paper")
"""Preset names shared by every config class."""
OBS_MODES: tuple[str, ...] = ("state", "pixels")
DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")


_SIMPLE_TYPES: dict[str, tuple[type, ...]] = {
    "int": (int,), "float": (int, float), "bool": (bool,), "str": (str,), "None": (type(None),),
}  # fmt: skip


def check_field_types(config: Any) -> None:
    """ValueError naming the field when a value does not have its annotated simple type
    (int, float, bool, str, or unions of them with None); other annotations are not checked."""
    for f in dataclasses.fields(config):
        names = [part.strip() for part in str(f.type).split("|")]
        if not all(n in _SIMPLE_TYPES for n in names):
            continue
        allowed = tuple(t for n in names for t in _SIMPLE_TYPES[n])
        value = getattr(config, f.name)
        if isinstance(value, bool) and bool not in allowed:
            allowed = ()  # True is an int to Python, not to a config
        if not isinstance(value, allowed):
            raise ValueError(
                f"{type(config).__name__}.{f.name} must be {f.type}, got {value!r}"
            )


def _check_preset(name: str) -> str:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid: {', '.join(PRESETS)}")
    return name


# ================================================================================ training


@dataclass
class TrainConfig:
    """The online loop on one task (Algorithm 1's inner loop).

    Optimisation hyperparameters (learning rates, gradient clip) are the model's recipe and
    live in its config (`lr`, `grad_clip_norm`).
    """

    steps: int = 100_000
    """Environment (agent) steps on the task."""
    seed_steps: int = 5_000
    """Initial steps with uniformly random actions. Updates start after them, once replay
    holds an episode of at least `horizon` transitions (episodes enter replay when they end)."""
    updates_per_step: int = 1
    """Gradient updates per environment step after the seed phase."""
    batch_size: int = 256
    """Subsequences per update."""
    horizon: int | None = None
    """Actions per sampled subsequence (H; H+1 observations). None: the model config's
    `horizon`; when both are set they must agree."""
    eval_interval: int = 10_000
    """Evaluate every this many task steps (and at step 0 and at the end)."""
    eval_episodes: int = 10
    """Episodes per evaluation, on a fixed set of layouts (the same at every evaluation)."""
    checkpoint_interval: int = 50_000
    """Write a resumable checkpoint every this many task steps (and at the end)."""
    buffer_capacity: int = 1_000_000
    """Replay capacity in rows (one per transition plus one per episode)."""
    seed: int = 0
    """Seeds torch, numpy, replay sampling and every episode's layout."""
    obs: str = "state"
    """Observation mode: 'state' (39-D privileged) or 'pixels' (9 x S x S + 7-D proprio)."""
    image_size: int = 64
    """Camera image side S in pixel mode."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu' or 'cuda'."""
    torch_threads: int = 1
    """CPU threads for torch (0: torch's default). One is fastest for small models on a shared
    CPU (measured: 5 ms vs 120 ms per smoke MPPI plan on a loaded 2-core machine) and fixes
    the reduction order, which keeps runs reproducible."""
    seed_dataset: str | None = None
    """LeRobot dataset (local directory or repo id) whose episodes of the task preload replay
    before training; None: start empty."""
    dataset_endpoint: str | None = None
    """Hub endpoint a repo-id `seed_dataset` is downloaded from when it is not in LeRobot's
    local cache (the same option as `ccdata push --endpoint`); None: HF_ENDPOINT or the hub."""

    def __post_init__(self) -> None:
        check_field_types(self)
        positive = (
            "steps", "updates_per_step", "batch_size", "eval_interval",
            "eval_episodes", "checkpoint_interval", "image_size",
        )  # fmt: skip
        for name in positive:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.torch_threads < 0:
            raise ValueError(f"TrainConfig.torch_threads must be >= 0, got {self.torch_threads}")
        if self.seed_steps < 0:
            raise ValueError(f"TrainConfig.seed_steps must be >= 0, got {self.seed_steps}")
        if self.obs not in OBS_MODES:
            raise ValueError(f"TrainConfig.obs must be one of {OBS_MODES}, got {self.obs!r}")
        if self.device not in DEVICES:
            raise ValueError(f"TrainConfig.device must be one of {DEVICES}, got {self.device!r}")
        if self.image_size < 8:
            raise ValueError(f"TrainConfig.image_size must be >= 8, got {self.image_size}")
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"TrainConfig.horizon must be >= 1 or None, got {self.horizon}")
        from ccdata.env import EPISODE_STEPS

        # One full episode (T+1 rows) must fit, or the buffer could never store it.
        if self.buffer_capacity < EPISODE_STEPS + 1:
            raise ValueError(
                f"TrainConfig.buffer_capacity must be >= {EPISODE_STEPS + 1} (one episode), "
                f"got {self.buffer_capacity}"
            )

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> TrainConfig:
        """`smoke`: seconds (CI); `cpu`: minutes to an hour on 2 cores; `paper`: GPU scale."""
        base = {
            "smoke": dict(
                steps=600, seed_steps=300, batch_size=16, eval_interval=300, eval_episodes=1,
                checkpoint_interval=300, buffer_capacity=5_000,
            ),
            "cpu": dict(
                steps=6_000, seed_steps=1_000, batch_size=64, eval_interval=1_000,
                eval_episodes=5, checkpoint_interval=1_000, buffer_capacity=50_000,
            ),
            "paper": dict(
                steps=1_000_000, seed_steps=5_000, batch_size=256, eval_interval=10_000,
                eval_episodes=10, checkpoint_interval=50_000, buffer_capacity=1_000_000,
                torch_threads=0,
            ),
        }[_check_preset(name)]  # fmt: skip
        return cls(**{**base, **overrides})


# ================================================================================= a run


@dataclass
class RunConfig:
    """Everything a run needs; saved resolved as `config.json` in the run directory."""

    task: str
    """Task id, e.g. 'reach-xy'."""
    model: str
    """World model name, e.g. 'tdmpc2'."""
    model_config: Any
    """The model's own config dataclass (e.g. TDMPC2Config)."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """The online loop's config."""

    def __post_init__(self) -> None:
        from ccdata.tasks import get_task

        get_task(self.task)  # unknown task -> ValueError listing valid ids
        if not dataclasses.is_dataclass(self.model_config):
            raise ValueError("RunConfig.model_config must be a config dataclass")
        mc, tc = self.model_config, self.train
        if getattr(mc, "obs_mode", tc.obs) != tc.obs:
            raise ValueError(f"model obs_mode {mc.obs_mode!r} != train obs {tc.obs!r}")
        if tc.obs == "pixels" and getattr(mc, "image_size", tc.image_size) != tc.image_size:
            raise ValueError(f"model image_size {mc.image_size} != train {tc.image_size}")
        model_h = getattr(mc, "horizon", None)
        if tc.horizon is None and model_h is not None:
            self.train = dataclasses.replace(tc, horizon=int(model_h))  # save it resolved
        elif tc.horizon is not None and model_h is not None and tc.horizon != model_h:
            raise ValueError(f"train horizon {tc.horizon} != model horizon {model_h}")

    def to_dict(self) -> dict:
        return {
            "task": self.task,
            "model": self.model,
            "model_config": dataclasses.asdict(self.model_config),
            "train": dataclasses.asdict(self.train),
        }

    def save(self, path: str | Path) -> None:
        """Write the resolved config as JSON atomically."""
        from ccfit.train import atomic_write_text

        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")


# ================================================================================ TD-MPC2

TDMPC2_SIZES: dict[str, dict[str, int]] = {
    # The five sizes of Hansen et al. (2024), with the official dims. Trainable parameters
    # counted for this benchmark (39-D state, 4-D action, 101 bins; target Qs excluded):
    # state 1.41M / 5.48M / 19.9M / 51.8M / 335M; pixels (64 px, 32 channels) 1.79M / 5.86M /
    # 23.6M / 62.4M / 387M.
    "1M": {"enc_dim": 256, "mlp_dim": 384, "latent_dim": 128, "num_enc_layers": 2, "num_q": 2},
    "5M": {"enc_dim": 256, "mlp_dim": 512, "latent_dim": 512, "num_enc_layers": 2, "num_q": 5},
    "19M": {"enc_dim": 1024, "mlp_dim": 1024, "latent_dim": 768, "num_enc_layers": 3, "num_q": 5},
    "48M": {"enc_dim": 1792, "mlp_dim": 1792, "latent_dim": 768, "num_enc_layers": 4, "num_q": 5},
    "317M": {
        "enc_dim": 4096, "mlp_dim": 4096, "latent_dim": 1376, "num_enc_layers": 5, "num_q": 8,
    },
}  # fmt: skip
"""Model-size table: encoder width, MLP width, latent width, encoder depth, Q ensemble size."""


@dataclass
class TDMPC2Config:
    """TD-MPC2 hyper-parameters. Defaults are the official single-task values at 5M."""

    obs_mode: str = "state"
    """'state' (39-D privileged state) or 'pixels' (9-channel images + 7-D proprio)."""
    state_dim: int = 39
    """Size of the 'state' vector."""
    proprio_dim: int = 7
    """Size of the 'proprio' vector (pixel mode)."""
    image_size: int = 64
    """Side S of the square (9, S, S) pixel input; at least 32."""
    action_dim: int = 4
    """Action size; actions live in [-1, 1]."""

    latent_dim: int = 512
    """Latent width; a multiple of `simnorm_dim`."""
    enc_dim: int = 256
    """Hidden width of the encoder MLPs (state encoder, proprio branch, fusion)."""
    mlp_dim: int = 512
    """Hidden width of dynamics, reward, termination, Q and policy MLPs."""
    num_enc_layers: int = 2
    """Encoder depth in linear layers (state encoder: num_enc_layers - 1 hidden layers)."""
    num_channels: int = 32
    """Channels of each of the 4 conv layers (pixel mode)."""
    simnorm_dim: int = 8
    """SimNorm group size."""
    num_q: int = 5
    """Q ensemble size (TD targets use two random members)."""
    dropout: float = 0.01
    """Dropout after the first layer of each Q member."""
    image_shift: int = 4
    """Random-shift augmentation pad in pixels, training mode only (0 disables)."""

    num_bins: int = 101
    """Bins of the two-hot reward / value distributions."""
    vmin: float = -10.0
    """Lowest bin, in symlog space."""
    vmax: float = 10.0
    """Highest bin, in symlog space."""
    log_std_min: float = -10.0
    """Lower bound of the policy's log standard deviation."""
    log_std_max: float = 2.0
    """Upper bound of the policy's log standard deviation."""
    entropy_coef: float = 1e-4
    """Weight of the (action-dim scaled) entropy bonus in the policy loss."""

    horizon: int = 3
    """Model rollout length in training (must equal the trainer's) and planning."""
    rho: float = 0.5
    """Per-step weight rho**t of the losses over the horizon."""
    consistency_coef: float = 20.0
    """Weight of the latent consistency loss."""
    reward_coef: float = 0.1
    """Weight of the reward cross-entropy."""
    value_coef: float = 0.1
    """Weight of the value cross-entropy."""
    termination_coef: float = 1.0
    """Weight of the termination binary cross-entropy."""

    lr: float = 3e-4
    """Adam learning rate (world model, heads and policy); set in every parameter group."""
    enc_lr_scale: float = 0.3
    """Encoder learning rate = lr * enc_lr_scale."""
    policy_adam_eps: float = 1e-5
    """Adam epsilon of the policy optimiser."""
    grad_clip_norm: float = 20.0
    """Gradient-norm clip of the policy update (the trainer clips the main update)."""
    tau: float = 0.01
    """Polyak rate of the target Q ensemble and of the running Q scale."""

    episode_length: int = 250
    """Agent steps per episode; sets the discount heuristic."""
    discount_denom: float = 5.0
    """Discount = (L/denom - 1) / (L/denom), clipped to [discount_min, discount_max]."""
    discount_min: float = 0.95
    """Lower clip of the discount."""
    discount_max: float = 0.995
    """Upper clip of the discount."""

    iterations: int = 6
    """MPPI iterations per plan."""
    num_samples: int = 512
    """Action sequences evaluated per MPPI iteration (policy trajectories included)."""
    num_elites: int = 64
    """Best sequences kept to refit the sampling distribution."""
    num_pi_trajs: int = 24
    """Sequences proposed by rolling out the policy in the model."""
    min_std: float = 0.05
    """Lower clamp of the MPPI standard deviation."""
    max_std: float = 2.0
    """Initial (and upper clamp of the) MPPI standard deviation."""
    temperature: float = 0.5
    """MPPI softmax temperature on elite values."""

    def __post_init__(self) -> None:
        check_field_types(self)
        if self.obs_mode not in OBS_MODES:
            raise ValueError(
                f"TDMPC2Config.obs_mode must be one of {OBS_MODES}, got {self.obs_mode!r}"
            )
        positive = (
            "state_dim", "proprio_dim", "action_dim", "latent_dim", "enc_dim", "mlp_dim",
            "num_enc_layers", "num_channels", "simnorm_dim", "horizon", "iterations",
            "num_samples", "num_elites", "episode_length",
        )  # fmt: skip
        for name in positive:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TDMPC2Config.{name} must be >= 1, got {getattr(self, name)}")
        checks = [
            (self.latent_dim % self.simnorm_dim == 0, "latent_dim must be a multiple of simnorm"),
            (self.image_size >= 32, "image_size must be >= 32 (conv encoder)"),
            (self.num_q >= 2, "num_q must be >= 2 (targets use two members)"),
            (self.num_bins >= 2 and self.vmin < self.vmax, "need num_bins >= 2 and vmin < vmax"),
            (0.0 <= self.dropout < 1.0, "dropout must be in [0, 1)"),
            (self.image_shift >= 0, "image_shift must be >= 0"),
            (self.log_std_min < self.log_std_max, "log_std_min must be below log_std_max"),
            (0.0 < self.rho <= 1.0 and 0.0 < self.tau <= 1.0, "rho and tau must be in (0, 1]"),
            (self.lr > 0 and self.enc_lr_scale > 0, "lr and enc_lr_scale must be > 0"),
            (self.grad_clip_norm > 0, "grad_clip_norm must be > 0"),
            (0.0 < self.discount_min <= self.discount_max < 1.0,
             "need 0 < discount_min <= discount_max < 1"),
            (0 <= self.num_pi_trajs < self.num_samples, "num_pi_trajs must be in [0, num_samples)"),
            (self.num_elites <= self.num_samples, "num_elites must be <= num_samples"),
            (0.0 < self.min_std <= self.max_std, "need 0 < min_std <= max_std"),
            (self.temperature > 0, "temperature must be > 0"),
        ]  # fmt: skip
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"TDMPC2Config: {msg} (got {self})")

    @property
    def discount(self) -> float:
        """TD-MPC2's heuristic: longer episodes get a discount closer to 1 (0.98 at 250)."""
        frac = self.episode_length / self.discount_denom
        return min(max((frac - 1) / frac, self.discount_min), self.discount_max)

    @classmethod
    def preset(cls, name: str, obs_mode: str = "state", **overrides: Any) -> TDMPC2Config:
        """Same as `tdmpc2_preset`."""
        return tdmpc2_preset(name, obs_mode, **overrides)


_TDMPC2_PRESETS: dict[str, dict[str, Any]] = {
    # Tiny: unit tests and smoke runs finish in seconds.
    "smoke": dict(
        latent_dim=32, enc_dim=64, mlp_dim=64, num_enc_layers=2, num_channels=8, num_q=2,
        num_bins=21, iterations=2, num_samples=32, num_elites=8, num_pi_trajs=4,
    ),
    # Sized by measurement for 2 CPU cores (bench/learn_reach.py, 1 torch thread): an update
    # (batch 64) plus a plan costs ~30 ms, so 30k online steps take ~15-20 min. Against the
    # previous choice (MLP 256, MPPI 3 x 128) that halves the update and cuts a plan ~4x;
    # MPPI keeps the paper's structure (policy-guided, warm-started) at 2 iterations of 64.
    "cpu": dict(
        latent_dim=64, enc_dim=128, mlp_dim=128, num_enc_layers=2, num_channels=16, num_q=2,
        iterations=2, num_samples=64, num_elites=8, num_pi_trajs=8,
    ),
    # Official single-task TD-MPC2 at 5M.
    "paper": dict(TDMPC2_SIZES["5M"]),
}  # fmt: skip


def tdmpc2_preset(name: str, obs_mode: str = "state", **overrides: Any) -> TDMPC2Config:
    """TD-MPC2 config for preset `name` ('smoke', 'cpu', 'paper', or a size of `TDMPC2_SIZES`
    such as '19M'), with `overrides` applied on top."""
    if name in _TDMPC2_PRESETS:
        fields = dict(_TDMPC2_PRESETS[name])
    elif name in TDMPC2_SIZES:
        fields = dict(TDMPC2_SIZES[name])
    else:
        valid = [*_TDMPC2_PRESETS, *TDMPC2_SIZES]
        raise ValueError(f"unknown TD-MPC2 preset {name!r}; valid: {', '.join(valid)}")
    return TDMPC2Config(obs_mode=obs_mode, **{**fields, **overrides})


# ==================================================================================== PWM

PWM_ROUTERS: tuple[str, ...] = ("task", "state")
"""Gate inputs of PWM's router: the task identity, or the latent and action."""


@dataclass
class PWMConfig(TDMPC2Config):
    """PWM (prismatic world model): TD-MPC2 whose latent dynamics is a mixture of experts.

    Every TD-MPC2 field keeps its meaning; the fields below configure the mixture. Experts are
    allocated in groups of `experts_per_task` (one group per task under the 'experts' continual
    method, a single group otherwise); the temperature schedule follows the authors' code.
    """

    experts_per_task: int = 3
    """K: experts in each group (the paper adds K = 3 per task)."""
    max_tasks: int = 8
    """Most expert groups (tasks) the model can hold; also the width of the task one-hot seen
    by the router. Groups are allocated up front; only active ones are computed and trained."""
    orthogonalize: bool = False
    """Gram-Schmidt orthonormalise the expert features across experts (in activation order)
    before mixing them."""
    router: str = "task"
    """Gate input: 'task' (one-hot task identity, as the authors) or 'state' ([z, a])."""
    tau_init: float = 1.8
    """Router temperature at the start of each task, held during the hold phase."""
    tau_min: float = 0.5
    """Lower clip of the temperature."""
    tau_max: float = 2.0
    """Upper clip of the temperature."""
    tau_rate: float = 0.02
    """Step of the entropy feedback: tau += tau_rate * tanh(H_target - H(w))."""
    tau_target_frac: float = 0.75
    """H_target = tau_target_frac * log(active experts)."""
    tau_hold_min: int = 5000
    """The temperature is held for max(tau_hold_min, tau_hold_frac * task_steps) updates."""
    tau_hold_frac: float = 0.05
    """Share of a task's steps during which the temperature is held (see tau_hold_min)."""
    task_steps: int | None = None
    """Steps of each task (TrainConfig.steps), for the hold length; None: tau_hold_min only.
    `PWM.begin_task(i, task_steps)` overrides it per task."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.router not in PWM_ROUTERS:
            raise ValueError(f"PWMConfig.router must be one of {PWM_ROUTERS}, got {self.router!r}")
        checks = [
            (self.experts_per_task >= 1, "experts_per_task must be >= 1"),
            (self.max_tasks >= 1, "max_tasks must be >= 1"),
            (0.0 < self.tau_min <= self.tau_init <= self.tau_max,
             "need 0 < tau_min <= tau_init <= tau_max"),
            (self.tau_rate >= 0.0, "tau_rate must be >= 0"),
            (self.tau_target_frac >= 0.0, "tau_target_frac must be >= 0"),
            (self.tau_hold_min >= 0, "tau_hold_min must be >= 0"),
            (0.0 <= self.tau_hold_frac <= 1.0, "tau_hold_frac must be in [0, 1]"),
            (self.task_steps is None or self.task_steps >= 1, "task_steps must be >= 1 or None"),
        ]  # fmt: skip
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"PWMConfig: {msg} (got {self})")

    def hold_steps(self, task_steps: int | None = None) -> int:
        """Updates during which the temperature is held for a task of `task_steps` steps."""
        steps = task_steps if task_steps is not None else self.task_steps
        frac = int(round(self.tau_hold_frac * steps)) if steps is not None else 0
        return max(self.tau_hold_min, frac)

    @classmethod
    def preset(cls, name: str, obs_mode: str = "state", **overrides: Any) -> PWMConfig:
        """Same as `pwm_preset`."""
        return pwm_preset(name, obs_mode, **overrides)


_PWM_PRESETS: dict[str, dict[str, Any]] = {
    # Short runs get a short hold, so that the entropy feedback runs at all.
    "smoke": dict(tau_hold_min=100),
    "cpu": dict(tau_hold_min=1000),
    "paper": dict(),
}
"""PWM settings on top of the TD-MPC2 preset of the same name (sizes: paper's settings)."""


def pwm_preset(name: str, obs_mode: str = "state", **overrides: Any) -> PWMConfig:
    """PWM config: the TD-MPC2 preset `name` ('smoke', 'cpu', 'paper' or a size of
    `TDMPC2_SIZES`), the mixture settings of that preset, then `overrides`."""
    if name in _TDMPC2_PRESETS:
        fields = {**_TDMPC2_PRESETS[name], **_PWM_PRESETS[name]}
    elif name in TDMPC2_SIZES:
        fields = dict(TDMPC2_SIZES[name])
    else:
        valid = [*_TDMPC2_PRESETS, *TDMPC2_SIZES]
        raise ValueError(f"unknown PWM preset {name!r}; valid: {', '.join(valid)}")
    return PWMConfig(obs_mode=obs_mode, **{**fields, **overrides})
