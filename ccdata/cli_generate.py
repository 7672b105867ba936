"""`ccdata generate` behind its parser (`ccdata.cli`): its settings from the command line,
the run here or its submission to SLURM, and the summary table it prints."""

from __future__ import annotations

import argparse
import dataclasses
import json

from ccdata.cli_options import field_values
from ccdata.errors import CliError
from ccdata.slurm import OPTIONS as SLURM_OPTIONS

GENERATE_FIELDS = ("suite", "episodes", "explore_episodes", "image_size", "seed", "max_steps",
                   "episode_steps", "workers", "root", "repo_id", "noise_std",
                   "random_prob")  # fmt: skip
"""The fields of `GenerateConfig` that `generate` takes as options (`--explore-episodes`), their
defaults and help the fields' own; the render's look (shadows, ...) stays the benchmark's."""
GENERATE_UNSET = {"workers": "one per core this process may use; the episodes are identical "
                             "with any number of workers"}  # fmt: skip
"""What `generate` decides where its option is not given, unlike the field's default."""


def generate_config(args: argparse.Namespace):
    """The GenerateConfig of a parsed `generate` command line, its launch options checked."""
    from ccdata.processes import available_cores
    from ccdata.record import GenerateConfig

    if args.launcher == "local":
        given = [f"--{k.replace('_', '-')}" for k in SLURM_FLAGS if getattr(args, k) is not None]
        if given:
            raise CliError(f"{', '.join(given)} need --launcher slurm (locally: --workers)")
    elif args.workers is not None:  # None: not given
        raise CliError("--workers is for --launcher local; with slurm use --shards")
    values = field_values(args, GENERATE_FIELDS)
    if values["workers"] is None:
        values["workers"] = available_cores()
    return GenerateConfig(**values)


def run_generate(args: argparse.Namespace) -> None:
    """`ccdata generate`: here, or as SLURM jobs (`--launcher slurm`)."""
    from ccdata.record import generate

    config = generate_config(args)
    if args.launcher == "slurm":
        return _submit_slurm(args, config)
    path, summary = generate(config)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    print(f"dataset: {path}")


SLURM_FLAGS = ("shards", "log_dir", *SLURM_OPTIONS)
"""`generate` options that only mean something with `--launcher slurm`."""
SLURM_TIME = "60"
"""`generate`'s time limit per job when `--time` is not given."""


def _submit_slurm(args: argparse.Namespace, config) -> None:
    from ccdata.launch import submit_generation
    from ccdata.slurm import settings_from_options

    slurm = settings_from_options(args, SLURM_TIME, shards=args.shards, log_dir=args.log_dir)
    sub = submit_generation(config, slurm)
    if args.json:
        print(json.dumps(dataclasses.asdict(sub), indent=2))
        return
    if sub.merge_job is None:
        print(f"nothing to submit: {sub.root} already holds every planned episode")
        return
    if sub.array_job:
        tasks = len(sub.shards)
        episodes = sum(len(k) for k in sub.shards.values())
        print(
            f"submitted {tasks} shard(s) with {episodes} episode(s) to write: job array "
            f"{sub.array_job} (shards {', '.join(map(str, sub.shards))})"
        )
    else:
        print("every episode is written; submitted the merge only")
    after = f" (starts after array {sub.array_job} ends)" if sub.array_job else ""
    print(f"merge job {sub.merge_job}{after} -> {sub.root}")
    print(f"logs: {sub.log_dir}  (code: {sub.code})")
    ids = ",".join(j for j in (sub.array_job, sub.merge_job) if j)
    print(
        f"follow: squeue -j {ids}; sacct -j {ids}; if the merge fails, run the same command again"
    )


SUMMARY_COLUMNS = (
    # key in a summary row, header, width, number format
    ("task", "task", -18, ""),
    ("policy", "policy", -13, ""),
    ("episodes", "episodes", 8, "d"),
    ("steps", "steps", 8, "d"),
    ("frames", "frames", 8, "d"),
    ("success_rate", "success", 8, ".2f"),
    ("mean_normalized_return", "norm.ret", 9, ".1f"),
    ("wall_time_s", "wall s", 8, ".1f"),
    ("frames_per_s", "frames/s", 9, ".1f"),
)


def _cell(value, width: int, number: str) -> str:
    text = "-" if value is None else format(value, number)
    return text.ljust(-width) if width < 0 else text.rjust(width)


def format_summary(summary: dict) -> str:
    """The per task and policy table of `ccdata generate`, then the run's totals."""
    lines = ["  ".join(_cell(title, w, "") for _, title, w, _ in SUMMARY_COLUMNS)]
    for row in summary["per_task_policy"]:
        lines.append("  ".join(_cell(row[k], w, n) for k, _, w, n in SUMMARY_COLUMNS))
    fps = summary["frames_per_s"]
    lines.append(
        f"{summary['episodes']} episodes, {summary['steps']} steps, {summary['frames']} frames "
        "(with each episode's final observation); this run: "
        f"{summary['new_episodes']} new episodes in {summary['wall_time_s'] or 0:.1f} s"
        + (f" ({fps:.1f} frames/s)" if fps else "")
    )
    return "\n".join(lines)
