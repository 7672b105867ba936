"""`ccfit report`: tables and plots over continual runs, in the layout of the paper.

Runs are grouped by their whole resolved config (config.json, flattened to dotted keys) except
what legitimately differs between the seeds of one experiment: the seed itself, seeds derived
from it and output paths (`PER_SEED`), and records of how a run was computed rather than what
(`AS_RUN`: compilation, worker processes, the dataset's location; both in `ccfit.report.runs`).
Only runs of one group are averaged; seeds within a group are averaged *before* a metric (the
paper's protocol), with a 95% bootstrap CI over seeds; the per-seed metrics give their mean (and
its CI) and the min/max. A group is named by (backbone,
suite, method) and, when groups of one table differ in anything else (observation mode, preset,
router, method options, step budget, ...), by a variant label naming those settings
("obs=pixels, preset=cpu"). Outputs:
- `table_<backbone>.md` / `.csv`: (suite, variant) x methods, BWT and FWT as the metric of the
  seed-averaged curves [95% bootstrap CI over seeds] (the paper's Appendix B layout), with the
  settings the variants differ in;
- `bars_<backbone>.png`: BWT and FWT bars per suite and method with CI whiskers (Fig. 4);
- `curves_<backbone>_<suite>_<method>[_<variant>].png`: every task's normalised return over the
  curriculum, the forgetting (BWT) region shaded after each task's end and the forward
  transfer (FWT) region between the composition curve and its from-scratch reference.
- `orderings.md`: the paper's four orderings checked on these groups (`ccfit.report.orderings`);
- `axes.md`: BWT and FWT by composition axis beside the paper's table (`ccfit.report.axes`);
- `cost.md`: CPU-hours per group and reference, and the machines that ran them
  (`ccfit.report.cost`);
- `stages.md` / `.csv`: every run's scores stage by stage, each task's mean and end-of-stage
  score while each task trains (`ccfit.report.stages`);
- `routing_<backbone>_<suite>_<method>_s<seed>.png`: the paper's Fig. 5 for every run with a
  `routing.jsonl` (`ccfit.analysis`); summary.json gets the top-expert statement per seed.

Tracks are kept apart: an offline run (`ccfit fit`, metrics.json `"track": "offline"`) is
labelled `<backbone>-offline`, so it has tables, bars and curves of its own, and its curves are
its prediction score (0 = persistence, 100 = perfect), not normalised returns.
"""

from __future__ import annotations

import csv
import functools
import io
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from ccdata.errors import InputError
from ccfit import metrics as M
from ccfit.analysis import report_routing
from ccfit.config_base import ENCODER_RECORD
from ccfit.io import atomic_write_text
from ccfit.metrics import metrics_from_curves, task_curves
from ccfit.offline.fit import TRACK
from ccfit.report.axes import write_axes
from ccfit.report.cost import write_cost
from ccfit.report.orderings import write_orderings
from ccfit.report.plots import (
    method_columns,
    metric_cell,
    plot_bars,
    plot_curves,
    row_label,
    slug,
)
from ccfit.report.runs import CURVE_KEYS, Run, find_runs, is_axis, scratch_dir_of
from ccfit.report.stages import write_stages
from ccfit.report.stats import curve_interval, metric_fields

SUMMARY_JSON = "summary.json"
"""Every report's summary: its groups' metrics (numbers, what the tables print)."""


