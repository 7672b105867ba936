"""What determines a ccdata dataset, and where a dataset lives.

A leaf of the dataset side: it imports the suites, the environment's constants and the render
settings, never the generation engine (`ccdata.record`, `ccdata.journal`), so cards, the
on-disk format, the journal and `ccfit` can all read a dataset's settings without it.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from ccdata.env import DEFAULT_EPISODE_STEPS, FPS
from ccdata.errors import InputError
from ccdata.render import RenderSettings
from ccdata.repo_id import validate_repo_id
from ccdata.suites import SUITES, get_suite
from ccdata.tasks import ExplorationNoise, get_task

FORMAT_VERSION = 2
"""ccdata's layout inside LeRobot v3. 2: every episode ends with a frame that holds the
observation after its last action (`is_final_observation`); 1 did not record it."""

POLICY_ORDER: tuple[str, ...] = ("oracle", "noisy-oracle", "random")
"""Policies in plan order; a frame's `policy_index` indexes this tuple."""

VIDEO_ENCODER: dict = {
    "vcodec": "h264",
    "pix_fmt": "yuv444p",
    "crf": 0,
    "g": 10,
    "preset": "veryfast",
    "extra_options": {"bf": 0},
}
"""Camera video encoding. libx264 with crf 0 is lossless in YUV 4:4:4, so the only loss is the
RGB<->YUV rounding: ~52 dB PSNR on every frame (LeRobot's default AV1 4:2:0 crf 30 gives ~27 dB).
No B-frames keep presentation and decoding order equal, which keeps concatenated episode videos'
timestamps exact; a keyframe every 10 frames bounds the decoding work per random access. Being
lossless, the x264 preset trades only file size for encoding time, never the decoded frames:
`veryfast` against `medium` measured -0.7 ms of writer CPU per frame (3 cameras, 64 px) for +5%
bytes; `ultrafast` saves 0.6 ms more for +23%."""

IDENTITY_KEYS = ("suite", "seed", "image_size", "noise_std", "random_prob", "max_steps")
"""Settings that must match to append to an existing dataset (plus the resolved exploration
noise per task, render, fps, video and format, and `LEGACY_IDENTITY`'s)."""
LEGACY_IDENTITY: dict = {"episode_steps": DEFAULT_EPISODE_STEPS}
"""Identity settings added after datasets were made, each with the value those datasets were
made with. `DatasetSettings.identity` leaves a setting out at that value, so a dataset written
before it existed is appended to as before; `check_identity` reads a missing one as it."""


def default_repo_id(suite: str) -> str:
    return f"ccdata/{suite}"


def dataset_root(repo_id: str, root: str | Path | None = None) -> Path:
    """Where the dataset `repo_id` lives: `root` when given, else LeRobot's cache
    `$HF_LEROBOT_HOME/<repo_id>` (where `LeRobotDataset(repo_id)` looks first)."""
    if root is not None:
        return Path(root).expanduser().resolve()
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return (HF_LEROBOT_HOME / repo_id).resolve()


def suite_dataset_root(suite: str) -> Path:
    """The default location of a suite's dataset (`ccdata generate --suite <suite>`)."""
    return dataset_root(default_repo_id(get_suite(suite).name))


