r"""ccfit: fit world models on the benchmark's tasks, online (model-based RL) or offline.

Example:
    ccfit train --task reach-xy --preset smoke --out runs/smoke

Commands:
    train    online model-based RL on one task (resumes when --out holds its checkpoint;
             a finished one with a larger --train.steps is extended)
    run      a suite's continual curriculum (Algorithm 1) with one method; writes metrics.json
    fit      the offline track: the backbone fitted on the suite's dataset task after task with
             one method, scored by open-loop prediction on held-out episodes; metrics.json
    sweep    a grid of runs (suites x models x methods x seeds), locally or on SLURM, and the
             report over them; again: submits only unfinished work; --status RUNS
    report   tables and plots over run directories (BWT / FWT per backbone, suite, method);
             `ccfit report results/` rewrites the results page over every published run
    compare  whether run B reproduces run A's records, and what differs between them
    publish  finished runs' small files (config, metrics, cost) and the report over them (the
             learnability tables over single-task runs), for a results folder under version
             control
    learnability   steps each task needs (single-task runs) and the per-suite budgets
    ablate   a finished routed-model run's expert ablation on the composition task (Fig. 6)
    probe-encoder   whether a frozen encoder's latent gives each task's hand, objects and goal,
             and which of the tasks that are one from state (a colour apart) a frame shows
    pretrain-encoder   the frozen-encoder diagnostic: the pixel encoder trained on every task's
             episodes (reconstruction and an episode-contrastive term), saved for
             `ccfit run --obs pixels --encoder frozen:PATH`

    ccfit run --suite Reach --preset cpu --seed 0 --method.type=ewc --method.lam=5000 \
        --train.steps=6000 [--model.type=NAME --model.FIELD=VALUE ...]
    ccfit run --config_path runs/X/config.json      # a saved config, run (or resumed) again
    ccfit run --suite Grasp --method.type=er --keep-stages --out runs/er   # keeps each task's state
    ccfit run --suite Grasp --method.type=er --method.replay_ratio=0 --out runs/er-off \
        --branch-from runs/er --branch-after 2      # runs/er up to task 2, no replay after it
    ccfit report runs/ --out report/

`train` and `run` take the typed config tree (`ccfit run --help` lists every field with its
meaning); a preset fills the defaults and flags override them. A run directory holds
config.json (the resolved config), metrics.jsonl (one line per evaluation), tb/ (TensorBoard)
and checkpoints.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

from ccdata.errors import (
    EXIT_USAGE,
    InputError,
    OneLineParser,
    add_command,
    stdout_closed,
    stdout_reader_gone,
)


class CliError(Exception):
    """A problem with the user's input: one line on stderr, exit 2."""


@dataclass(frozen=True)
class Flag:
    """An option of `train`, `run` or `fit` outside the config tree (read with its options,
    kept out of the config): where shared work goes, what is kept, where a branch starts."""

    value: str | None
    """What the option takes, as help shows it (`DIR`); None: it takes no value."""
    help: str


QUIET = {"quiet": Flag(None, "no progress bars")}
SCRATCH_ROOT = {
    "scratch_root": Flag("DIR", "where the from-scratch references (FWT's baselines) are kept "
                         "and shared by runs of equal settings (default: scratch/ beside the "
                         "run's folder)"),
}  # fmt: skip
BRANCHING = {
    "keep_stages": Flag(None, "keep the state after each task too (stages/after-K.pt), for "
                        "runs that branch off this one"),
    "branch_from": Flag("RUN", "start as RUN up to task K (--branch-after K; RUN kept its "
                        "stages) and go on from there with this command's options"),
    "branch_after": Flag("K", "the tasks taken from --branch-from's run"),
}  # fmt: skip


def _parse_config(cls, argv: list[str], prog: str, flags: dict[str, Flag]):
    """The config of a config command and its other options (`flags`, and `config_path` when
    given), from one reading of `argv`; its --help lists both."""
    from ccfit.config_argv import asks_for_help, missing_value, read_argv
    from ccfit.config_parse import parse_options, print_help

    switches = {key: flag.value for key, flag in flags.items()}
    if asks_for_help(argv):
        try:
            print_help(cls, argv, prog, switches)  # the config tree's help
        except SystemExit:
            print(f"\n{prog}'s options outside the config tree:")
            for key, flag in flags.items():
                spelt = "--" + key.replace("_", "-") + (f" {flag.value}" if flag.value else "")
                print(textwrap.fill(flag.help, 80, initial_indent=f"  {spelt:22s}",
                                    subsequent_indent=" " * 24))  # fmt: skip
            raise
    options = read_argv(argv, switches)
    extra = {key: options.pop(key) for key in flags if key in options}
    for key, value in extra.items():
        if value is None:
            raise missing_value(key.replace("_", "-"), flags[key].value)
    cfg = parse_options(cls, options, prog)
    return cfg, {**extra, "config_path": options.get("config_path")}