def group_metrics(runs: list[Run]) -> dict:
    """Metrics of seed-averaged curves, plus min/max of the per-seed metrics. Refuses runs that
    differ in anything but `PER_SEED` settings."""
    identities = [r.identity for r in runs]
    if any(i != identities[0] for i in identities[1:]):
        differ = sorted(
            k for k in set().union(*identities) if len({repr(i.get(k)) for i in identities}) > 1
        )
        raise InputError(
            f"refusing to average runs whose configs differ in {differ}: "
            + ", ".join(str(r.path) for r in runs)
        )
    seeds = [r.seed for r in runs]
    twice = sorted({s for s in seeds if seeds.count(s) > 1})
    if twice:
        raise InputError(
            f"refusing to average seed(s) {twice} more than once (the same run under two of "
            "the paths given?): " + ", ".join(str(r.path) for r in runs if r.seed in twice)
        )
    num_tasks = len(runs[0].metrics["task_ends"])
    budget = runs[0].metrics["budget"]
    ends = runs[0].metrics["task_ends"]
    track = runs[0].track
    key = CURVE_KEYS[track]
    per_seed = [task_curves(r.records, num_tasks, key) for r in runs]
    scratches = [task_curves(r.scratch, num_tasks, key)[-1] for r in runs]

    @functools.cache
    def averaged(multiset: tuple[int, ...]) -> tuple[list, Any, dict]:
        """The curves of the seeds at `multiset` averaged, and their metrics."""
        curves = [M.average_curves([per_seed[i][t] for i in multiset]) for t in range(num_tasks)]
        scratch = M.average_curves([scratches[i] for i in multiset])
        return curves, scratch, metrics_from_curves(curves, ends, scratch, budget)

    curves, scratch, mean = averaged(tuple(range(len(runs))))
    config = runs[0].config
    out = {"seeds": sorted(seeds), "curves": curves, "scratch": scratch,
           "ends": ends, "budget": budget, "runs": [str(r.path) for r in runs],
           "track": track, "obs": config.get("obs"),
           # which frozen encoder (its file's hash where recorded): comparisons across
           # backbones pair only groups through the same one
           "encoder": config.get(ENCODER_RECORD) or config.get("encoder")}  # fmt: skip
    if mean["bwt"] is None:
        out["bwt_reason"] = M.bwt(curves, ends).reason
    for name, source in METRICS_SHOWN.items():
        ci = curve_interval(len(runs), lambda m, s=source: averaged(m)[2][s])
        by_seed = {r.seed: r.metrics.get(source) for r in runs}
        out |= metric_fields(name, mean[source], ci, by_seed)
    return out


_MISSING = "—"

METRICS_SHOWN = {"bwt": "bwt", "forgetting": "cw_forgetting", "fwt": "fwt"}
"""Table columns per method -> the metrics.json key they read. Forgetting (Continual World's,
end-of-task score minus final score, averaged over every task but the last, in score points) is
shown beside BWT because it needs no floor: BWT leaves out a task whose end-of-task score is at
or below 0 (never learnt), which offline means no better than persistence."""
COLUMN_NAMES = {"bwt": "BWT", "forgetting": "F", "fwt": "FWT"}
GROUP_VALUES = [
    f"{x}{end}"
    for x in METRICS_SHOWN
    for end in ("", "_lo", "_hi", "_seed_mean", "_seed_mean_lo", "_seed_mean_hi", "_min", "_max")
]
"""What a group reports per metric (csv, summary): the metric of the seed-averaged curves and
its 95% CI, the mean of the per-seed metrics and its CI, and the per-seed min and max."""


def _distinguishing_keys(identities: list[dict[str, Any]]) -> list[str]:
    """Few settings whose values tell `identities` apart: shallow keys first (`obs` before
    `train.obs`), each kept only if it separates groups the earlier ones did not."""
    keys = sorted(
        {k for i in identities for k in i if not is_axis(k)}, key=lambda k: (k.count("."), k)
    )

    def classes(ks: list[str]) -> int:
        return len({tuple(repr(i.get(k, _MISSING)) for k in ks) for i in identities})

    chosen: list[str] = []
    for k in keys:
        if classes(chosen) == len(identities):
            break
        if classes([*chosen, k]) > classes(chosen):
            chosen.append(k)
    return chosen


def _variant(identity: dict[str, Any], keys: list[str]) -> str:
    return ", ".join(_setting(identity, k) for k in keys if k in identity)


def _setting(identity: dict[str, Any], key: str) -> str:
    """`key=value`; runs through two frozen encoders differ in the files' SHA-256 (the encoder
    is an axis, shown in the backbone's name), which is named by the file and its hash's head."""
    if key == ENCODER_RECORD and "encoder" in identity:
        name = str(identity["encoder"]).removeprefix("frozen:")
        return f"encoder={name} ({str(identity[key])[:8]})"
    return f"{key}={identity[key]}"