@dataclass
class DatasetSettings:
    """Everything that determines a generated dataset's content. Validated on construction."""

    suite: str
    """Suite name (one of `ccdata.SUITES`); the dataset holds every task of the suite."""
    episodes: int = 50
    """Oracle episodes per task."""
    explore_episodes: int = 25
    """Episodes per task for each exploration policy (noisy-oracle and random)."""
    image_size: int = 64
    """Side of the square camera images in pixels."""
    seed: int = 0
    """Base seed; every episode seed derives from it, the task, the policy and the index."""
    root: str | Path | None = None
    """Dataset directory; None -> LeRobot's default `$HF_LEROBOT_HOME/<repo_id>`, so that
    `LeRobotDataset(repo_id)` opens it with no other argument."""
    repo_id: str | None = None
    """LeRobot / Hub repository id; None -> `ccdata/<Suite>`."""
    noise_std: float | None = None
    """Std of the Gaussian noise the noisy oracle adds to the oracle's action, for every task;
    None -> each task's calibrated value (`TaskSpec.exploration`)."""
    random_prob: float | None = None
    """Probability that the noisy oracle takes a uniform random action instead, for every task;
    None -> each task's calibrated value."""
    shadows: bool = False
    """Render shadows (see `ccdata.RenderSettings`)."""
    reflections: bool = False
    """Render reflections."""
    skybox: bool = False
    """Render the skybox."""
    msaa_samples: int = 0
    """Multisample anti-aliasing samples."""
    max_steps: int | None = None
    """Cut every episode after this many agent steps (tests, previews), without the
    environment's truncation; None -> full episodes (`episode_steps` steps or success)."""
    episode_steps: int = DEFAULT_EPISODE_STEPS
    """Agent steps after which the environment truncates an unsolved episode (the benchmark's
    250); recorded in the dataset's metadata and card."""

    def __post_init__(self) -> None:
        if self.suite not in SUITES:
            raise InputError(f"unknown suite {self.suite!r}; valid suites: {', '.join(SUITES)}")
        for name in ("episodes", "explore_episodes"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.episodes + self.explore_episodes == 0:
            raise InputError("episodes and explore_episodes are both 0: nothing to generate")
        if self.seed < 0:
            raise InputError(f"seed must be >= 0, got {self.seed}")
        if self.episode_steps < 1:
            raise InputError(f"episode_steps must be >= 1, got {self.episode_steps}")
        if self.max_steps is not None and not 1 <= self.max_steps <= self.episode_steps:
            raise InputError(
                f"max_steps must be in [1, {self.episode_steps}] (episode_steps) or None, "
                f"got {self.max_steps}"
            )
        if (self.noise_std is not None and not self.noise_std >= 0) or (
            self.random_prob is not None and not 0.0 <= self.random_prob <= 1.0
        ):
            raise InputError("noise_std must be >= 0 and random_prob in [0, 1] (or unset)")
        if self.repo_id is None:
            self.repo_id = default_repo_id(self.suite)
        validate_repo_id(self.repo_id)  # it names a folder under LeRobot's cache too
        _ = self.render_settings  # validates image_size and msaa_samples

    @property
    def render_settings(self) -> RenderSettings:
        return RenderSettings(
            image_size=self.image_size,
            shadows=self.shadows,
            reflections=self.reflections,
            skybox=self.skybox,
            msaa_samples=self.msaa_samples,
        )

    @property
    def dataset_root(self) -> Path:
        return dataset_root(self.repo_id, self.root)

    def exploration(self, task_id: str) -> ExplorationNoise:
        """The noisy oracle's noise on `task_id`: the task's calibration, unless overridden."""
        calibrated = get_task(task_id).exploration
        return ExplorationNoise(
            noise_std=calibrated.noise_std if self.noise_std is None else self.noise_std,
            random_prob=calibrated.random_prob if self.random_prob is None else self.random_prob,
        )

    def exploration_table(self) -> dict[str, dict[str, float]]:
        """Task id -> the noisy oracle's noise, for every task of the suite."""
        return {t: self.exploration(t).to_dict() for t in get_suite(self.suite).task_ids}

    def to_dict(self) -> dict:
        """The fields (root resolved), as stored in a dataset's metadata."""
        d = dataclasses.asdict(self)
        d["root"] = str(self.dataset_root)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DatasetSettings:
        """Inverse of `to_dict` (unknown keys, e.g. a GenerateConfig's `workers`, ignored)."""
        names = {f.name for f in dataclasses.fields(DatasetSettings)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def identity(self) -> dict:
        """The settings an existing dataset must share to be appended to."""
        ident = {k: getattr(self, k) for k in IDENTITY_KEYS}
        ident.update({k: getattr(self, k) for k, legacy in LEGACY_IDENTITY.items()
                      if getattr(self, k) != legacy})  # fmt: skip
        ident["exploration"] = self.exploration_table()
        ident["render"] = self.render_settings.to_dict()
        ident["fps"] = FPS
        ident["video"] = VIDEO_ENCODER
        ident["format"] = FORMAT_VERSION
        return json.loads(json.dumps(ident))