def _check_seed_dataset_as_run(cfg, suite: str | None, config_path: str | None, out: Path):
    """A run made again from a saved config.json (`config_path`) into `out` seeds from the
    dataset it had (or stops). Where `out` already holds a run, it is resumed, and its own
    config.json is the judge (`check_saved_config`: another dataset content there is a note)."""
    from ccfit.config_parse import given_config_file
    from ccfit.train.run import CONFIG, check_seed_dataset_as_run

    given = given_config_file(config_path)
    if given is not None and not (out / CONFIG).is_file():
        check_seed_dataset_as_run(cfg, suite, *given)


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def cmd_train(argv: list[str]) -> None:
    """ccfit train --task reach-xy --preset smoke --out runs/smoke  (see --help)"""
    from ccfit.config import TaskRunConfig
    from ccfit.train.run import default_out, suite_of, train_single

    cfg, extra = _parse_config(TaskRunConfig, argv, "ccfit train", QUIET)
    out = Path(cfg.out or default_out(cfg))
    _check_seed_dataset_as_run(cfg, suite_of(cfg.task), extra["config_path"], out)
    record = train_single(cfg, progress=not extra.get("quiet"))
    norm = record["normalized_return"]
    print(
        f"{cfg.task} step {record['global_step']}: return {record['discounted_return']:.2f}, "
        f"normalised {'n/a' if norm is None else f'{norm:.1f}'}, "
        f"success {record['success_rate']:.2f}  ->  {cfg.out or default_out(cfg)}"
    )


def run_dir(cfg) -> Path:
    """Where a curriculum run goes: `--out`, else a name made from its config."""
    from ccfit.run_files import run_name

    if cfg.out:
        return Path(cfg.out)
    return Path("runs") / run_name(cfg)


def cmd_run(argv: list[str]) -> None:
    """ccfit run --suite Reach --preset cpu --method.type=packnet  (see --help)"""
    from ccfit.analysis import stage_callbacks
    from ccfit.config import CurriculumConfig
    from ccfit.config_parse import curriculum_notes
    from ccfit.curriculum import Curriculum

    flags = QUIET | SCRATCH_ROOT | BRANCHING
    cfg, extra = _parse_config(CurriculumConfig, argv, "ccfit run", flags)
    out = run_dir(cfg)
    _check_seed_dataset_as_run(cfg, cfg.suite, extra["config_path"], out)
    # Made before the notes: a run whose start refuses it (its encoder file) says one line.
    curriculum = Curriculum(
        cfg,
        out,
        extra.get("scratch_root") or None,
        progress=not extra.get("quiet"),
        callbacks=stage_callbacks(cfg),
        keep_stages=bool(extra.get("keep_stages")),
        branch=_branch(extra),
    )
    for note in curriculum_notes(cfg.to_dict()):
        print(f"ccfit run: note: {note}", file=sys.stderr)
    result = curriculum.run()
    print(
        f"{cfg.suite} {cfg.model.type} {cfg.method.type} seed {cfg.seed}: "
        f"BWT {_fmt(result['bwt'])}, FWT {_fmt(result['fwt'])}  ->  {out}"
    )


def _branch(extra: dict):
    """`--branch-from RUN --branch-after K` of `ccfit run` (both or neither)."""
    from ccfit.branch import Branch

    source, after = extra.get("branch_from"), extra.get("branch_after")
    if source is None and after is None:
        return None
    if not source or not after:
        raise CliError("--branch-from RUN and --branch-after K go together")
    try:
        return Branch(Path(source), int(after))
    except ValueError:
        raise CliError(f"--branch-after takes a number of tasks, got {after!r}") from None


def cmd_fit(argv: list[str]) -> None:
    """ccfit fit --suite Reach --preset cpu --method.type=ewc  (offline track; see --help)"""
    from ccfit.config_parse import curriculum_notes
    from ccfit.offline import OfflineConfig, OfflineCurriculum, default_out

    cfg, extra = _parse_config(OfflineConfig, argv, "ccfit fit", QUIET | SCRATCH_ROOT)
    out = Path(cfg.out) if cfg.out else default_out(cfg)
    # Made before the notes: a run whose start refuses it (its encoder file) says one line.
    curriculum = OfflineCurriculum(cfg, out, extra.get("scratch_root") or None,
                                   progress=not extra.get("quiet"))  # fmt: skip
    for note in curriculum_notes(cfg.to_dict()):
        print(f"ccfit fit: note: {note}", file=sys.stderr)
    result = curriculum.run()
    print(
        f"{cfg.suite} {cfg.model.type} {cfg.method.type} seed {cfg.seed} offline "
        f"({result['measurement_space']}): BWT {_fmt(result['bwt'])}, "
        f"FWT {_fmt(result['fwt'])}  ->  {out}"
    )