def group_runs(runs: list[Run]) -> dict[tuple[str, str, str, str], list[Run]]:
    """Runs by (backbone, suite, method, variant): one group per distinct config (seeds and
    paths aside). The variant names the settings that tell apart groups sharing a backbone,
    suite and method ('' when nothing does); the same settings label every group of the
    backbone, so rows line up across methods."""
    by_identity: dict[tuple, list[Run]] = defaultdict(list)
    for r in runs:
        by_identity[tuple(sorted((k, repr(v)) for k, v in r.identity.items()))].append(r)
    groups = list(by_identity.values())
    cells: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for g in groups:
        cells[g[0].key].append(g[0].identity)
    keys_of: dict[str, list[str]] = defaultdict(list)
    for (backbone, _, _), identities in cells.items():
        for k in _distinguishing_keys(identities) if len(identities) > 1 else []:
            if k not in keys_of[backbone]:
                keys_of[backbone].append(k)
    out = {}
    for g in groups:
        backbone, suite, method = g[0].key
        keys = sorted(keys_of[backbone], key=lambda k: (k.count("."), k))
        key = (backbone, suite, method, _variant(g[0].identity, keys))
        assert key not in out, f"two groups of runs under one label: {key}"
        out[key] = g
    return dict(sorted(out.items()))


def differing_settings(groups: dict, backbone: str) -> list[str]:
    """The settings the variants of `backbone`'s groups are named by."""
    names = [
        part.split("=", 1)[0]
        for k in groups
        if k[0] == backbone and k[3]
        for part in k[3].split(", ")
    ]
    return list(dict.fromkeys(names))


def _rows(groups: dict, backbone: str) -> list[tuple[str, str]]:
    return sorted({(k[1], k[3]) for k in groups if k[0] == backbone})


def write_tables(groups: dict, out: Path) -> list[Path]:
    written = []
    for backbone in sorted({k[0] for k in groups}):
        methods = method_columns(groups, backbone)
        header = ["suite"] + [f"{m} {COLUMN_NAMES[x]}" for m in methods for x in METRICS_SHOWN]
        rows = []
        for suite, variant in _rows(groups, backbone):
            row = [row_label(suite, variant)]
            for m in methods:
                g = groups.get((backbone, suite, m, variant))
                row += [metric_cell(g, x) if g else "" for x in METRICS_SHOWN]
            rows.append(row)
        lines = [
            f"# {backbone}: BWT and F (lower is better), FWT (higher is better)",
            "",
            "The metric of the seed-averaged curves (the paper's convention) and its 95% "
            "bootstrap confidence interval over seeds (rliable; `ccfit.report.stats`). "
            "F: Continual World's forgetting, end-of-task minus final score in score "
            "points, averaged over every task but the last (defined where BWT leaves out "
            "a task never learnt above 0).",
        ]
        if any(g["track"] == TRACK for k, g in groups.items() if k[0] == backbone):
            lines += ["", "Offline track (`ccfit fit`): the curves are the open-loop prediction "
                      "score on held-out dataset episodes (0 = persistence, 100 = perfect "
                      "prediction, -100 = infinitely worse than persistence), over backbone "
                      "updates; BWT and FWT are read from them as from normalised returns "
                      "online."]  # fmt: skip
        differ = differing_settings(groups, backbone)
        if differ:
            lines += [
                "",
                f"Runs differ in {', '.join(f'`{d}`' for d in differ)}: each row "
                "names its values, and only runs of one row and method are averaged.",
            ]
        lines += ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        md = out / f"table_{backbone}.md"
        atomic_write_text(md, "\n".join(lines) + "\n")
        path = out / f"table_{backbone}.csv"
        text = io.StringIO(newline="")
        writer = csv.writer(text)
        writer.writerow(["backbone", "suite", "method", "variant", "seeds", *GROUP_VALUES])
        for (b, suite, m, variant), g in sorted(groups.items()):
            if b == backbone:
                values = [g[k] for k in GROUP_VALUES]
                writer.writerow([b, suite, m, variant, len(g["seeds"]), *values])
        atomic_write_text(path, text.getvalue())
        written += [md, path]
    return written


def load_groups(paths: list[Path]) -> dict[tuple[str, str, str, str], dict]:
    """Finished runs under `paths` grouped by (backbone, suite, method, variant)
    (`group_runs`), each group's metrics (`group_metrics`)."""
    return grouped(paths)[1]


