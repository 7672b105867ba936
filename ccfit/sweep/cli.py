r"""`ccfit sweep`: a grid of continual runs, here or on SLURM, and the report over them.

    ccfit sweep --suites Reach,Grasp --methods ft,er,ewc,packnet --seeds 0,1,2 --preset cpu \
        --out runs/sweep1 [--models M1,M2] [--launcher slurm] [--max-parallel 4] \
        [--obs pixels --train.steps=2000 --model.FIELD=VALUE ...] [--keep-stages] \
        [--no-share-first-task]
    ccfit sweep --track offline --suites Reach --methods ft,ewc \
        --out runs/offline1                    # `ccfit fit` runs on the suite datasets
    ccfit sweep --status runs/sweep1

Options the sweep does not know are run options (`ccfit run --help`, or `ccfit fit --help`
with `--track offline`), set for every run; a field of some models' or methods' configs only
(`--method.retrain_steps=6000`, PackNet's) is set for their runs.
Running the same command again submits only the unfinished work. A local sweep (or a SLURM
one with `--wait`) whose runs did not all finish, or whose report failed, exits 1 after the
report, so that `ccfit sweep ... && next` stops there.
"""

from __future__ import annotations

import argparse
import shutil
import sys

from ccdata.errors import InputError, OneLineParser
from ccdata.processes import available_cores
from ccdata.slurm import REQUEUE_SAFE_MIN, LaunchError, check_slurm, settings_from_options
from ccdata.slurm import add_options as add_slurm_options
from ccfit.config_base import DEFAULTS, PRESETS
from ccfit.config_parse import curriculum_notes
from ccfit.continual import method_names
from ccfit.io import out_dir
from ccfit.models import DEFAULT_MODEL, DEFAULT_OFFLINE_MODEL, model_names
from ccfit.sweep.grid import (
    SWEEP_JSON,
    TRACKS,
    Grid,
    check_same_sweep,
    expand,
    import_plugins,
    read_record,
)
from ccfit.sweep.jobs import RunJob, report_current
from ccfit.sweep.launch import launch_local, launch_slurm, plan_work, slurm_active, sweep_lock
from ccfit.sweep.status import hours_to_go, print_status, sweep_status

EXIT_RUNS_MISSING = 1
"""Exit status of a sweep that ended with runs failed or missing, or its report failed (bad
input exits 2)."""

SLURM_TIME = "1-00:00:00"
"""Time limit of every run and reference job when `--time` is not given."""


class _Parser(OneLineParser):
    """The sweep's own options (either spelling, `OneLineParser`); a usage error is raised as
    `InputError` for the command to report."""

    def error(self, message: str) -> None:
        raise InputError(message)


def _csv(text: str) -> tuple[str, ...]:
    return tuple(x.strip() for x in text.split(",") if x.strip())


def _seeds(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in _csv(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers like 0,1,2, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ccfit sweep", description=__doc__, allow_abbrev=False,
                formatter_class=argparse.RawDescriptionHelpFormatter,
                epilog="Any other option is a run option (`ccfit run --help`), set for every "
                       "run.")  # fmt: skip
    p.add_argument("--suites", type=_csv, help="suites, comma-separated (Reach,Grasp)")
    p.add_argument("--models", type=_csv, default=None,
                   help=f"world models, comma-separated ({','.join(model_names())}; default "
                        f"{DEFAULT_MODEL}, offline {DEFAULT_OFFLINE_MODEL})")  # fmt: skip
    p.add_argument(
        "--methods",
        type=_csv,
        default=(DEFAULTS["method"],),
        help=f"continual methods, comma-separated ({','.join(method_names())})",
    )
    p.add_argument("--seeds", type=_seeds, default=(0,), help="seeds (0,1,2)")
    p.add_argument(
        "--preset",
        default=DEFAULTS["preset"],
        help=f"size preset of every run ({', '.join(PRESETS)})",
    )
    p.add_argument("--out", help="sweep folder RUNS: runs, scratch/, report/, sweep.json")
    p.add_argument("--track", choices=TRACKS, default="online",
                   help="online: `ccfit run` curricula; offline: `ccfit fit` on the suite "
                        "datasets (models offering 'prediction')")  # fmt: skip
    p.add_argument("--launcher", choices=("local", "slurm"), default="local")
    p.add_argument(
        "--max-parallel",
        type=int,
        default=None,
        help="jobs at once (local default: CPU count; SLURM: array throttle)",
    )
    p.add_argument("--plugins", type=_csv, default=(),
                   help="modules to import first, here and in every job (they register models "
                        "or methods defined outside ccfit)")  # fmt: skip
    p.add_argument("--keep-stages", action="store_true",
                   help="online runs keep their state after each task (stages/after-K.pt), to "
                        "branch from (`ccfit run --branch-from`); not part of a run's identity; "
                        "a run that kept stages keeps them when resumed without it")  # fmt: skip
    p.add_argument("--share-first-task", action=argparse.BooleanOptionalAction, default=None,
                   help="runs of one seed whose methods leave the first task as FT trains it "
                        "(ft, er, ewc, packnet) train it once, as a job of its own into "
                        "RUNS/first/, and each closes it with its own method "
                        "(`ccfit.first_task`): the same records, one first task's training "
                        "less per such method; not part of a run's identity (default: on "
                        "online; the offline track has none to share)")  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="print what would run; write nothing")
    p.add_argument("--status", metavar="RUNS", help="show the state of the sweep in RUNS")
    p.add_argument("--wait", action="store_true", help="SLURM: block until the report job ended")
    add_slurm_options(p.add_argument_group("SLURM"), default_time=SLURM_TIME)
    return p


