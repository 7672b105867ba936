"""`ccfit report`'s `stages.md` and `stages.csv`: every run's scores stage by stage.

BWT and FWT condense a curriculum into two numbers; where the forgetting happened, and how a
task held up between its own end and the curriculum's, is in the stages. For each run, each
stage (the task it trains) and each task evaluated during it: how many evaluations, their mean,
the evaluation episodes that succeeded (online), and the score at the stage's end. The last
column is the continual-learning literature's accuracy matrix R (R[i][j]: task j's score after
training task i): its diagonal is the end-of-task scores, its last stage the final scores. A
stage's mean is read over many evaluations where its end is one, so it is the steadier account
of how a task fared while another trained.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ccdata.errors import InputError
from ccdata.suites import get_suite
from ccfit.io import atomic_write_text
from ccfit.report.plots import method_rank, row_label
from ccfit.report.runs import Run
from ccfit.train import METRICS

GroupKey = tuple[str, str, str, str]

STAGES_MD = "stages.md"
STAGES_CSV = "stages.csv"
READING = (
    "Per run, each stage (the task the curriculum trains in it) and each task evaluated during "
    "it: the evaluations, their mean score, the evaluation episodes that succeeded (online "
    "runs) and the score at the stage's end, its last evaluation (after the method's "
    "end-of-task step, e.g. PackNet's prune and retraining). Scores are normalised returns "
    "online and the open-loop prediction score offline (0 = persistence, 100 = perfect). The "
    "ends are the accuracy matrix R of continual learning (R[i][j]: task j after training "
    "task i): the end of a task's own stage is its end-of-task score, the last stage's ends are "
    "the final scores. A mean is read over the whole stage and an end is one evaluation, so "
    "the mean says more of how a task held up while another trained."
)
"""How stages.md reads (printed under its title)."""
READING_SE = (
    "An end shown as `score ± SE` carries its standard error over its evaluation's episodes "
    "(runs whose records hold each episode's return)."
)
"""Printed under `READING` where some end carries its standard error."""
CSV_HEADER = ["backbone", "suite", "method", "variant", "seed", "run", "stage", "training",
              "task", "evaluations", "mean", "successes", "episodes", "end", "end_se"]  # fmt: skip


@dataclass(frozen=True)
class StageCell:
    """One task's evaluations during one stage of a run."""

    stage: int
    task: int
    scores: tuple[float, ...]
    successes: int | None
    """Evaluation episodes that succeeded, None where the records do not say (offline)."""
    episodes: int | None
    end_se: float | None = None
    """The end's standard error over its evaluation's episodes (their normalised returns'
    sample std / sqrt(episodes)), where its record holds each episode's return; else None."""

    @property
    def mean(self) -> float:
        return sum(self.scores) / len(self.scores)

    @property
    def end(self) -> float:
        return self.scores[-1]


def stage_cells(records: list[dict], key: str, source: str = "records") -> list[StageCell]:
    """The records' `key` per (stage, task), in order of stage then task. Records without the
    score are left out; should one step of a task be logged twice in a stage, the later stands
    (as `ccfit.metrics.task_curves` reads them). A scored record without its stage is bad
    input (InputError naming `source`)."""
    by_cell: dict[tuple[int, int], dict[int, dict]] = {}
    for r in records:
        if r.get(key) is None or "task_index" not in r:
            continue
        if "stage" not in r:
            step = r.get("global_step")
            raise InputError(f"{source}: the evaluation record at step {step} names no stage; "
                             "rerun the run or leave it out of the report")  # fmt: skip
        by_cell.setdefault((int(r["stage"]), int(r["task_index"])), {})[int(r["global_step"])] = r
    cells = []
    for (stage, task), by_step in sorted(by_cell.items()):
        rs = [by_step[s] for s in sorted(by_step)]
        counted = all(r.get("success_rate") is not None and r.get("episodes") for r in rs)
        cells.append(StageCell(
            stage, task, tuple(float(r[key]) for r in rs),
            sum(round(r["success_rate"] * r["episodes"]) for r in rs) if counted else None,
            sum(int(r["episodes"]) for r in rs) if counted else None,
            end_standard_error(rs[-1]) if key == "normalized_return" else None,
        ))  # fmt: skip
    return cells


def end_standard_error(record: dict) -> float | None:
    """Standard error of an online record's normalised return over its episodes: the sample
    std of the episodes' normalised returns / sqrt(episodes). None where the record holds no
    per-episode returns (records before they were kept), fewer than two, or the task has no
    oracle reference yet."""
    from ccfit.train.evaluate import normalized_or_none

    returns = record.get("returns") or []
    scores = [normalized_or_none(record["task"], r) for r in returns]
    if len(scores) < 2 or None in scores:
        return None
    return float(np.std(scores, ddof=1) / np.sqrt(len(scores)))


def _ordered(run_groups: dict[GroupKey, list[Run]]) -> list[tuple[GroupKey, Run]]:
    """(group key, run) for every run, by backbone, suite, method (`METHOD_ORDER`), variant
    and seed."""
    keys = sorted(run_groups, key=lambda k: (k[0], k[1], method_rank(k[2]), k[2], k[3]))
    return [(k, r) for k in keys for r in sorted(run_groups[k], key=lambda r: r.seed)]


def write_stages(run_groups: dict[GroupKey, list[Run]], curve_keys: dict[str, str],
                 out: Path) -> list[Path]:  # fmt: skip
    """`stages.md` and `stages.csv` over `run_groups` (`ccfit.report.group_runs`), each run's
    scores read from the record field `curve_keys` names for its track."""
    lines = ["# Each task's score, stage by stage", "", READING]
    with_se = False
    table = io.StringIO(newline="")
    writer = csv.writer(table)
    writer.writerow(CSV_HEADER)
    for (backbone, suite, method, variant), run in _ordered(run_groups):
        names = list(get_suite(suite).task_ids)
        lines += ["", f"## {backbone}, {row_label(suite, variant)}, {method}, seed {run.seed} "
                  f"(`{run.path.name}`)", "",
                  "| stage | training | task | evaluations | mean | successes | at its end |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for c in stage_cells(run.records, curve_keys[run.track], str(run.path / METRICS)):
            n = len(c.scores)
            successes = "—" if c.successes is None else f"{c.successes}/{c.episodes}"
            end = f"{c.end:.1f}" + ("" if c.end_se is None else f" ± {c.end_se:.1f}")
            with_se = with_se or c.end_se is not None
            lines.append(f"| {c.stage} | {names[c.stage]} | {names[c.task]} | {n} | "
                         f"{c.mean:.1f} | {successes} | {end} |")  # fmt: skip
            writer.writerow([backbone, suite, method, variant, run.seed, run.path.name, c.stage,
                             names[c.stage], names[c.task], n, c.mean, c.successes, c.episodes,
                             c.end, c.end_se])  # fmt: skip
    if with_se:
        lines[3:3] = ["", READING_SE]
    md, csv_path = out / STAGES_MD, out / STAGES_CSV
    atomic_write_text(md, "\n".join(lines) + "\n")
    atomic_write_text(csv_path, table.getvalue())
    return [md, csv_path]
