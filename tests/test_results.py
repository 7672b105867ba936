"""The published numbers in `results/` agree with the runs committed beside them: every
report's tables, orderings and costs are rebuilt from the copied config.json / metrics files and
compared byte for byte (`ccfit publish` wrote them; a hand edit or a stale table fails here), and
so are `results/orderings.md`, `results/axes.md` and `results/cost.md`, the orderings, the
composition-axis table and the cost over every published run, and each `learnability/`
folder's tables over the single-task runs published beside it."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from ccfit.analysis.learnability import finished_task_runs, write_learnability
from ccfit.metrics import compute_metrics
from ccfit.publish import LEARNABILITY
from ccfit.report import write_overview_of, write_report
from ccfit.report.axes import AXES_MD
from ccfit.report.cost import COST_MD
from ccfit.report.orderings import ORDERINGS_MD
from ccfit.report.runs import CURVE_KEYS, find_runs
from ccfit.report.stages import STAGES_CSV, STAGES_MD
from ccfit.sweep.grid import SWEEP_JSON
from ccfit.sweep.status import sweep_status

try:
    from stage_ends import assert_stage_ends_are_the_metrics
except ImportError:
    from tests.stage_ends import assert_stage_ends_are_the_metrics

RESULTS = Path(__file__).resolve().parents[1] / "results"
REPORTS = sorted(p for p in RESULTS.rglob("report") if p.is_dir())
LEARNABILITY_TABLES = sorted(p for p in RESULTS.rglob(LEARNABILITY) if p.is_dir())
SWEEPS = sorted(p.parent for p in RESULTS.rglob(SWEEP_JSON))


def test_results_hold_published_reports():
    assert REPORTS, f"no published report under {RESULTS}"


@pytest.mark.parametrize("report", REPORTS, ids=lambda p: str(p.parent.relative_to(RESULTS)))
def test_committed_tables_match_the_metrics_beside_them(report, tmp_path):
    write_report([report.parent], tmp_path)
    committed = sorted(p.name for p in report.glob("table_*"))
    assert committed, f"{report} has no tables"
    for name in [*committed, ORDERINGS_MD, AXES_MD, COST_MD, STAGES_MD, STAGES_CSV]:
        assert (tmp_path / name).read_text() == (report / name).read_text(), name


@pytest.mark.parametrize("report", REPORTS, ids=lambda p: str(p.parent.relative_to(RESULTS)))
def test_the_stage_ends_are_each_runs_end_of_task_and_final_scores(report):
    # stages.csv reads the records as they are; metrics.json read them through the metrics'
    # curves when the run finished: the two agree on every published run.
    rows = list(csv.DictReader((report / STAGES_CSV).open()))
    for metrics in report.parent.glob("*/metrics.json"):
        mine = [r for r in rows if r["run"] == metrics.parent.name]
        assert_stage_ends_are_the_metrics(mine, json.loads(metrics.read_text()))


@pytest.mark.parametrize("report", REPORTS, ids=lambda p: str(p.parent.relative_to(RESULTS)))
def test_each_runs_metrics_json_is_what_its_records_give(report):
    # A table's value is computed from the seeds' records at report time, its [min, max] read
    # from each run's metrics.json, written when the run finished: the two agree only while
    # every metrics.json is what the metrics code makes of the records beside it today.
    for run in find_runs([report.parent]):
        n, budget = len(run.metrics["task_ends"]), run.metrics["budget"]
        fresh = compute_metrics(run.records, run.scratch, n, budget, CURVE_KEYS[run.track])
        assert fresh == {k: run.metrics[k] for k in fresh}, run.path


def test_the_tables_over_all_results_match_them(tmp_path):
    # results/orderings.md: the paper's orderings over every published run at once, so that
    # comparisons across folders (DreamerV3 against TD-MPC2, PWM against TD-MPC2) are made;
    # axes.md the composition-axis table over them; cost.md every published group's cost.
    # `ccfit publish --root results` rewrites them.
    written = write_overview_of([RESULTS], tmp_path)
    assert sorted(p.name for p in written) == sorted([ORDERINGS_MD, AXES_MD, COST_MD])
    for path in written:
        assert path.read_text() == (RESULTS / path.name).read_text(), path.name


def test_results_hold_published_learnability_tables():
    assert LEARNABILITY_TABLES, f"no published learnability tables under {RESULTS}"


@pytest.mark.parametrize("tables", LEARNABILITY_TABLES,
                         ids=lambda p: str(p.parent.relative_to(RESULTS)))  # fmt: skip
def test_committed_learnability_tables_match_the_runs_beside_them(tables, tmp_path):
    runs = finished_task_runs(tables.parent)
    assert runs, f"{tables} has no published single-task run beside it"
    for written in write_learnability(runs, tmp_path):
        assert written.read_text() == (tables / written.name).read_text(), written.name


@pytest.mark.parametrize("root", SWEEPS, ids=lambda p: str(p.relative_to(RESULTS)))
def test_sweep_status_reads_every_published_run_and_report_as_done(root):
    # What a published folder holds is done; what its sweep had not finished is not there.
    status = sweep_status(root)
    assert status.pop("report")["state"] == "done"
    runs = {name: s["state"] for name, s in status.items() if name.startswith("run:")}
    published = {f"run:{p.parent.name}" for p in root.glob("*/metrics.json")}
    assert published and published <= set(runs)
    assert {name for name, state in runs.items() if state == "done"} == published


def _readme_sweeps() -> list[tuple[dict, list[tuple[str, str]]]]:
    """The `ccfit sweep` commands of results/README.md's command block: (grid, run options)."""
    import shlex

    from ccfit.sweep.cli import build_parser

    text = (RESULTS / "README.md").read_text()
    block = text.split("```bash\n", 1)[1].split("```", 1)[0].replace("\\\n", " ")
    names, found = {}, []
    for line in block.splitlines():
        line = line.split("#", 1)[0].strip()
        if "=" in line.split(" ")[0] and not line.startswith("--"):  # ENC=...
            key, value = line.split("=", 1)
            names[key] = value.strip()
            continue
        line = re.sub(r"\$(\w+)", lambda m: names.get(m[1], m[0]), line)
        if line.startswith("ccfit sweep "):
            args, run_args = build_parser().parse_known_args(shlex.split(line)[2:])
            grid = {k: list(getattr(args, k) or []) for k in ("suites", "models", "methods")}
            grid.update(seeds=list(args.seeds), preset=args.preset, track=args.track)
            found.append((grid, _options(run_args)))
    return found


