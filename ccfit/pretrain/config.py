"""The settings of encoder pretraining."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from ccdata.errors import InputError
from ccdata.suites import SUITES
from ccfit.config_base import ConfigError, Presets
from ccfit.models import DEFAULT_MODEL
from ccfit.models.encoders import IMAGE_TRUNKS, EncoderSpec
from ccfit.models.registry import model_class, model_names
from ccfit.settings import check_device_name

KIND = "ccfit-pretrained-encoder"
"""The sidecar's 'kind': an encoder made by this module."""
CHECKPOINT_VERSION = 1
_SAMPLE_TAG = 2  # seed stream of batch sampling, independent of the split's (SPLIT_TAG)
_NOT_IDENTITY = ("device", "torch_threads", "checkpoint_interval", "log_interval")
"""Config fields that may change between a run and its resumption (they do not change what is
learnt, up to floating-point differences across devices)."""

BATCH_FROM = ("all", "suite")
"""Where a batch's frames come from (`PretrainConfig.batch_from`)."""

LEGACY_SETTINGS = {
    "policies": ["oracle"],
    "foreground_weight": 0.0,
    "keypoints": 0,
    "image_trunk": "stacked",
    "contrastive_coef": 0.0,
    "batch_from": "all",
}
"""Settings added after encoders were made, at the value that reproduces those encoders (a
sidecar that leaves one out was made at it)."""

OBJECTIVE = (
    "MSE(image) + proprio_coef * MSE(proprio); image MSE over the 9 stacked channels on the "
    "[0, 1] scale (uint8 / 255), each camera pixel's error weighted 1 + foreground_weight where "
    "it differs from its suite's background by more than foreground_threshold (and divided by "
    "the weights' sum); proprio MSE on the proprio standardised with the training frames' mean "
    "and std (the encoder reads the raw proprio); + contrastive_coef * InfoNCE of each frame's "
    "projected latent against another frame of its episode among the batch's (temperature "
    "contrastive_temperature)"
)


_SEES_THE_TASK = dict(policies=("oracle", "noisy-oracle", "random"), foreground_weight=20.0,
                     contrastive_coef=1.0, proprio_coef=1.0, image_trunk="per-camera")  # fmt: skip
"""The recipe whose latent holds the goal, the objects and their colours, and the hand (the
proprio weight 1: the contrastive term alone gives the hand up; the per-camera trunk: stacked,
the latent keeps one cue per episode, a goal or an object, and the hand less; docs/encoder.md:
the levers measured); the `smoke` preset keeps the plain autoencoder, for speed."""

# ============================================================================== config