def _cmd_report(args: argparse.Namespace) -> None:
    from ccfit.io import out_dir
    from ccfit.report import write_page, write_report

    if args.out is None:
        if len(args.runs) != 1 or not Path(args.runs[0]).is_dir():
            raise InputError(
                "without --out, give one folder of published runs (its README.md, the results "
                f"page, is rewritten); got {' '.join(args.runs)}"
            )
        paths = write_page(Path(args.runs[0]))
    else:
        paths = write_report([Path(p) for p in args.runs], out_dir(args.out))
    for path in paths:
        print(path)


def _cmd_publish(args: argparse.Namespace) -> None:
    from ccfit.io import out_dir
    from ccfit.publish import publish

    paths = publish(Path(args.runs), out_dir(args.out), Path(args.root) if args.root else None)
    print(f"{len(paths)} files -> {args.out}")


def _cmd_learnability(args: argparse.Namespace) -> None:
    from ccfit.analysis.learnability import write_learnability
    from ccfit.io import out_dir

    paths = write_learnability([Path(p) for p in args.runs], out_dir(args.out))
    for path in paths:
        print(path)


def _cmd_probe_encoder(args: argparse.Namespace) -> None:
    from ccfit.analysis.encoder_probe import (
        markdown,
        probe_encoder,
        probed_sidecar,
        select_tasks,
        write_probe,
    )
    from ccfit.io import out_dir
    from ccfit.settings import torch_threads

    suites, tasks = select_tasks(args.suites, args.tasks)
    if args.frames < 10:
        raise CliError(
            f"--frames must be at least 10 (a held-out fifth to score), got {args.frames}"
        )
    if args.torch_threads < 0:
        raise CliError(f"--torch-threads must be >= 0, got {args.torch_threads}")
    if args.workers < 1:
        raise CliError(f"--workers must be >= 1, got {args.workers}")
    sidecar = probed_sidecar(args.encoder)  # read first: a damaged one stops before the probe
    with torch_threads(args.torch_threads):
        result = probe_encoder(args.encoder, tasks, frames=args.frames, seed=args.seed,
                               suites=suites, workers=args.workers)  # fmt: skip
    print(markdown(result), end="")
    print("-> " + ", ".join(str(p) for p in write_probe(result, out_dir(args.out), sidecar)))


def _cmd_compare(args: argparse.Namespace) -> int:
    from ccfit.compare import compare_runs, describe

    a, b = Path(args.a), Path(args.b)
    comparison = compare_runs(a, b)
    print(describe(comparison, a, b), end="")
    return 0 if comparison.reproduces else 1


