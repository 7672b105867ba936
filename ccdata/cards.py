"""Dataset cards: one Markdown card per suite, checked in as cards/<Suite>.md and shipped as the
dataset's README.md. The card is a pure function of the package (suites, tasks, render and
generation defaults, oracle references), so regenerating it is reproducible.
"""

from __future__ import annotations

import dataclasses

from ccdata.env import ACTION_REPEAT, EPISODE_STEPS, FPS
from ccdata.render import CAMERAS, RenderSettings
from ccdata.scoring import GAMMA, floor_return, references
from ccdata.suites import get_suite

PAPER = {
    "title": "Benchmarking World Models for Continual Learning on Compositional Tasks",
    "authors": "Haoyu Zhou, Joe Watson, Anson Lei, Ingmar Posner",
    "url": "https://object814.github.io/Compositional-Continual-Learning/",
}

SIZE_PER_1000_FRAMES = {"videos_mb": 4.2, "data_mb": 0.20}
"""Dataset size per 1000 frames at 64 px with the video settings below, measured by
`bench/dataset_write.py` (Grasp suite, all three policies)."""

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


def _generation_defaults():
    from ccdata.dataset_format import VIDEO_ENCODER
    from ccdata.record import GenerateConfig

    fields = {f.name: f.default for f in dataclasses.fields(GenerateConfig)}
    return fields, VIDEO_ENCODER


def render_card(suite_name: str) -> str:
    suite = get_suite(suite_name)
    tasks = suite.tasks
    matrix = suite.composition_matrix().astype(int)
    gen, video = _generation_defaults()
    refs = references().get("tasks", {})
    settings = RenderSettings(image_size=gen.get("image_size", 64))
    repo_id = f"ccdata/{suite.name}"

    header = "\n".join(
        [
            "---",
            "license: mit",
            "task_categories:",
            "- robotics",
            "tags:",
            _yaml_list(
                ["LeRobot", "metaworld", "continual-learning", "world-models", suite.name],
                indent=0,
            ),
            "configs:",
            "- config_name: default",
            "  data_files: data/*/*.parquet",
            "ccdata:",
            f"  suite: {suite.name}",
            f"  axis: {suite.axis}",
            "  tasks:",
            _yaml_list([t.id for t in tasks], indent=2),
            "  composition_matrix:",
            _yaml_list([str(list(map(int, row))) for row in matrix], indent=2),
            "---",
        ]
    )

    task_rows = ["| # | id | task | instruction | success |", "|---|---|---|---|---|"]
    for i, t in enumerate(tasks):
        name = f"**{t.title}**" if i == len(tasks) - 1 else t.title
        task_rows.append(f"| {i} | `{t.id}` | {name} | {t.instruction} | {t.success} |")

    mat_rows = ["| task \\ reuses | " + " | ".join(f"`{t.id}`" for t in tasks) + " |"]
    mat_rows.append("|---" * (len(tasks) + 1) + "|")
    for t, row in zip(tasks, matrix, strict=True):
        mat_rows.append(f"| `{t.id}` | " + " | ".join("✓" if v else "·" for v in row) + " |")

    comp_rows = ["| task | action components | perception components |", "|---|---|---|"]
    for t in tasks:
        comp_rows.append(
            f"| `{t.id}` | {', '.join(t.components.get('action', ())) or '—'} | "
            f"{', '.join(t.components.get('perception', ())) or '—'} |"
        )

    ref_rows = ["| task | oracle mean discounted return | success rate | median length |"]
    ref_rows.append("|---|---|---|---|")
    for t in tasks:
        r = refs.get(t.id)
        if r:
            ref_rows.append(
                f"| `{t.id}` | {r['mean_discounted_return']:.3f} | {r['success_rate']:.2f} | "
                f"{r['median_length']:.0f} |"
            )
        else:
            ref_rows.append(f"| `{t.id}` | not yet generated (`ccdata references`) | | |")

    render_lines = [f"- `{k}`: {v}" for k, v in settings.to_dict().items()]
    video_lines = [f"- `{k}`: {v}" for k, v in video.items()]

    body = f"""
# ccdata/{suite.name}

One suite of the compositional continual-learning benchmark for world models: {len(tasks)}
Meta-World (Sawyer) tasks learnt in order, the last being the **composition** of the ones
before it. Axis: {AXIS_TEXT[suite.axis]}.

{suite.description}

## Tasks (curriculum order)

{chr(10).join(task_rows)}

## Composition matrix

Entry (i, j) is ✓ when task i reuses a component of task j along the suite's axis
(`{suite.axis}`). It is derived from the components each task declares, never typed by hand:

{chr(10).join(mat_rows)}

{chr(10).join(comp_rows)}

## Observations, actions, rewards

- Cameras (video features, channel order for models): {", ".join(f"`{c}`" for c in CAMERAS)};
  square {settings.image_size} px, upright.
- `observation.state`: proprioception (7) = end-effector position (3), end-effector velocity
  (3), gripper opening (1). `observation.environment_state`: the 39-D privileged state
  (hand, gripper, two objects' position and quaternion, the previous frame's 18 values, goal).
- `action`: end-effector displacement (3) and gripper effort (1) in [-1, 1].
- `next.reward`: the task's dense shaped reward rescaled to [-1, 0], 0 on success;
  `next.success` ends the episode (absorbing success); `next.done` marks the last frame.
- {FPS} frames per second: action repeat {ACTION_REPEAT} over Meta-World's 80 Hz control,
  at most {EPISODE_STEPS} steps per episode.
- Per frame: `task` (the instruction), the task id's index in the suite order, the policy that
  produced the episode, and the episode's seed (replaying its actions in
  `ccdata.make_env(task_id, seed=episode_seed)` reproduces its states).

## Rendering

{chr(10).join(render_lines)}

Video encoding (chosen so a decoded frame matches the live render at PSNR >= 40 dB on every
camera; colour is what tells the tasks of perception suites apart):

{chr(10).join(video_lines)}

Size: about {SIZE_PER_1000_FRAMES["videos_mb"]} MB of video and
{SIZE_PER_1000_FRAMES["data_mb"]} MB of parquet per 1000 frames (64 px, three cameras).

## Policies and counts

Per task: {gen.get("episodes")} episodes of the scripted `oracle` (privileged state, phases),
and {gen.get("explore_episodes")} episodes each of `noisy-oracle` (oracle + Gaussian noise,
std {gen.get("noise_std")}, and a uniform random action with probability
{gen.get("random_prob")}) and `random` (uniform). Generate with
`ccdata generate --suite {suite.name}`.

## Oracle reference returns

Discount {GAMMA}. Normalised score = 100 (R - floor) / (oracle - floor), floor =
{floor_return():.3f} (reward -1 for all {EPISODE_STEPS} steps); not capped.

{chr(10).join(ref_rows)}

## Loading

```python
from lerobot.datasets.lerobot_dataset import LeRobotDataset
ds = LeRobotDataset("{repo_id}")
frame = ds[0]  # dict of tensors: observation.images.*, observation.state, action, ...
```

```python
from datasets import load_dataset
table = load_dataset("parquet", data_files="data/*/*.parquet")  # tabular columns, no video
```

## Citation

{PAPER["authors"]}. *{PAPER["title"]}*. Project page: {PAPER["url"]}
"""
    return header + "\n" + body
