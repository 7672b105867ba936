"""Where is a task's end-of-task score C_i read, and what does PackNet's BWT owe to it?

    python results/diagnostics/end_score.py results/online > results/diagnostics/end_score.jsonl

The toolkit reads C_i at b_i after the continual method closed the task, so PackNet's C_i is
that of the pruned and retrained backbone the later tasks start from (`ccfit.train.loop`). The
paper's authors' code evaluates before the prune, so there the prune's loss counts as
forgetting. The records hold no evaluation at b_i before the prune, so this reads the last
evaluation before it (b_i - eval_interval) in its place. To separate the prune from the noise
of a single evaluation, every method's runs are read both ways: a method that closes a task
without changing it (FT, ER, EWC) moves only by that noise.

One JSON line per finished curriculum (online, every published sweep under the given folders):
its BWT as published (recomputed from its records) and with each C_i, i < N, taken from the
evaluation before b_i, and both C_i. The last line averages each (published folder, suite,
backbone, method) group over its seeds: two folders may hold the same grid under other settings
(a preset changed between them), and a run is named by its folder and its name.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from ccdata.errors import OneLineParser, run_script
from ccfit.metrics import compute_metrics
from ccfit.report.runs import CURVE_KEYS, find_runs


def read_before_close(records: list[dict], ends: list[int], key: str) -> list[dict]:
    """`records` with task i's score at b_i (i < N) replaced by its last one before b_i."""
    out = [dict(r) for r in records]
    for i, end in enumerate(ends[:-1]):
        mine = sorted((r for r in out if r["task_index"] == i), key=lambda r: r["global_step"])
        before = [r for r in mine if r["global_step"] < end]
        for r in mine:
            if r["global_step"] == end and before:
                r[key] = before[-1][key]
    return out


def end_scores(records: list[dict], ends: list[int], key: str) -> list[float]:
    return [next(r[key] for r in records if r["task_index"] == i and r["global_step"] == end)
            for i, end in enumerate(ends[:-1])]  # fmt: skip


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", help="folders holding published curricula")
    args = parser.parse_args(argv)
    groups = defaultdict(lambda: defaultdict(list))
    for run in find_runs([Path(p) for p in args.folders]):
        if run.track != "online":
            continue
        key, m = CURVE_KEYS[run.track], run.metrics
        ends, n = m["task_ends"], len(m["task_ends"])
        shifted = read_before_close(run.records, ends, key)
        as_read = compute_metrics(run.records, run.scratch, n, m["budget"], key)
        before = compute_metrics(shifted, run.scratch, n, m["budget"], key)
        line = {
            "folder": run.path.parent.name,
            "run": run.path.name,
            "suite": run.config["suite"],
            "backbone": run.backbone,
            "method": run.config["method"]["type"],
            "seed": run.config["seed"],
            "bwt": as_read["bwt"],
            "bwt_before_close": before["bwt"],
            "end_scores": end_scores(run.records, ends, key),
            "end_scores_before_close": end_scores(shifted, ends, key),
        }
        print(json.dumps(line))
        group = groups[(line["folder"], line["suite"], line["backbone"], line["method"])]
        for k in ("bwt", "bwt_before_close"):
            group[k].append(line[k])

    def mean(values):
        kept = [v for v in values if v is not None]
        return float(np.mean(kept)) if kept else None

    print(json.dumps({"groups": [
        {"folder": f, "suite": s, "backbone": b, "method": meth, "runs": len(g["bwt"]),
         "bwt": mean(g["bwt"]), "bwt_before_close": mean(g["bwt_before_close"])}
        for (f, s, b, meth), g in sorted(groups.items())
    ]}))  # fmt: skip


if __name__ == "__main__":
    sys.exit(run_script(main, "end_score.py"))
