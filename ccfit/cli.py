"""ccfit: fit world models online on the benchmark's tasks.

Example:
    ccfit train --task reach-xy --model tdmpc2 --obs state --preset smoke --out runs/smoke

Commands:
    train    online model-based RL on one task (resumes when --out holds its checkpoint)

A run directory holds config.json (the resolved config), metrics.jsonl (one line per
evaluation), tb/ (TensorBoard) and checkpoint.pt.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_USAGE = 2


class CliError(Exception):
    """A problem with the user's input: one line on stderr, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def _default_dataset(task_id: str) -> str:
    """The repo id of the first suite that contains `task_id` (ccdata's naming)."""
    from ccdata import SUITES

    for suite in SUITES.values():
        if task_id in suite.task_ids:
            return f"ccdata/{suite.name}"
    raise CliError(f"task {task_id!r} is in no suite; pass --seed-dataset SOURCE")


def _cmd_train(args: argparse.Namespace) -> None:
    from ccdata.tasks import get_task
    from ccfit.config import PRESETS, RunConfig, TrainConfig
    from ccfit.train import check_model, model_config, train_task

    try:
        get_task(args.task)
        check_model(args.model)
        if args.preset not in PRESETS:
            raise ValueError(f"unknown preset {args.preset!r}; valid: {', '.join(PRESETS)}")
        overrides = {"obs": args.obs, "seed": args.seed, "image_size": args.image_size}
        if args.steps is not None:
            overrides["steps"] = args.steps
        if args.device is not None:
            overrides["device"] = args.device
        if args.seed_dataset is not None:
            overrides["seed_dataset"] = args.seed_dataset or _default_dataset(args.task)
        train = TrainConfig.preset(args.preset, **overrides)
        mcfg = model_config(args.model, args.preset, args.obs, image_size=args.image_size)
        run = RunConfig(task=args.task, model=args.model, model_config=mcfg, train=train)
    except ValueError as e:
        raise CliError(str(e)) from None
    out = Path(args.out) if args.out else Path("runs") / f"{args.task}-{args.model}-s{args.seed}"
    try:
        record = train_task(run, out, progress=not args.quiet)
    except ValueError as e:  # e.g. another config in --out, unreadable seed dataset
        raise CliError(str(e)) from None
    norm = record["normalized_return"]
    print(
        f"{args.task} step {record['global_step']}: return {record['discounted_return']:.2f}, "
        f"normalised {'n/a' if norm is None else f'{norm:.1f}'}, "
        f"success {record['success_rate']:.2f}  ->  {out}"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ccfit", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    p = sub.add_parser("train", help="online model-based RL on one task")
    p.add_argument("--task", required=True, help="task id, e.g. reach-xy (`ccdata list`)")
    p.add_argument("--model", default="tdmpc2", help="world model (default tdmpc2)")
    p.add_argument("--obs", default="state", help="observation mode: state | pixels")
    p.add_argument("--preset", default="cpu", help="smoke | cpu | paper (default cpu)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    p.add_argument("--image-size", type=int, default=64, help="pixel mode image side")
    p.add_argument("--device", default=None, help="auto | cpu | cuda (default auto)")
    p.add_argument("--out", default=None, help="run directory (default runs/TASK-MODEL-sSEED)")
    p.add_argument(
        "--seed-dataset", nargs="?", const="", default=None, metavar="SOURCE",
        help="preload the task's episodes from a LeRobot dataset (directory or repo id; "
        "without a value: the task's suite dataset ccdata/<Suite>)",
    )  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_train)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except CliError as e:
        print(f"ccfit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("ccfit: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
