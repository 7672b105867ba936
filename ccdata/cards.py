"""Dataset cards (Markdown with a YAML header).

`render_card(suite)` is the card of a suite's dataset at the default settings, checked in as
cards/<Suite>.md: a pure function of the package (suites, tasks, default settings, calibrated
exploration noise, reference measurements in `references.json`), so regenerating it is
reproducible. `render_card(settings, dataset=root)` is the card a generated dataset ships as its
README.md: rendered from the settings that dataset was generated with, plus what was measured on
the dataset itself (counts, success rates, returns, size, library versions).
"""

from __future__ import annotations

from pathlib import Path

from ccdata.dataset_format import FINAL_KEY, measure_dataset
from ccdata.env import ACTION_REPEAT, FPS
from ccdata.render import CAMERAS
from ccdata.scoring import GAMMA, floor_return, reference_episode_steps, references
from ccdata.settings import FORMAT_VERSION, POLICY_ORDER, VIDEO_ENCODER, DatasetSettings
from ccdata.suites import get_suite

PAPER = {
    "title": "Benchmarking World Models for Continual Learning on Compositional Tasks",
    "authors": "Haoyu Zhou, Joe Watson, Anson Lei, Ingmar Posner",
    "url": "https://object814.github.io/Compositional-Continual-Learning/",
}

REFERENCE_SIZE_PER_1000_FRAMES = {
    "videos_mb": 4.5,
    "data_mb": 0.20,
    "measured_on": (
        "a Grasp dataset with 4 oracle, 2 noisy-oracle and 2 random episodes per task, by "
        "bench/dataset_write.py"
    ),
}
"""Size of the default settings' datasets per 1000 stored frames, for the default cards (a
generated dataset's card states its own measured size)."""

AXIS_TEXT = {
    "action": "action composition: the scene stays the same while the composition task "
    "recombines the action primitives learnt before it",
    "perception": "perception composition: the manipulation stays the same while object "
    "appearance changes; the composition task meets an unseen combination of appearances",
    "full": "full composition: primitives differ in both action and perception, and the "
    "composition task chains them in time",
}


def _yaml_list(items, indent: int = 2) -> str:
    pad = " " * indent
    return "\n".join(f"{pad}- {item}" for item in items)


