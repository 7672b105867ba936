"""`ccfit report`: tables and plots over continual runs, in the layout of the paper.

Runs are grouped by (backbone, suite, method); seeds within a group are averaged *before* a
metric (the paper's protocol), and the per-seed metrics give the min/max. Outputs:
- `table_<backbone>.md` / `.csv`: suites x methods, BWT and FWT as mean [min, max]
  (the paper's Appendix B layout);
- `bars_<backbone>.png`: BWT and FWT bars per suite and method with min-max whiskers (Fig. 4);
- `curves_<backbone>_<suite>_<method>.png`: every task's normalised return over the
  curriculum, the forgetting (BWT) region shaded after each task's end and the forward
  transfer (FWT) region between the composition curve and its from-scratch reference.
- `routing_<suite>_<method>_s<seed>.png`: the paper's Fig. 5 for every PWM run with a
  `routing.jsonl` (`ccfit.analysis`); summary.json gets the top-expert statement per seed.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ccfit import metrics as M
from ccfit.analysis import report_routing
from ccfit.curriculum import METRICS_JSON
from ccfit.metrics import metrics_from_curves, task_curves
from ccfit.train import CONFIG, METRICS

METHOD_ORDER = ("ft", "er", "ewc", "packnet", "experts")


@dataclass
class Run:
    path: Path
    config: dict
    records: list[dict]
    scratch: list[dict]
    metrics: dict

    @property
    def backbone(self) -> str:
        return self.config["model"]["type"] + ("+frozen-enc" if self.config.get("encoder") else "")

    @property
    def key(self) -> tuple[str, str, str]:
        return self.backbone, self.config["suite"], self.config["method"]["type"]


def find_runs(paths: list[Path]) -> list[Run]:
    dirs: list[Path] = []
    for p in paths:
        if not p.exists():
            raise ValueError(f"no such run directory: {p}")
        dirs += [m.parent for m in sorted(p.rglob(METRICS_JSON))] if p.is_dir() else []
    if not dirs:
        where = ", ".join(map(str, paths))
        raise ValueError(f"no finished runs (with {METRICS_JSON}) under {where}")
    runs = []
    for d in dict.fromkeys(dirs):
        metrics = json.loads((d / METRICS_JSON).read_text())
        records = [json.loads(x) for x in (d / METRICS).read_text().splitlines() if x.strip()]
        scratch = json.loads((_scratch_dir(d, metrics) / "done.json").read_text())
        runs.append(Run(d, json.loads((d / CONFIG).read_text()), records, scratch, metrics))
    return runs


def _scratch_dir(run_dir: Path, metrics: dict) -> Path:
    """The run's from-scratch reference: where the run wrote it or, when that path does not
    resolve from here (a relative path from another working directory, a moved tree), the
    default location beside the run (`<run>/../scratch/<key>`)."""
    stored = Path(metrics["scratch_dir"])
    if (stored / "done.json").is_file():
        return stored
    beside = run_dir.parent / "scratch" / stored.name
    if (beside / "done.json").is_file():
        return beside
    raise ValueError(f"{run_dir}: its from-scratch reference {stored} is missing")


def group_metrics(runs: list[Run]) -> dict:
    """Metrics of seed-averaged curves, plus min/max of the per-seed metrics."""
    num_tasks = len(runs[0].metrics["task_ends"])
    budget = runs[0].metrics["budget"]
    ends = runs[0].metrics["task_ends"]
    per_seed = [task_curves(r.records, num_tasks) for r in runs]
    curves = [M.average_curves([c[t] for c in per_seed]) for t in range(num_tasks)]
    scratch = M.average_curves([task_curves(r.scratch, num_tasks)[-1] for r in runs])
    mean = metrics_from_curves(curves, ends, scratch, budget)
    out = {"seeds": sorted(r.config["seed"] for r in runs), "curves": curves, "scratch": scratch,
           "ends": ends, "budget": budget}  # fmt: skip
    for name in ("bwt", "fwt"):
        values = [r.metrics[name] for r in runs if r.metrics[name] is not None]
        out[name] = mean[name]
        out[f"{name}_min"] = min(values) if values else None
        out[f"{name}_max"] = max(values) if values else None
    return out


def _cell(g: dict, name: str) -> str:
    if g[name] is None:
        return "n/a"
    if len(g["seeds"]) == 1:
        return f"{g[name]:.2f}"
    return f"{g[name]:.2f} [{g[f'{name}_min']:.2f}, {g[f'{name}_max']:.2f}]"


def write_tables(groups: dict, out: Path) -> list[Path]:
    written = []
    for backbone in sorted({k[0] for k in groups}):
        suites = sorted({k[1] for k in groups if k[0] == backbone})
        methods = [m for m in METHOD_ORDER if any(k[0] == backbone and k[2] == m for k in groups)]
        header = ["suite"] + [f"{m} {x}" for m in methods for x in ("BWT", "FWT")]
        rows = []
        for suite in suites:
            row = [suite]
            for m in methods:
                g = groups.get((backbone, suite, m))
                row += [_cell(g, "bwt"), _cell(g, "fwt")] if g else ["", ""]
            rows.append(row)
        md = out / f"table_{backbone}.md"
        lines = [f"# {backbone}: BWT (lower is better) and FWT (higher is better)", "",
                 "Mean over seeds of the seed-averaged curves' metric, [min, max] per seed.", "",
                 "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]  # fmt: skip
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        md.write_text("\n".join(lines) + "\n")
        path = out / f"table_{backbone}.csv"
        with path.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["backbone", "suite", "method", "seeds", "bwt", "bwt_min", "bwt_max",
                             "fwt", "fwt_min", "fwt_max"])  # fmt: skip
            for (b, suite, m), g in sorted(groups.items()):
                if b == backbone:
                    writer.writerow([b, suite, m, len(g["seeds"])] + [
                        g[k] for k in ("bwt", "bwt_min", "bwt_max", "fwt", "fwt_min", "fwt_max")
                    ])  # fmt: skip
        written += [md, path]
    return written


def plot_bars(groups: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for backbone in sorted({k[0] for k in groups}):
        suites = sorted({k[1] for k in groups if k[0] == backbone})
        methods = [m for m in METHOD_ORDER if any(k[0] == backbone and k[2] == m for k in groups)]
        fig, axes = plt.subplots(1, 2, figsize=(4 + 1.6 * len(suites), 3.6))
        width = 0.8 / max(len(methods), 1)
        for ax, name, better in zip(axes, ("bwt", "fwt"), ("lower", "higher"), strict=True):
            for k, m in enumerate(methods):
                xs, ys, lo, hi = [], [], [], []
                for s, suite in enumerate(suites):
                    g = groups.get((backbone, suite, m))
                    if g is None or g[name] is None:
                        continue
                    xs.append(s + (k - (len(methods) - 1) / 2) * width)
                    ys.append(g[name])
                    low, high = g[f"{name}_min"], g[f"{name}_max"]
                    lo.append(g[name] - (g[name] if low is None else low))
                    hi.append((g[name] if high is None else high) - g[name])
                ax.bar(xs, ys, width, label=m, yerr=[np.maximum(lo, 0), np.maximum(hi, 0)],
                       capsize=2)  # fmt: skip
            ax.set_xticks(range(len(suites)), suites, rotation=20)
            ax.set_title(f"{name.upper()} ({better} is better)")
            ax.axhline(0, color="k", lw=0.5)
        axes[1].legend(fontsize=8)
        fig.suptitle(backbone)
        fig.tight_layout()
        path = out / f"bars_{backbone}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written


def plot_curves(key: tuple[str, str, str], g: dict, task_ids: list[str], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.8))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    ends = g["ends"]
    for i, (steps, scores) in enumerate(g["curves"]):
        c = colours[i % len(colours)]
        ax.plot(steps, scores, color=c, lw=1.5, label=task_ids[i])
        if i < len(ends) - 1:
            # Forgetting region: below the score the task had when its training ended.
            after = steps >= ends[i]
            c_i = M.value_at((steps, scores), ends[i])
            ax.fill_between(steps[after], scores[after], c_i,
                            where=scores[after] < c_i, color=c, alpha=0.2, lw=0)  # fmt: skip
    # Forward transfer: composition curve vs from-scratch over the same budget.
    s_steps, s_scores = g["scratch"]
    start = ends[-1] - g["budget"]
    ax.plot(s_steps + start, s_scores, "k--", lw=1.2, label=f"{task_ids[-1]} (scratch)")
    seq_steps, seq_scores = g["curves"][-1]
    grid = np.union1d(seq_steps[seq_steps >= start], s_steps + start)
    seq = np.interp(grid, seq_steps, seq_scores)
    scr = np.interp(grid - start, s_steps, s_scores)
    ax.fill_between(grid, seq, scr, where=seq >= scr, color="tab:green", alpha=0.15, lw=0,
                    label="FWT +")  # fmt: skip
    ax.fill_between(grid, seq, scr, where=seq < scr, color="tab:red", alpha=0.15, lw=0,
                    label="FWT -")  # fmt: skip
    for e in ends[:-1]:
        ax.axvline(e, color="grey", lw=0.6, ls=":")
    backbone, suite, method = key
    bwt, fwt = g["bwt"], g["fwt"]
    ax.set_title(f"{suite} / {backbone} / {method}: BWT {bwt if bwt is None else round(bwt, 2)}, "
                 f"FWT {fwt if fwt is None else round(fwt, 2)} (seeds {g['seeds']})")  # fmt: skip
    ax.set_xlabel("global step")
    ax.set_ylabel("normalised return")
    ax.legend(fontsize=7, ncol=2, loc="best")
    fig.tight_layout()
    path = out / f"curves_{backbone}_{suite}_{method}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def load_groups(paths: list[Path]) -> dict[tuple[str, str, str], dict]:
    """Finished runs under `paths`, grouped by (backbone, suite, method) (`group_metrics`)."""
    by_key: dict[tuple, list[Run]] = defaultdict(list)
    for r in find_runs([Path(p) for p in paths]):
        by_key[r.key].append(r)
    return {k: group_metrics(v) for k, v in sorted(by_key.items())}


def table_frame(groups: dict, backbone: str):
    """One backbone's table as a pandas DataFrame: suites x (method, BWT / FWT), the metric of
    the seed-averaged curves (numbers; `table_<backbone>.md` adds the per-seed [min, max])."""
    import pandas as pd

    keys = [k for k in groups if k[0] == backbone]
    if not keys:
        valid = ", ".join(sorted({k[0] for k in groups}))
        raise ValueError(f"no runs of backbone {backbone!r}; valid: {valid}")
    suites = sorted({k[1] for k in keys})
    methods = [m for m in METHOD_ORDER if any(k[2] == m for k in keys)]
    columns = pd.MultiIndex.from_product([methods, ["BWT", "FWT"]], names=["method", "metric"])
    frame = pd.DataFrame(index=pd.Index(suites, name="suite"), columns=columns, dtype=float)
    for _, suite, method in keys:
        g = groups[(backbone, suite, method)]
        frame.loc[suite, (method, "BWT")] = np.nan if g["bwt"] is None else g["bwt"]
        frame.loc[suite, (method, "FWT")] = np.nan if g["fwt"] is None else g["fwt"]
    return frame


def write_report(paths: list[Path], out: Path) -> list[Path]:
    """Tables and plots for every (backbone, suite, method) group of finished runs."""
    groups = load_groups(paths)
    out.mkdir(parents=True, exist_ok=True)
    written = write_tables(groups, out) + plot_bars(groups, out)
    for k, g in groups.items():
        written.append(plot_curves(k, g, _task_ids(k[1]), out))
    summary = {
        "/".join(k): {n: g[n] for n in ("seeds", "bwt", "bwt_min", "bwt_max", "fwt", "fwt_min",
                                         "fwt_max")}  # fmt: skip
        for k, g in groups.items()
    }
    pngs, routing = report_routing(find_runs([Path(p) for p in paths]), out)  # Fig. 5, PWM runs
    for key, per_seed in routing.items():
        summary["/".join(key)]["routing"] = per_seed
    written += pngs
    path = out / "summary.json"
    path.write_text(json.dumps(summary, indent=2) + "\n")
    return written + [path]


def _task_ids(suite: str) -> list[str]:
    from ccdata.suites import get_suite

    return list(get_suite(suite).task_ids)