def _options(args: list[str]) -> list[tuple[str, str]]:
    """Run options as (name, value), `--a=b` and `--a b` alike; an encoder file by its name
    (the README gives it relative to the checkout, the record absolute)."""
    out, i = [], 0
    while i < len(args):
        name, sep, value = args[i].partition("=")
        if not sep:
            i += 1
            value = args[i]
        if value.startswith("frozen:"):
            value = f"frozen:{Path(value.removeprefix('frozen:')).name}"
        out.append((name, value))
        i += 1
    return sorted(out)


@pytest.mark.parametrize("sweep", SWEEPS, ids=lambda p: str(p.relative_to(RESULTS)))
def test_the_readme_gives_the_command_each_published_sweep_recorded(sweep):
    """results/README.md's command block holds the `ccfit sweep` command that made each
    published sweep: its grid and every run option its sweep.json records."""
    grid = json.loads((sweep / SWEEP_JSON).read_text())["grid"]
    recorded = {k: grid[k] for k in ("suites", "methods", "seeds", "preset", "track")}
    commands = [(g, opts) for g, opts in _readme_sweeps()
                if {k: g[k] for k in recorded} == recorded
                and g["models"] in ([], grid["models"])]  # fmt: skip
    assert commands, f"no command in results/README.md makes {sweep.name}'s grid {recorded}"
    assert _options(grid["args"]) in [opts for _, opts in commands], (
        f"{sweep.name} recorded {grid['args']}; the README's commands for its grid give "
        f"{[opts for _, opts in commands]}"
    )


MACHINE_PATH = re.compile(r"/(work|root|tmp|home)/")
"""A path of the machine a result was made on (`ccfit publish` writes none: `ccfit.portable`)."""
UNCHECKED = ("README.md", "NOTES.md")
"""Prose at the top of results/, which may quote a command's folder."""


def test_published_files_hold_no_path_of_the_machine_that_made_them():
    files = [p for p in sorted(RESULTS.rglob("*")) if p.is_file() and p.suffix != ".png"
             and p.relative_to(RESULTS).as_posix() not in UNCHECKED]  # fmt: skip
    assert len(files) > 100
    naming = [str(p.relative_to(RESULTS)) for p in files
              if MACHINE_PATH.search(p.read_text(errors="replace"))]  # fmt: skip
    assert not naming, f"{len(naming)} files under results/ name a machine's path: {naming}"