@dataclass
class PretrainConfig(Presets):
    """Autoencoder pretraining of the frozen encoder. Validated on construction.

    The encoder's sizes are not fields: they come from the config of `model` at
    `model_preset` in pixel mode, so the encoder always fits the model preset it is meant for.
    `model` must build the shared pixel encoder (`ccfit.models.encoders`, the capability
    'pixel-encoder'). Preset values for steps, batch size, learning rate and decoder width are
    this project's choices (the paper gives none).
    """

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # smoke: seconds (CI); cpu: minutes to an hour on 2 cores; paper: GPU scale. The
        # encoder's sizes follow the model's preset of the same name.
        "smoke": dict(model_preset="smoke", steps=100, batch_size=16, lr=1e-3,
                      decoder_channels=16, checkpoint_interval=50, log_interval=10),
        "cpu": dict(model_preset="cpu", steps=10_000, batch_size=64, lr=5e-4,
                    decoder_channels=16, augment_shift=4, checkpoint_interval=1_000,
                    log_interval=100, **_SEES_THE_TASK),
        "paper": dict(model_preset="paper", steps=100_000, batch_size=256, lr=3e-4,
                      decoder_channels=64, augment_shift=4, checkpoint_interval=5_000,
                      log_interval=500, **_SEES_THE_TASK),
    }  # fmt: skip

    model: str = DEFAULT_MODEL
    """The registered world model whose pixel encoder is pretrained (one offering
    'pixel-encoder'); the frozen encoder fits it and models sharing its encoder layout."""
    model_preset: str = "cpu"
    """That model's preset ('smoke', 'cpu', 'paper', or one of its own, e.g. a size) whose
    pixel encoder is pretrained; use the frozen encoder with a model of this preset."""
    suites: tuple[str, ...] = tuple(SUITES)
    """Suites whose oracle episodes are used (default: all six)."""
    dataset_roots: dict[str, str] = field(default_factory=dict)
    """Suite -> dataset directory; a suite not listed uses
    `ccdata.settings.suite_dataset_root(suite)` (LeRobot's cache for `ccdata/<Suite>`)."""
    image_size: int = 64
    """Camera image side; every dataset must have been generated at this size."""
    keypoints: int = 0
    """The encoder's image features as this many spatial-softmax keypoints (the model
    config's `keypoints`, recorded in the encoder file; a run through it takes it from
    there); 0: the model preset's own image features."""
    image_trunk: str = "stacked"
    """The encoder's conv stack on the 9 channel-stacked channels ('stacked') or on each
    camera's 3 apart ('per-camera', the `cpu` and `paper` presets'): the model config's
    `image_trunk`, recorded in the encoder file as `keypoints` is."""
    steps: int = 20_000
    """Gradient steps."""
    batch_size: int = 64
    """Frames per gradient step, sampled uniformly from the training episodes' frames (of one
    suite at a time where `batch_from` is 'suite')."""
    batch_from: str = "all"
    """'all': each batch drawn from every suite's frames; 'suite': each from one suite's (the
    suite drawn in proportion to its training frames, so every frame stays equally likely), so
    that the contrastive term's other episodes show the same scene and only the layout (where
    the objects and the goal are, which colours) tells them apart."""
    lr: float = 5e-4
    """Adam learning rate (encoder and decoder)."""
    grad_clip_norm: float = 20.0
    """Gradient-norm clip."""
    proprio_coef: float = 0.1
    """Weight of the standardised-proprio MSE against the [0, 1]-scale image MSE."""
    decoder_channels: int = 32
    """Channels of the decoder's last transposed convolution (earlier layers: 2x and 4x)."""
    augment_shift: int = 0
    """Random-shift augmentation in pixels, applied identically to the input and the
    reconstruction target (0: none). The encoder's own training-time shift is never used."""
    holdout: float = 0.1
    """Fraction of each task's episodes held out for evaluation (at least one episode overall
    when there are two or more)."""
    frame_stride: int = 1
    """Keep every `frame_stride`-th frame of each oracle episode (memory: ~37 KB per 64 px
    frame)."""
    policies: tuple[str, ...] = ("oracle",)
    """The policies whose episodes are read (names as the datasets' meta holds them: 'oracle',
    'noisy-oracle', 'random'). The exploration policies' episodes put the hand where an
    oracle's never goes, away from the goal and objects, and are 250 frames long."""
    explore_frame_stride: int = 5
    """Keep every this-many-th frame of the other policies' episodes (their hand moves slowly:
    neighbouring frames are nearly the same image)."""
    foreground_weight: float = 0.0
    """Extra weight of a reconstruction error on a foreground pixel (one that differs from its
    suite's static background, `ccfit.pretrain.foreground`): each such pixel counts 1 +
    this. 0: plain MSE over the frame."""
    contrastive_coef: float = 0.0
    """Weight of the episode-contrastive term (`ccfit.pretrain.contrastive`): a frame's latent
    must pick out another frame of its episode among the batch's other episodes, which only the
    layout (goal, objects, colours) tells apart. 0: none."""
    contrastive_temperature: float = 0.1
    """Temperature of that term's softmax over the batch."""
    foreground_threshold: float = 0.08
    """A pixel is foreground where a colour channel differs from the background by more than
    this, on the [0, 1] scale."""
    eval_batch_size: int = 256
    """Frames per forward pass in evaluation."""
    checkpoint_interval: int = 1_000
    """Write a resumable checkpoint every this many steps (and on Ctrl-C)."""
    log_interval: int = 100
    """Steps averaged into each point of the loss history."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N', as `--train.device`
    (resolved when pretraining starts: `ccfit.settings.resolve_execution`)."""
    torch_threads: int = 1
    """CPU threads for torch during pretraining (0: leave torch's setting); restored after. 1,
    as training's: at torch's own count (2 on a 2-core machine) beside one other job a step took
    3-5 s, at 1 thread 0.23 s (docs/encoder.md)."""
    seed: int = 0
    """Seeds the initialisation, the episode split, batch sampling and augmentation."""

    def __post_init__(self) -> None:
        if isinstance(self.suites, str):  # 'all' or a comma list, as on the command line
            names = [s.strip() for s in self.suites.split(",") if s.strip()]
            self.suites = tuple(SUITES) if [n.lower() for n in names] == ["all"] else names
        self.suites = tuple(self.suites)
        bad = [s for s in self.suites if s not in SUITES]
        if bad or not self.suites:
            raise InputError(
                f"unknown suite(s) {bad or '(none given)'}; valid: {', '.join(SUITES)} or 'all'"
            )
        if len(set(self.suites)) != len(self.suites):
            raise InputError(f"PretrainConfig.suites lists a suite twice: {self.suites}")
        self.dataset_roots = {str(k): str(v) for k, v in dict(self.dataset_roots).items()}
        extra = [s for s in self.dataset_roots if s not in SUITES]
        if extra:
            raise InputError(f"dataset_roots has unknown suite(s) {extra}; valid: {list(SUITES)}")
        if isinstance(self.policies, str):  # a comma list, as on the command line
            self.policies = [p.strip() for p in self.policies.split(",") if p.strip()]
        self.policies = tuple(self.policies)
        if "oracle" not in self.policies or len(set(self.policies)) != len(self.policies):
            raise InputError(f"PretrainConfig.policies must hold 'oracle' once, got "
                             f"{list(self.policies)}")  # fmt: skip
        for name in ("steps", "batch_size", "decoder_channels", "frame_stride",
                     "explore_frame_stride", "eval_batch_size", "checkpoint_interval",
                     "log_interval"):  # fmt: skip
            if int(getattr(self, name)) < 1:
                raise InputError(f"PretrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        checks = [
            (self.lr > 0 and self.grad_clip_norm > 0, "lr and grad_clip_norm must be > 0"),
            (self.proprio_coef >= 0, "proprio_coef must be >= 0"),
            (self.foreground_weight >= 0, "foreground_weight must be >= 0"),
            (self.keypoints >= 0, "keypoints must be >= 0"),
            (self.image_trunk in IMAGE_TRUNKS, f"image_trunk must be one of {IMAGE_TRUNKS}"),
            (self.contrastive_coef >= 0, "contrastive_coef must be >= 0"),
            (self.contrastive_temperature > 0, "contrastive_temperature must be > 0"),
            (0 < self.foreground_threshold < 1, "foreground_threshold must be in (0, 1)"),
            (self.augment_shift >= 0, "augment_shift must be >= 0"),
            (0.0 <= self.holdout < 1.0, "holdout must be in [0, 1)"),
            (self.torch_threads >= 0, "torch_threads must be >= 0"),
            (self.seed >= 0, "seed must be >= 0"),
            (self.batch_from in BATCH_FROM, f"batch_from must be one of {BATCH_FROM}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"PretrainConfig: {msg}")
        check_device_name(self.device, "PretrainConfig: device")
        self.encoder_config()  # unknown preset or bad image size -> InputError

    def encoder_config(self) -> EncoderSpec:
        """The settings of the encoder this run pretrains: `model`'s, at `model_preset`, in
        pixel mode."""
        try:
            cls = model_class(self.model)
        except ConfigError as e:
            raise InputError(str(e)) from None
        if "pixel-encoder" not in cls.capabilities:
            offering = [n for n in model_names() if "pixel-encoder" in model_class(n).capabilities]
            raise InputError(f"model {self.model!r} does not build the shared pixel encoder; "
                             f"models that do: {', '.join(offering)}")  # fmt: skip
        given = {"keypoints": self.keypoints} if self.keypoints else {}
        if self.image_trunk != "stacked":
            given["image_trunk"] = self.image_trunk
        cfg = cls.config_class.preset(self.model_preset, obs_mode="pixels",
                                      image_size=self.image_size, **given)  # fmt: skip
        return EncoderSpec.of(cfg)

    def resolved_roots(self) -> dict[str, Path]:
        """Suite -> dataset directory for every suite of the run."""
        from ccdata.settings import suite_dataset_root

        return {
            s: Path(self.dataset_roots[s]).expanduser().resolve()
            if s in self.dataset_roots else suite_dataset_root(s)
            for s in self.suites
        }  # fmt: skip

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["suites"] = list(self.suites)
        d["policies"] = list(self.policies)
        d["dataset_roots"] = {s: str(p) for s, p in self.resolved_roots().items()}
        return d

    def identity(self) -> dict:
        """The settings a checkpoint or finished output must share to be resumed or reused;
        a setting at its `LEGACY_SETTINGS` value is left out, so an output made before it
        existed is still this run's."""
        settings = self.to_dict()
        legacy = {k: v for k, v in LEGACY_SETTINGS.items() if settings[k] == v}
        if self.policies == ("oracle",):  # the exploration stride has nothing to stride
            legacy["explore_frame_stride"] = self.explore_frame_stride
        if self.foreground_weight == 0:
            legacy["foreground_threshold"] = self.foreground_threshold
        if self.contrastive_coef == 0:
            legacy["contrastive_temperature"] = self.contrastive_temperature
        return {k: v for k, v in settings.items()
                if k not in _NOT_IDENTITY and k not in legacy}  # fmt: skip