def cmd_sweep(argv: list[str]) -> int:
    """ccfit sweep --suites Reach --methods ft,er --seeds 0,1 --out RUNS  (see --help)
    Returns the exit status: EXIT_RUNS_MISSING where the work ran and its report does not
    list every run as done."""
    args, run_args = build_parser().parse_known_args(argv)
    if args.status:
        print_status(sweep_status(args.status), hours_to_go(args.status))
        return 0
    if not args.suites or not args.out:
        raise InputError("--suites and --out are required (or --status RUNS)")
    settings = None
    if args.launcher == "slurm":
        settings = settings_from_options(args, SLURM_TIME, max_parallel=args.max_parallel)
        if settings.time_min < REQUEUE_SAFE_MIN:
            raise LaunchError(
                f"--time must be at least {REQUEUE_SAFE_MIN} minutes (shorter "
                f"limits break requeueing on preemption), got {settings.time_min}"
            )
        check_slurm()
    elif args.max_parallel is not None and args.max_parallel < 1:
        raise InputError(f"--max-parallel must be >= 1, got {args.max_parallel}")
    if args.keep_stages and args.track == "offline":
        raise InputError("--keep-stages keeps online runs' states after each task; the offline "
                         "track has none to branch from")  # fmt: skip
    if args.share_first_task and args.track == "offline":
        raise InputError("--share-first-task shares online runs' first task; an offline "
                         "run's first task is a fit of its dataset, cheap to repeat")  # fmt: skip
    if args.share_first_task is None:
        args.share_first_task = args.track == "online"
    run_job = RunJob(args.keep_stages, args.share_first_task)
    if args.models is None:
        args.models = (DEFAULT_OFFLINE_MODEL if args.track == "offline" else DEFAULT_MODEL,)
    grid = Grid(args.suites, args.models, args.methods, args.seeds, args.preset,
                tuple(run_args), args.plugins, args.track)  # fmt: skip
    import_plugins(grid.plugins)
    sweep = expand(grid, out_dir(args.out))
    record = read_record(sweep.root)
    if record is not None and (added := check_same_sweep(sweep, record)):
        print(f"ccfit sweep: adding seeds {', '.join(map(str, added))} to the sweep in "
              f"{sweep.root}", file=sys.stderr)  # fmt: skip
    submissions = record.get("submissions", []) if record else []
    active = slurm_active(submissions) if shutil.which("squeue") else {}
    if active and args.launcher == "local":
        raise InputError(f"jobs of a SLURM submission are still queued or running in "
                         f"{sweep.root} ({', '.join(sorted(set(active.values()))[:5])}): wait "
                         f"for them or scancel them")  # fmt: skip
    work = plan_work(sweep, active, args.share_first_task)
    for note in dict.fromkeys(n for run in sweep.runs for n in curriculum_notes(run.config)):
        print(f"ccfit sweep: note: {note}", file=sys.stderr)
    _print_plan(sweep, work, args.dry_run)
    if args.dry_run or work.empty:
        return 0
    if args.launcher == "local":
        cores = available_cores()  # not os.cpu_count(): inside taskset or SLURM it overstates
        parallel = args.max_parallel or cores
        # a config asking for torch's default thread count shares the cores among the jobs
        threads = max(1, cores // parallel)
        with sweep_lock(sweep):
            launch_local(sweep, work, submissions, parallel, threads, run_job)
        return 0 if report_current(sweep) else EXIT_RUNS_MISSING
    entry = launch_slurm(sweep, work, submissions, settings, run_job)
    for name, job in entry["jobs"].items():
        print(f"  {job}  {name}")
    print(
        f"submitted {len(entry['jobs'])} jobs; logs in {sweep.root / 'slurm'}; "
        f"`ccfit sweep --status {args.out}` follows them"
    )
    if args.wait:
        from ccfit.sweep.launch import wait_report

        wait_report(entry, timeout_s=float("inf"))
        print_status(sweep_status(sweep.root), hours_to_go(sweep.root))
        return 0 if report_current(sweep) else EXIT_RUNS_MISSING
    return 0


def _print_plan(sweep, work, dry_run: bool) -> None:
    verb = "would run" if dry_run else "to run"
    print(
        f"{sweep.root / SWEEP_JSON}: {len(sweep.runs)} runs, {work.finished} finished, "
        f"{len(work.active)} jobs still queued or running"
    )
    if work.empty:
        print("nothing to submit: every run is done or queued" if work.active or work.finished
              else "nothing to submit")  # fmt: skip
        return
    first = f"{len(work.first)} shared first tasks, " if work.first else ""
    print(
        f"{verb}: {len(work.scratch)} from-scratch references, {first}{len(work.runs)} runs"
        f"{', then the report' if work.report else ''}"
    )
    if dry_run:
        for key in work.scratch:
            print(f"  scratch/{key}")
        for key in work.first:
            print(f"  first/{key}")
        for run in work.runs:
            print(f"  {run.name}")
    sys.stdout.flush()