def grouped(paths: list[Path]) -> tuple[dict, dict]:
    """Finished runs under `paths` by group (`group_runs`), and each group's metrics."""
    run_groups = group_runs(find_runs([Path(p) for p in paths]))
    return run_groups, {k: group_metrics(v) for k, v in run_groups.items()}


def table_frame(groups: dict, backbone: str):
    """One backbone's table as a pandas DataFrame: (suite [variant]) x (method, BWT / FWT), the
    metric of the seed-averaged curves (numbers; `table_<backbone>.md` adds the CI)."""
    import pandas as pd

    if not any(k[0] == backbone for k in groups):
        valid = ", ".join(sorted({k[0] for k in groups}))
        raise InputError(f"no runs of backbone {backbone!r}; valid: {valid}")
    rows = _rows(groups, backbone)
    methods = method_columns(groups, backbone)
    names = [COLUMN_NAMES[x] for x in METRICS_SHOWN]
    columns = pd.MultiIndex.from_product([methods, names], names=["method", "metric"])
    index = pd.Index([row_label(s, v) for s, v in rows], name="suite")
    frame = pd.DataFrame(index=index, columns=columns, dtype=float)
    for (b, suite, method, variant), g in groups.items():
        if b != backbone:
            continue
        label = row_label(suite, variant)
        for x in METRICS_SHOWN:
            frame.loc[label, (method, COLUMN_NAMES[x])] = np.nan if g[x] is None else g[x]
    return frame


def _summary_name(key: tuple[str, str, str, str]) -> str:
    return "/".join(key[:3]) + (f" [{key[3]}]" if key[3] else "")


def references_of(run_groups: dict) -> dict[Path, tuple[str, str, str]]:
    """The from-scratch reference directory of every run in `run_groups` (`group_runs`) ->
    (backbone, suite, variant) of its group; a reference shared by several runs once."""
    return {scratch_dir_of(r.path, r.metrics): (k[0], k[1], k[3])
            for k, runs in run_groups.items() for r in runs}  # fmt: skip


def write_overview(run_groups: dict, groups: dict, out: Path) -> list[Path]:
    """`orderings.md`, `axes.md` and `cost.md` over `run_groups` (`group_runs`) and their
    `groups` (`group_metrics` of each): the tables that compare across groups, and so across
    published folders when made over all of them."""
    return [write_orderings(groups, out), write_axes(groups, out),
            write_cost(run_groups, references_of(run_groups), out)]  # fmt: skip


def write_overview_of(paths: list[Path], out: Path) -> list[Path]:
    """`write_overview` over every finished run under `paths` (`ccfit publish --root`)."""
    return write_overview(*grouped(paths), out)


def write_report(paths: list[Path], out: Path) -> list[Path]:
    """Tables and plots for every (backbone, suite, method, variant) group of finished runs."""
    run_groups, groups = grouped(paths)
    out.mkdir(parents=True, exist_ok=True)
    written = write_tables(groups, out) + write_overview(run_groups, groups, out)
    written += plot_bars(groups, out) + write_stages(run_groups, CURVE_KEYS, out)
    summary = {}
    for k, g in groups.items():
        written.append(plot_curves(k, g, _task_ids(k[1]), out))
        summary[_summary_name(k)] = {
            "variant": k[3], "track": g["track"],
            "seeds": g["seeds"], "runs": g["runs"],
            **{k: g[k] for k in GROUP_VALUES},
        }  # fmt: skip
        # Fig. 5 of the group's routed runs; a variant's figures in a folder of their own, since
        # their file names only say suite, method and seed.
        where = out / f"routing_{slug(k[3])}" if k[3] else out
        where.mkdir(exist_ok=True)
        pngs, routing = report_routing(run_groups[k], where)
        for per_seed in routing.values():
            summary[_summary_name(k)]["routing"] = per_seed
        written += pngs
        if where != out and not any(where.iterdir()):
            where.rmdir()
    path = out / SUMMARY_JSON
    atomic_write_text(path, json.dumps(summary, indent=2) + "\n")
    return written + [path]


def _task_ids(suite: str) -> list[str]:
    from ccdata.suites import get_suite

    return list(get_suite(suite).task_ids)