def _cmd_ablate(args: argparse.Namespace) -> None:
    from ccfit.analysis import ABLATION_JSON, ABLATION_PNG, ablate

    run = Path(args.run)
    result = ablate(run, episodes=args.episodes, horizon=args.horizon)

    def fmt(x):
        return "n/a" if x is None else f"{x:.2f}"

    for name, m in result["modes"].items():
        print(
            f"{name:8s} return x{fmt(m['return_ratio'])} (normalised "
            f"{fmt(m['normalized_return'])}), latent error x{fmt(m['latent_error_ratio'])}"
        )
    print(f"-> {run / ABLATION_JSON}, {run / ABLATION_PNG}")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="ccfit", description=__doc__,
                          formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    for name, fn in CONFIG_COMMANDS.items():  # listed in --help; each parses its own in main()
        sub.add_parser(name, help=fn.__doc__.split("  (")[0], add_help=False)
    from ccfit.pretrain import add_pretrain_parser

    add_pretrain_parser(sub)

    p = add_command(sub, "report", "tables and plots over run directories; without --out, the "
                    "results page (README.md) of a folder of published runs",
                    "ccfit report results/online/reach-tdmpc2 --out report/\n"
                    "    ccfit report results/")  # fmt: skip
    p.add_argument("runs", nargs="+", help="run directories (or folders holding them)")
    p.add_argument("--out", help="output directory (tables and plots); without it, RUNS is one "
                   "folder whose README.md, orderings.md, axes.md, cost.md and intervals.png "
                   "are rewritten over every run under it")  # fmt: skip
    p.set_defaults(func=_cmd_report)

    p = add_command(sub, "publish", "copy finished runs' small files (config, metrics, cost) and "
                    "write the report (curricula) or the learnability tables (single-task runs) "
                    "over them, for a results folder",
                    "ccfit publish runs/sweep1 --out results/online/my-sweep "
                    "--root results")  # fmt: skip
    p.add_argument("runs", help="folder holding finished runs (a sweep's, or `ccfit train` runs)")
    p.add_argument(
        "--out", required=True, help="results folder (its report/ and learnability/ are rewritten)"
    )
    p.add_argument("--root", help="folder holding --out and every other published result: its "
                   "orderings.md, axes.md and cost.md are rewritten over all of them")  # fmt: skip
    p.set_defaults(func=_cmd_publish)

    p = add_command(sub, "learnability", "steps each task needs to reach 50 and 80, and the "
                    "per-suite budgets, from single-task `ccfit train` runs",
                    "ccfit learnability results/single-task --out learn/")  # fmt: skip
    p.add_argument("runs", nargs="+", help="run directories (or folders holding them)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_learnability)

    p = add_command(sub, "compare", "whether run B reproduces run A's records, the first that "
                    "differs, and what differs between the runs (settings, code, machines, "
                    "datasets); exit 1 when a record differs",
                    "ccfit compare results/online/reach-tdmpc2/Reach-tdmpc2-ft-state-cpu-s0 "
                    "runs/my-ft-s0")  # fmt: skip
    p.add_argument("a", help="run directory (a curriculum, a single-task or an offline run)")
    p.add_argument("b", help="run directory to compare with it")
    p.set_defaults(func=_cmd_compare)

    p = add_command(sub, "probe-encoder", "how well a frozen encoder's latent gives each task's "
                    "hand, object and goal positions (held-out R^2 of linear probes, beside the "
                    "same from the pixels), and which task of a group that is one MDP from "
                    "state a frame shows (held-out accuracy of a linear classifier)",
                    "ccfit probe-encoder enc.safetensors --suites all --out probe/")  # fmt: skip
    p.add_argument("encoder", help="weights file written by `ccfit pretrain-encoder`")
    p.add_argument("--suites", help="'all' or a comma list, e.g. BinPnP,PnPBlock: their every "
                   "task (with --tasks: both, each task once)")  # fmt: skip
    p.add_argument("--tasks", help="comma list of task ids, e.g. reach-xy,pick-cube")
    p.add_argument("--frames", type=int, default=1000,
                   help="frames per task, each from a fresh layout (default 1000); one takes "
                        "0.06-0.17 s to collect by task (0.11 on average, on a busy 2-core "
                        "CPU), so all six suites' 18 tasks take about 35 minutes in one "
                        "process (--workers)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--torch-threads", type=int, default=1,
                   help="CPU threads for torch (default 1, as training's; 0: torch's own "
                        "count, which beside another job on a small machine runs many times "
                        "slower)")  # fmt: skip
    p.add_argument("--workers", type=int, default=1,
                   help="processes collecting frames, a task each at a time (default 1; the "
                        "result does not depend on it)")  # fmt: skip
    p.add_argument("--out", required=True, help="output directory (probe.json, probe.md)")
    p.set_defaults(func=_cmd_probe_encoder)

    p = add_command(sub, "ablate", "expert ablation of a finished run of a model offering "
                    "'routing' (prior / new / uniform routing on the composition task)",
                    "ccfit ablate runs/Reach-pwm-experts-pixels-cpu-s0")  # fmt: skip
    p.add_argument("run", help="run directory of a finished curriculum of a routed model")
    p.add_argument("--episodes", type=int, default=None,
                   help="evaluation layouts (default: the run's eval_episodes)")  # fmt: skip
    p.add_argument("--horizon", type=int, default=None,
                   help="open-loop prediction steps (default: the model's horizon)")  # fmt: skip
    p.set_defaults(func=_cmd_ablate)
    return parser


def cmd_sweep(argv: list[str]) -> int:
    """ccfit sweep --suites Reach --methods ft,er --seeds 0,1 --out RUNS  (see --help)"""
    from ccfit.sweep.cli import cmd_sweep as sweep

    return sweep(argv)


CONFIG_COMMANDS = {"train": cmd_train, "run": cmd_run, "fit": cmd_fit, "sweep": cmd_sweep}
"""Commands whose options are the typed config tree (draccus): `ccfit run --help` lists it."""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in CONFIG_COMMANDS:
            code = CONFIG_COMMANDS[argv[0]](argv[1:])
        else:
            args = build_parser().parse_args(argv)
            code = args.func(args)
        sys.stdout.flush()  # here, so that a reader gone (`| head`) is caught below
    except (CliError, InputError) as e:
        print(f"ccfit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("ccfit: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except BrokenPipeError:
        if not stdout_reader_gone():
            raise  # a pipe of the program's own broke: a bug, its traceback shows
        return stdout_closed()
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
