"""`ccfit report`'s `cost.md`: what each group's runs cost and on what machines, from the
`cost.json` beside every run (`ccfit.train.cost`).

What the numbers count: `READING`.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from ccfit.io import atomic_write_text, read_run_json
from ccfit.report.plots import row_label
from ccfit.run_files import FIRST_RECORD
from ccfit.train.cost import COST, read_cost

COST_MD = "cost.md"
READING = (
    "CPU-hours are user and system time summed over a run's processes (training, its "
    "evaluation worker, environment workers) and over its resumptions, so on N cores a run of "
    "H CPU-hours took at least H/N hours; a run begun before cost.json existed counts only its "
    "later segments. A from-scratch reference trained as a job of its own (a sweep's) has a "
    "cost.json of its own and is counted once, in the references' table; one a curriculum "
    "trained is part of that curriculum's cost. So is a seed's shared first task (a sweep "
    "trains it once for all the seed's methods): one trained by a job of its own is counted "
    "once, in the shared first tasks' table, from the record every run that started from it "
    "holds; one a run trained is part of that run's cost. The machine column counts segments "
    "per machine kind (the GPU where a run used one; the CPU model, the vector instruction "
    "set torch used, cores): runs on different kinds round differently, so the same seed does "
    "not reproduce across them. Segments run before cost.json recorded machines are counted as "
    "not recorded."
)
"""How cost.md's numbers read (printed under its title)."""


def run_cost(run_dir: Path) -> dict:
    """`read_cost` of a run directory; a damaged cost.json is bad input, named."""
    if (Path(run_dir) / COST).is_file():
        read_run_json(Path(run_dir) / COST)
    return read_cost(run_dir)


def machine_label(machine: dict) -> str:
    cpu = f"{machine['cpu']} ({machine['cpu_capability']}, {machine['cores']} cores)"
    return f"{machine['gpu']}, {cpu}" if machine.get("gpu") else cpu


def counted(labels: list[str], segments: int) -> str:
    """Segments per label ('AMD EPYC (AVX2, 2 cores) x3'), most first; the `segments` that
    have no label (run before it was recorded) last."""
    cells = [f"{label} x{n}" for label, n in Counter(labels).most_common()]
    missing = segments - len(labels)
    return "; ".join(cells + ([f"not recorded x{missing}"] if missing else [])) or "—"


def machines_cell(costs: list[dict]) -> str:
    """Segments per machine kind over `costs`."""
    labels = [machine_label(m) for c in costs for m in c["machines"]]
    return counted(labels, sum(c["segments"] for c in costs))


def hours_cells(costs: list[dict]) -> tuple[str, str]:
    """CPU-hours per run (the mean, [min, max] over several) and in all, over the runs with a
    cost.json; how many have none is said."""
    hours = [c["cpu_s"] / 3600 for c in costs if c["segments"]]
    missing = len(costs) - len(hours)
    if not hours:
        return "—", f"— ({missing} without cost.json)"
    mean = sum(hours) / len(hours)
    per_run = f"{mean:.2f}" if len(hours) == 1 else \
        f"{mean:.2f} [{min(hours):.2f}, {max(hours):.2f}]"  # fmt: skip
    return per_run, f"{sum(hours):.2f}" + (f" ({missing} without cost.json)" if missing else "")


def first_tasks_by_job(run_groups: dict) -> dict[tuple[str, str, str], list[dict]]:
    """(backbone, suite, variant) -> the cost of each shared first task that a job of its own
    trained for the runs of `run_groups` (`group_runs`), once however many runs started from
    it. Read from the runs' `first_task.json` (the shared folder itself is not published)."""
    found: dict[tuple[Path, str], tuple[tuple[str, str, str], dict]] = {}
    for (backbone, suite, _, variant), runs in run_groups.items():
        for run in runs:
            path = Path(run.path) / FIRST_RECORD
            if not path.is_file():
                continue
            record = read_run_json(path)
            if record.get("trained_by") == "job" and record.get("cost"):
                key = (Path(run.path).resolve().parent, record["shared"])
                found[key] = ((backbone, suite, variant), record["cost"])
    by_scope: dict[tuple[str, str, str], list[dict]] = {}
    for _, (scope, cost) in sorted(found.items()):
        by_scope.setdefault(scope, []).append({"code": [], "machines": [], **cost})
    return by_scope


def scope_table(title: str, noun: str, by_scope: dict[tuple, list[dict]]) -> list[str]:
    """cost.md's table of jobs that no run counts (references, shared first tasks), per
    (backbone, suite, variant), with their total."""
    lines = ["", f"## {title}", "",
             f"| backbone | suite | {noun}s | CPU-hours per {noun} | CPU-hours | machines |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for (backbone, suite, variant), costs in sorted(by_scope.items()):
        per_run, total = hours_cells(costs)
        lines.append(f"| {backbone} | {row_label(suite, variant)} | {len(costs)} | "
                     f"{per_run} | {total} | {machines_cell(costs)} |")  # fmt: skip
    costs = [c for group in by_scope.values() for c in group]
    return lines + [f"| all | | {len(costs)} | | {hours_cells(costs)[1]} | |"]


def write_cost(run_groups: dict, references: dict[Path, tuple[str, str, str]], out: Path) -> Path:
    """`cost.md` for `run_groups` ((backbone, suite, method, variant) -> runs with a `path`) and
    their from-scratch `references` (directory -> (backbone, suite, variant))."""
    lines = ["# What the runs cost", "", READING, "",
             "| backbone | suite | method | runs | CPU-hours per run | CPU-hours | machines |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    every: list[dict] = []
    for (backbone, suite, method, variant), runs in sorted(run_groups.items()):
        costs = [run_cost(r.path) for r in runs]
        every += costs
        per_run, total = hours_cells(costs)
        lines.append(f"| {backbone} | {row_label(suite, variant)} | {method} | {len(runs)} | "
                     f"{per_run} | {total} | {machines_cell(costs)} |")  # fmt: skip
    lines.append(f"| all | | | {len(every)} | | {hours_cells(every)[1]} | |")
    by_scope: dict[tuple[str, str, str], list[dict]] = {}
    unrecorded = 0
    for where, scope in sorted(references.items()):
        cost = run_cost(where)
        if cost["segments"]:
            by_scope.setdefault(scope, []).append(cost)
        unrecorded += not cost["segments"]
    if by_scope:
        lines += scope_table("From-scratch references with a cost.json of their own",
                             "reference", by_scope)  # fmt: skip
    first_tasks = first_tasks_by_job(run_groups)
    if first_tasks:
        lines += scope_table("Shared first tasks trained by a job of their own", "first task",
                             first_tasks)  # fmt: skip
    if unrecorded:
        lines += ["", f"From-scratch references without a cost.json: {unrecorded} of "
                  f"{len(references)} (trained by a curriculum, whose cost counts them, or by a "
                  "job before references recorded their own)."]  # fmt: skip
    path = out / COST_MD
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
