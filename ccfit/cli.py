"""ccfit: fit world models online on the benchmark's tasks.

Example:
    ccfit train --task reach-xy --model tdmpc2 --obs state --preset smoke --out runs/smoke

Commands:
    train    online model-based RL on one task (resumes when --out holds its checkpoint)
    run      a suite's continual curriculum (Algorithm 1) with one method; writes metrics.json
    report   tables and plots over run directories (BWT / FWT per backbone, suite, method)
    ablate   a finished PWM run's expert ablation on the composition task (the paper's Fig. 6)
    pretrain-encoder   the frozen-encoder diagnostic: an autoencoder on every task's oracle
             episodes, saved for `ccfit run --obs pixels --encoder frozen:PATH`

    ccfit run --suite Reach --model tdmpc2 --method packnet --obs state --preset cpu --seed 0
    ccfit report runs/ --out report/

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
        if args.endpoint is not None:
            overrides["dataset_endpoint"] = args.endpoint
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


def _parse_options(items: list[str]) -> dict:
    """KEY=VALUE pairs; values parsed as JSON when they can be (numbers, booleans)."""
    import json

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise CliError(f"expected KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def run_config(args: argparse.Namespace):
    """The `CurriculumConfig` of parsed `ccfit run` arguments (ValueError/CliError if bad)."""
    from ccfit.curriculum import CurriculumConfig

    seed_dataset = {"auto": "auto", "none": None}.get(args.seed_dataset, args.seed_dataset)
    model_overrides = _parse_options(args.model_option)
    if args.router is not None:
        if args.model != "pwm":
            raise CliError("--router needs --model pwm (TD-MPC2 has no router)")
        if model_overrides.get("router", args.router) != args.router:
            raise CliError(f"--router {args.router} contradicts --model-option "
                           f"router={model_overrides['router']}")  # fmt: skip
        model_overrides["router"] = args.router
    return CurriculumConfig(
        suite=args.suite, model=args.model, method=args.method, preset=args.preset,
        obs=args.obs, seed=args.seed, image_size=args.image_size, encoder=args.encoder,
        seed_dataset=seed_dataset, method_options=_parse_options(args.method_option),
        model_overrides=model_overrides,
        train_overrides={**_parse_options(args.train), **(
            {"dataset_endpoint": args.endpoint} if args.endpoint else {})},
    )  # fmt: skip


def _cmd_run(args: argparse.Namespace) -> None:
    from ccfit.curriculum import Curriculum

    try:
        cfg = run_config(args)
        out = Path(args.out) if args.out else (
            Path("runs") / f"{args.suite}-{args.model}-{args.method}-{args.obs}-{args.preset}"
            f"-s{args.seed}"
        )  # fmt: skip
        result = Curriculum(cfg, out, args.scratch_root, progress=not args.quiet).run()
    except (ValueError, TypeError) as e:
        raise CliError(str(e)) from None

    def fmt(x):
        return "n/a" if x is None else f"{x:.2f}"

    print(f"{cfg.suite} {cfg.model} {cfg.method} seed {cfg.seed}: BWT {fmt(result['bwt'])}, "
          f"FWT {fmt(result['fwt'])}  ->  {out}")  # fmt: skip


def _cmd_report(args: argparse.Namespace) -> None:
    from ccfit.report import write_report

    try:
        paths = write_report([Path(p) for p in args.runs], Path(args.out))
    except ValueError as e:
        raise CliError(str(e)) from None
    for path in paths:
        print(path)


def _cmd_ablate(args: argparse.Namespace) -> None:
    from ccfit.analysis import ABLATION_JSON, ABLATION_PNG, ablate

    run = Path(args.run)
    try:
        result = ablate(run, episodes=args.episodes, horizon=args.horizon)
    except (ValueError, TypeError) as e:
        raise CliError(str(e)) from None

    def fmt(x):
        return "n/a" if x is None else f"{x:.2f}"

    for name, m in result["modes"].items():
        print(f"{name:8s} return x{fmt(m['return_ratio'])} (normalised "
              f"{fmt(m['normalized_return'])}), latent error x{fmt(m['latent_error_ratio'])}")
    print(f"-> {run / ABLATION_JSON}, {run / ABLATION_PNG}")


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
    p.add_argument("--endpoint", default=None,
                   help="Hub endpoint to download a repo-id seed dataset from (as ccdata push)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("run", help="a suite's continual curriculum (Algorithm 1)")
    p.add_argument("--suite", required=True, help="suite name (`ccdata list`)")
    p.add_argument("--model", default="tdmpc2", help="tdmpc2 | pwm")
    p.add_argument("--method", default="ft", help="ft | er | ewc | packnet | experts (PWM)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--preset", default="cpu", help="smoke | cpu | paper (default cpu)")
    p.add_argument("--obs", default="state", help="state | pixels (default state)")
    p.add_argument("--image-size", type=int, default=64)
    p.add_argument("--encoder", default=None, help="frozen:PATH, a pretrained encoder")
    p.add_argument("--seed-dataset", default="auto",
                   help="auto (the suite's dataset when present) | none | SOURCE")  # fmt: skip
    p.add_argument("--method-option", action="append", default=[], metavar="KEY=VALUE",
                   help="method setting, e.g. lam=5000 (EWC), fraction=0.05 (ER)")  # fmt: skip
    p.add_argument("--router", default=None, choices=("task", "state"),
                   help="PWM's router input: the task identity (default, as the paper) or the "
                   "latent and action (same as --model-option router=state)")  # fmt: skip
    p.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                   help="model config override, e.g. router=state (PWM)")  # fmt: skip
    p.add_argument("--train", action="append", default=[], metavar="KEY=VALUE",
                   help="TrainConfig override, e.g. steps=5000")  # fmt: skip
    p.add_argument("--endpoint", default=None,
                   help="Hub endpoint to download a repo-id seed dataset from (as ccdata push)")
    p.add_argument("--out", default=None, help="run directory")
    p.add_argument("--scratch-root", default=None,
                   help="where from-scratch reference runs are shared (default OUT/../scratch)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run)

    from ccfit.pretrain import add_pretrain_parser

    add_pretrain_parser(sub)

    p = sub.add_parser("report", help="tables and plots over run directories")
    p.add_argument("runs", nargs="+", help="run directories (or folders holding them)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("ablate", help="expert ablation of a finished PWM run (prior / new / "
                       "uniform routing on the composition task)")  # fmt: skip
    p.add_argument("run", help="run directory of a finished `ccfit run --model pwm` curriculum")
    p.add_argument("--episodes", type=int, default=None,
                   help="evaluation layouts (default: the run's eval_episodes)")  # fmt: skip
    p.add_argument("--horizon", type=int, default=None,
                   help="open-loop prediction steps (default: the model's horizon)")  # fmt: skip
    p.set_defaults(func=_cmd_ablate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except (CliError, ValueError) as e:
        print(f"ccfit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("ccfit: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