def _table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _num(value, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def render_card(
    suite_or_settings: str | DatasetSettings,
    dataset: str | Path | None = None,
    metadata: dict | None = None,
) -> str:
    """A suite's default card (given a suite name), or the card of the dataset at `dataset`
    generated with `suite_or_settings` (its `meta/ccdata.json` content may be passed as
    `metadata`, else it is read from the dataset)."""
    settings = (
        DatasetSettings(suite=suite_or_settings)
        if isinstance(suite_or_settings, str)
        else suite_or_settings
    )
    measured = None
    if dataset is not None:
        if metadata is None:
            from ccdata.dataset_format import read_ccdata_metadata

            metadata = read_ccdata_metadata(Path(dataset))
        measured = measure_dataset(Path(dataset), list(get_suite(settings.suite).task_ids))
    return _header(settings) + "\n" + _body(settings, measured, metadata)


def _header(settings: DatasetSettings) -> str:
    suite = get_suite(settings.suite)
    matrix = suite.composition_matrix().astype(int)
    counts = {
        "oracle": settings.episodes,
        "noisy-oracle": settings.explore_episodes,
        "random": settings.explore_episodes,
    }
    return "\n".join(
        [
            "---",
            "license: mit",
            "task_categories:",
            "- robotics",
            "tags:",
            _yaml_list(
                ["LeRobot", "metaworld", "continual-learning", "world-models", suite.name], indent=0
            ),
            "configs:",
            "- config_name: default",
            "  data_files: data/*/*.parquet",
            "ccdata:",
            f"  suite: {suite.name}",
            f"  axis: {suite.axis}",
            "  tasks:",
            _yaml_list([t.id for t in suite.tasks], indent=2),
            "  composition_matrix:",
            _yaml_list([str(list(map(int, row))) for row in matrix], indent=2),
            f"  image_size: {settings.image_size}",
            "  episodes_per_task:",
            *[f"    {p}: {counts[p]}" for p in POLICY_ORDER],
            f"  seed: {settings.seed}",
            f"  format: {FORMAT_VERSION}",
            "---",
        ]
    )


def _tasks_section(settings: DatasetSettings) -> str:
    suite = get_suite(settings.suite)
    tasks = suite.tasks
    matrix = suite.composition_matrix().astype(int)
    task_rows = [
        [
            i,
            f"`{t.id}`",
            f"**{t.title}**" if i == len(tasks) - 1 else t.title,
            t.instruction,
            t.success,
        ]
        for i, t in enumerate(tasks)
    ]
    mat_rows = [
        [f"`{t.id}`"] + ["✓" if v else "·" for v in row]
        for t, row in zip(tasks, matrix, strict=True)
    ]
    comp_rows = [
        [
            f"`{t.id}`",
            ", ".join(t.components.get("action", ())) or "—",
            ", ".join(t.components.get("perception", ())) or "—",
        ]
        for t in tasks
    ]
    return f"""## Tasks (curriculum order)

{_table(["#", "id", "task", "instruction", "success"], task_rows)}

## Composition matrix

Entry (i, j) is ✓ when task i reuses a component of task j along the suite's axis
(`{suite.axis}`). It is derived from the components each task declares, never typed by hand:

{_table(["task \\ reuses"] + [f"`{t.id}`" for t in tasks], mat_rows)}

{_table(["task", "action components", "perception components"], comp_rows)}{_state_text(suite)}"""


def _state_text(suite) -> str:
    """What the state observation cannot tell apart (`Suite.same_from_state`), or nothing."""
    if not suite.same_from_state:
        return ""
    return (
        f"\n\nFrom the `state` observation, {suite.same_from_state_text('`')} are one task: "
        "they differ only in colours, which the state does not hold (the same observations and "
        "rewards along the same actions). Their difference is in the images alone."
    )


def _policies_section(settings: DatasetSettings) -> str:
    suite = get_suite(settings.suite)
    refs = references().get("tasks", {})
    calibrated = settings.noise_std is None and settings.random_prob is None
    rows = []
    for t in suite.tasks:
        noise = settings.exploration(t.id)
        ref = refs.get(t.id, {})
        # Quoted only when measured with this very noise (`ccdata references`).
        rate = (
            ref.get("noisy_oracle_success_rate")
            if ref.get("noisy_oracle") == noise.to_dict()
            else None
        )
        rows.append(
            [
                f"`{t.id}`",
                noise.noise_std,
                noise.random_prob,
                "—" if rate is None else f"{rate:.2f} ({ref['episodes']} episodes)",
            ]
        )
    cut = (
        ""
        if settings.max_steps is None
        else f" Every episode was cut after at most {settings.max_steps} steps."
    )
    source = (
        "each task's calibrated noise (`TaskSpec.exploration`, found by `ccdata "
        "calibrate` so that about half of the noisy-oracle episodes succeed)"
        if calibrated
        else "noise set for every task by the generating command"
    )
    return f"""## Policies and counts

Per task: {settings.episodes} episodes of the scripted `oracle` (privileged state, phases),
and {settings.explore_episodes} episodes each of `noisy-oracle` and `random` (uniform actions).{cut}
The noisy oracle adds Gaussian noise (std `noise_std`) to each component of the oracle's action
and takes a uniform random action with probability `random_prob`, with {source}:

{_table(["task", "noise_std", "random_prob", "noisy-oracle success (reference layouts)"], rows)}

Seeds: base seed {settings.seed}. Episode `i` of a policy on a task has layout seed
`SeedSequence([base, crc32(task_id), policy_index, i])` (62 bits, the frames' `episode_seed`),
and its policy draws from `SeedSequence([episode_seed, 0x9E3779B9])`; the same settings give the
same episodes, bit for bit, with any number of workers."""


def _measured_section(measured: dict, metadata: dict) -> str:
    rows = [
        [
            f"`{r['task']}`",
            r["policy"],
            r["episodes"],
            r["steps"],
            f"{r['success_rate']:.2f}",
            f"{r['mean_return']:.2f}",
            _num(r["mean_normalized_return"], ".1f"),
        ]
        for r in measured["per_task_policy"]
    ]
    size = measured["bytes_per_1000_frames"]
    versions = ", ".join(f"{k} {v}" for k, v in metadata.get("versions", {}).items() if v)
    return f"""## Measured on this dataset

{measured["episodes"]} episodes, {measured["steps"]} steps, {measured["frames"]} frames (one
more per episode than steps: the final observation). Success rate and mean discounted return
(discount {GAMMA}) per task and policy, and the normalised return (oracle reference = 100):

{_table(["task", "policy", "episodes", "steps", "success rate", "mean return", "normalised"], rows)}

Size: {size["videos"] / 1e6:.2f} MB of video and {size["data"] / 1e6:.2f} MB of parquet per
1000 frames. Generated with {versions}."""


def _body(settings: DatasetSettings, measured: dict | None, metadata: dict | None) -> str:
    suite = get_suite(settings.suite)
    refs = references().get("tasks", {})
    ref_rows = []
    ref_steps = reference_episode_steps()  # the score's episodes, not the dataset's
    for t in suite.tasks:
        r = refs.get(t.id)
        ref_rows.append(
            [
                f"`{t.id}`",
                f"{r['mean_discounted_return']:.3f}",
                f"{r['success_rate']:.2f}",
                f"{r['median_length']:.0f}",
            ]
            if r
            else [f"`{t.id}`", "not yet measured (`ccdata references`)", "", ""]
        )
    render_lines = [f"- `{k}`: {v}" for k, v in settings.render_settings.to_dict().items()]
    video_lines = [f"- `{k}`: {v}" for k, v in VIDEO_ENCODER.items()]
    if measured is None:
        ref = REFERENCE_SIZE_PER_1000_FRAMES
        size = (
            f"Size: about {ref['videos_mb']} MB of video and {ref['data_mb']} MB of parquet "
            f"per 1000 frames at 64 px (measured on {ref['measured_on']}); a generated "
            "dataset's own card states its measured size and success rates."
        )
        measured_text = ""
    else:
        size = "Size: see *Measured on this dataset*."
        measured_text = "\n" + _measured_section(measured, metadata or {}) + "\n"
    return f"""
# {settings.repo_id}

One suite of the compositional continual-learning benchmark for world models: {len(suite.tasks)}
Meta-World (Sawyer) tasks learnt in order, the last being the **composition** of the ones
before it. Axis: {AXIS_TEXT[suite.axis]}.

{suite.description}

{_tasks_section(settings)}

## Observations, actions, rewards

- Cameras (video features, channel order for models): {", ".join(f"`{c}`" for c in CAMERAS)};
  square {settings.image_size} px, upright.
- `observation.state`: proprioception (7) = end-effector position (3), end-effector velocity
  (3), gripper opening (1). `observation.environment_state`: the 39-D privileged state
  (hand, gripper, two objects' position and quaternion, the previous frame's 18 values, goal).
- `action`: end-effector displacement (3) and gripper effort (1) in [-1, 1].
- `next.reward`: the task's dense shaped reward rescaled to [-1, 0], 0 on success;
  `next.success` ends the episode (absorbing success); `next.done` marks the step that ends it.
- Every episode ends with one more frame, marked `{FINAL_KEY}`: the observation after the
  last action (for a successful episode, the success state). It has no transition of its own:
  its `action` is zeros and `next.reward` 0 (`next.done` true, `next.success` repeats the
  episode's outcome). Keep `{FINAL_KEY} == False` to read only transitions (e.g. for behaviour
  cloning); keep it to pair every action with the observation it led to.
- {FPS} frames per second: action repeat {ACTION_REPEAT} over Meta-World's 80 Hz control,
  at most {settings.episode_steps} steps per episode.
- Per frame: `task` (the instruction), the task id's index in the suite order, the policy that
  produced the episode, and the episode's seed (replaying its actions in
  `ccdata.make_env(task_id, seed=episode_seed)` reproduces its states).

## Rendering

{chr(10).join(render_lines)}

Video encoding (chosen so a decoded frame matches the live render at PSNR >= 40 dB on every
camera; colour is what tells the tasks of perception suites apart):

{chr(10).join(video_lines)}

{size}

{_policies_section(settings)}
{measured_text}
## Oracle reference returns

Discount {GAMMA}. Normalised score = 100 (R - floor) / (oracle - floor), floor =
{floor_return(steps=ref_steps):.3f} (reward -1 for all {ref_steps} steps); not capped.

{_table(["task", "oracle mean discounted return", "success rate", "median length"], ref_rows)}

## Loading

```python
from lerobot.datasets.lerobot_dataset import LeRobotDataset
ds = LeRobotDataset("{settings.repo_id}")
frame = ds[0]  # dict of tensors: observation.images.*, observation.state, action, ...
```

```python
from datasets import load_dataset
table = load_dataset("parquet", data_files="data/*/*.parquet")  # tabular columns, no video
```

Generate it with {_command(settings)}.

## Citation

{PAPER["authors"]}. *{PAPER["title"]}*. Project page: {PAPER["url"]}
"""


def _command(settings: DatasetSettings) -> str:
    """The `ccdata generate` command that makes a dataset with these settings."""
    default = DatasetSettings(suite=settings.suite)
    render = ("shadows", "reflections", "skybox", "msaa_samples")
    if any(getattr(settings, name) != getattr(default, name) for name in render):
        return "`ccdata.record.generate` and the settings above (not all are command options)"
    flags = {
        "episodes": "--episodes",
        "explore_episodes": "--explore-episodes",
        "image_size": "--image-size",
        "seed": "--seed",
        "noise_std": "--noise-std",
        "random_prob": "--random-prob",
        "max_steps": "--max-steps",
        "episode_steps": "--episode-steps",
    }
    parts = [f"ccdata generate --suite {settings.suite}"]
    parts += [
        f"{flag} {getattr(settings, name)}"
        for name, flag in flags.items()
        if getattr(settings, name) != getattr(default, name)
    ]
    if settings.repo_id != default.repo_id:
        parts.append(f"--repo-id {settings.repo_id}")
    return "`" + " ".join(parts) + "`"
