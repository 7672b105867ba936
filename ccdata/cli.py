"""ccdata: build, inspect and publish the benchmark's task suites and datasets.

Example:
    ccdata generate --suite PnPBoxClose

Commands:
    list          suites, tasks and composition matrices
    render        the three camera views of a task (PNG) and optionally an oracle episode (MP4)
    references    regenerate the reference measurements (oracle returns, noisy-oracle success)
    calibrate     find each task's noisy-oracle noise (about half of its episodes succeed)
    generate      roll out oracle and exploration policies into one LeRobot v3 dataset per suite
                  (here, or as SLURM jobs with --launcher slurm)
    card          render a suite's default dataset card, or a generated dataset's own card
    verify        check a dataset end to end (exit 1 with findings)
    push          upload a dataset and its card to a Hugging Face Hub compatible endpoint
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ccdata.cli_generate import SLURM_TIME, run_generate
from ccdata.errors import (
    EXIT_USAGE,
    CliError,
    InputError,
    OneLineParser,
    add_command,
    stdout_closed,
    stdout_reader_gone,
)
from ccdata.slurm import add_options as add_slurm_options

EXIT_FINDINGS = 1


def _cmd_list(args: argparse.Namespace) -> None:
    import ccdata

    suites = [ccdata.get_suite(args.suite)] if args.suite else list(ccdata.SUITES.values())
    for suite in suites:
        print(f"{suite.name}  (axis: {suite.axis})  {suite.description}")
        matrix = suite.composition_matrix()
        width = max(len(t.id) for t in suite.tasks)
        for i, task in enumerate(suite.tasks):
            marks = " ".join("x" if m else "." for m in matrix[i])
            role = "composition" if i == len(suite.tasks) - 1 else "primitive"
            print(f"  {i}  {task.id:<{width}}  [{marks}]  {role}: {task.title}")
        if suite.same_from_state:
            same = suite.same_from_state_text()
            print(f"  from state, {same} are one task (only colours differ)")
        print()


def _cmd_render(args: argparse.Namespace) -> None:
    import numpy as np

    import ccdata
    from ccdata.policies import make_policy
    from ccdata.render import write_mp4, write_png

    env = ccdata.make_env(args.task, seed=args.seed, image_size=args.image_size)
    obs, _ = env.reset()
    frame = env.render()
    out = Path(args.out)
    write_png(out, frame)
    print(f"wrote {out} ({' | '.join(ccdata.CAMERAS)})")
    if args.video:
        policy = make_policy("oracle", args.task, seed=args.seed)
        policy.reset()
        frames = [frame]
        done = False
        while not done:
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            frames.append(env.render())
            done = terminated or truncated
        write_mp4(Path(args.video), np.stack(frames), fps=ccdata.env.FPS)
        print(f"wrote {args.video} ({len(frames)} frames, oracle, success={terminated})")
    env.close()


def _cmd_references(args: argparse.Namespace) -> None:
    from ccdata.references import write_references

    out = None if args.in_place else Path(args.out)
    path = write_references(tasks=args.task or None, episodes=args.episodes, path=out)
    print(f"wrote {path}")


def _dataset_root(args: argparse.Namespace) -> Path:
    """The dataset directory of --root, else of --suite; CliError if it holds no dataset."""
    from ccdata.settings import suite_dataset_root

    if args.root:
        root = Path(args.root)
    elif args.suite is None:
        raise CliError("give --suite or --root")
    else:
        root = suite_dataset_root(args.suite)
    if not (root / "meta/info.json").is_file():
        fix = "" if args.root else f": run `ccdata generate --suite {args.suite}` first"
        raise CliError(f"no dataset at {root} (no meta/info.json){fix}")
    return root


def _cmd_card(args: argparse.Namespace) -> None:
    from ccdata.cards import render_card

    if args.root:
        from ccdata.dataset_format import read_ccdata_metadata
        from ccdata.settings import DatasetSettings
        from ccdata.verify import check_intact

        root = _dataset_root(args)
        meta = read_ccdata_metadata(root)
        check_intact(root, "its card cannot be written")  # the card reads every episode
        settings = DatasetSettings.from_dict({**meta["config"], "root": args.root})
        text = render_card(settings, dataset=root, metadata=meta)
    elif args.suite:
        text = render_card(args.suite)
    else:
        raise CliError("give --suite (the default card) or --root (a dataset's card)")
    if args.out:
        if Path(args.out).is_dir():
            raise CliError(f"--out {args.out} is a directory: name the card's file")
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        sys.stdout.write(text)


def _cmd_calibrate(args: argparse.Namespace) -> None:
    from ccdata.calibration import calibrate, level_of
    from ccdata.tasks import TASKS, get_task

    tasks = args.task or list(TASKS)
    found = {}
    for task_id in tasks:
        refine = (
            {"start": level_of(get_task(task_id).exploration), "step": 1.5} if args.refine else {}
        )
        noise, rate, _ = calibrate(
            task_id,
            target=args.target,
            episodes=args.episodes,
            iterations=args.iterations,
            tolerance=args.tolerance,
            **refine,
            on_step=lambda r: print(json.dumps(r), file=sys.stderr, flush=True),
        )
        found[task_id] = {**noise.to_dict(), "success_rate": rate, "episodes": args.episodes}
        print(
            f"{task_id}: ExplorationNoise(noise_std={noise.noise_std}, "
            f"random_prob={noise.random_prob})  success {rate:.2f}",
            flush=True,
        )
    if args.json:
        print(json.dumps(found, indent=2))


def _cmd_verify(args: argparse.Namespace) -> int:
    from ccdata.verify import verify_dataset

    root = _dataset_root(args)
    findings = verify_dataset(root)
    if findings:
        print(f"{root}: {len(findings)} problem(s)")
        for f in findings:
            print(f"  - {f}")
        return EXIT_FINDINGS
    print(f"{root}: OK")
    return 0


def _cmd_push(args: argparse.Namespace) -> None:
    from ccdata.hub import push_dataset

    root = _dataset_root(args)
    url = push_dataset(root, args.repo_id, endpoint=args.endpoint, private=args.private)
    print(f"pushed {root} -> {url}")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="ccdata", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    p = add_command(
        sub, "list", "suites, tasks and composition matrices", "ccdata list --suite Grasp"
    )
    p.add_argument("--suite")
    p.set_defaults(func=_cmd_list)

    p = add_command(sub, "render", "render a task's three views (PNG) and an episode (MP4)",
                    "ccdata render --task stack-blocks --out views.png "
                    "--video episode.mp4")  # fmt: skip
    p.add_argument("--task", required=True)
    p.add_argument("--out", required=True, help="PNG file for the first frame")
    p.add_argument("--video", help="also write an oracle episode as MP4")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, default=128)
    p.set_defaults(func=_cmd_render)

    p = add_command(sub, "references", "regenerate the reference measurements into --out "
                    "(or, with --in-place, the package's references.json, which normalised "
                    "scores read)",
                    "ccdata references --task reach-xy --episodes 5 --out refs.json")  # fmt: skip
    p.add_argument("--task", action="append", help="only these tasks (repeatable)")
    p.add_argument("--episodes", type=int, default=50)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", help="write the references here (a JSON file, added to if it "
                       "holds references)")  # fmt: skip
    where.add_argument("--in-place", action="store_true",
                       help="rewrite the installed package's own references.json (a maintainer "
                       "updating the published references)")  # fmt: skip
    p.set_defaults(func=_cmd_references)

    p = add_command(sub, "calibrate", "find each task's noisy-oracle noise (prints it)",
                    "ccdata calibrate --task reach-xy --episodes 10 --iterations 2")  # fmt: skip
    p.add_argument("--task", action="append", help="only these tasks (repeatable)")
    p.add_argument("--episodes", type=int, default=40, help="episodes per evaluation")
    p.add_argument("--target", type=float, default=0.5, help="noisy-oracle success rate")
    p.add_argument("--iterations", type=int, default=8, help="evaluations at most, per task")
    p.add_argument("--tolerance", type=float, default=0.1, help="accepted |rate - target|")
    p.add_argument(
        "--refine",
        action="store_true",
        help="start from each task's current calibration, in smaller steps",
    )
    p.add_argument("--json", action="store_true", help="also print the results as JSON")
    p.set_defaults(func=_cmd_calibrate)

    p = add_command(
        sub, "generate", "generate a suite's LeRobot dataset", "ccdata generate --suite PnPBoxClose"
    )
    p.add_argument("--suite", required=True)
    p.add_argument("--episodes", type=int, default=50, help="oracle episodes per task")
    p.add_argument(
        "--explore-episodes", type=int, default=25, help="per task and exploration policy"
    )
    p.add_argument("--image-size", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--max-steps",
        type=int,
        help="cut episodes after this many steps (tests, previews; default: full)",
    )
    p.add_argument(
        "--episode-steps",
        type=int,
        help="agent steps after which the environment ends an unsolved episode "
        "(default: the benchmark's 250)",
    )
    p.add_argument(
        "--workers",
        type=int,
        help="rollout processes (default: one per core this process may use); the "
        "episodes are identical with any number of workers",
    )
    p.add_argument("--root", help="dataset directory (default: LeRobot's cache for the repo id)")
    p.add_argument("--repo-id", help="default ccdata/<Suite>")
    p.add_argument(
        "--noise-std",
        type=float,
        help="noisy-oracle noise std for every task (default: each task's calibration)",
    )
    p.add_argument(
        "--random-prob",
        type=float,
        help="noisy-oracle random-action probability for every task (default: "
        "each task's calibration)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument(
        "--launcher",
        choices=("local", "slurm"),
        default="local",
        help="local: processes here (default); slurm: a job array of shards, then a "
        "merge job (returns at once; needs sbatch and sacct)",
    )
    g = p.add_argument_group("with --launcher slurm")
    g.add_argument("--shards", type=int, help="array tasks to split the episodes into (1)")
    add_slurm_options(g, default_time=SLURM_TIME)
    g.add_argument(
        "--log-dir",
        help="submitit logs, on a filesystem the nodes share "
        "(default: .<name>.ccdata-logs beside the dataset)",
    )
    p.set_defaults(func=run_generate)

    p = add_command(sub, "card", "render a suite's default card or a dataset's own card",
                    "ccdata card --suite PnPBoxClose")  # fmt: skip
    p.add_argument("--suite", help="the suite's default card (cards/<Suite>.md)")
    p.add_argument("--root", help="the card of the dataset in this directory")
    p.add_argument("--out")
    p.set_defaults(func=_cmd_card)

    p = add_command(sub, "verify", "check a dataset end to end (exit 1 with findings)",
                    "ccdata verify --suite PnPBoxClose")  # fmt: skip
    p.add_argument("--suite")
    p.add_argument("--root")
    p.set_defaults(func=_cmd_verify)

    p = add_command(sub, "push", "upload a dataset to a Hub-compatible endpoint",
                    "ccdata push --suite PnPBoxClose --repo-id ORG/PnPBoxClose")  # fmt: skip
    p.add_argument("--suite", help="the suite's dataset in LeRobot's cache")
    p.add_argument("--repo-id", required=True)
    p.add_argument("--endpoint", help="default: HF_ENDPOINT or the public hub")
    p.add_argument("--root", help="local dataset directory (default: from the suite)")
    p.add_argument("--private", action="store_true")
    p.set_defaults(func=_cmd_push)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from ccdata.hub import HubError

    try:
        code = args.func(args)
        sys.stdout.flush()  # here, so that a reader gone (`| head`) is caught below
    except (CliError, HubError, InputError, FileNotFoundError, FileExistsError) as err:
        print(f"ccdata {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"ccdata {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        if not stdout_reader_gone():
            raise  # a pipe of the program's own broke: a bug, its traceback shows
        return stdout_closed()
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
