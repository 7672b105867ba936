"""`ccfit report results/`: the results page, `README.md` of a folder of published runs.

Its first screen is one table: a row per suite x backbone x observation and track, a column per
continual method, each cell BWT and FWT of the seed-averaged curves with their 95% bootstrap CIs
(`ccfit.report.stats`), beside the row's seeds, steps per task, preset and status (complete:
every run its sweep's grid names is published; partial; not run: a row of the paper's design
with no run here). Then the paper's own figures beside ours, the orderings, the figures and the
commands that made every published sweep (from its `sweep.json`). Everything on the page is
computed from the files under the folder, so it is rebuilt byte for byte from them.
"""

from __future__ import annotations

import itertools
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from ccdata.suites import SUITES
from ccfit.io import atomic_write_text
from ccfit.report.axes import axis_cells
from ccfit.report.build import grouped, write_overview
from ccfit.report.commands import (
    frozen_encoders,
    published_folders,
    setup_commands,
    sweep_commands,
    sweep_grids,
)
from ccfit.report.orderings import ORDERINGS_MD, is_offline, ordering_rows
from ccfit.report.plots import method_rank, ordered_methods
from ccfit.report.runs import Run
from ccfit.report.stats import iqm_interval
from ccfit.run_files import REPORT

PAGE = "README.md"
NOTES = "NOTES.md"
INTERVALS_PNG = "intervals.png"

PAPER_DESIGN = {"dreamerv3": "state", "tdmpc2": "state",
                "pwm+frozen-enc": "pixels", "tdmpc2+frozen-enc": "pixels"}  # fmt: skip
"""The online rows the paper reports on every suite (backbone label -> observation): a row
with no run here is listed as not run."""
PAPER_FROZEN = {("pwm+frozen-enc", "experts"): (3.85, 36.18),
                ("tdmpc2+frozen-enc", "ft"): (34.97, 38.11)}  # fmt: skip
"""(backbone, method) -> (BWT, FWT) averaged over the six suites, the paper's Sec. 5 (PWM with
progressive experts against TD-MPC2 fine-tuned, both through a frozen pretrained encoder)."""

Row = tuple[str, str, str]  # backbone, suite, variant
METHOD_COLORS = {"ft": "#0173b2", "er": "#de8f05", "ewc": "#029e73", "packnet": "#d55e00",
                 "experts": "#cc78bc"}  # fmt: skip
"""One colour per method in the interval plot (seaborn's colorblind palette)."""


def _num(x: float | None) -> str:
    if x is None:
        return "n/a"
    return f"{x:.1f}" if abs(x) >= 10 else f"{x:.2f}"


def _interval(g: dict, name: str) -> str:
    if g[name] is None:
        return "n/a"
    lo, hi = g[f"{name}_lo"], g[f"{name}_hi"]
    if len(g["seeds"]) == 1 or lo is None:  # one seed, or a resample leaves it undefined
        return _num(g[name])
    return f"{_num(g[name])} [{_num(lo)}, {_num(hi)}]"


def _settings(runs: list[Run]) -> tuple[str, str, str]:
    """(observation, steps per task, preset) of a row's runs."""
    config = runs[0].config
    obs = config.get("obs", "state")
    encoder = str(config.get("encoder") or "")
    if encoder.startswith("frozen:"):
        obs += ", frozen encoder"
    if "fit" in config:
        steps = f"{config['fit']['updates']:,} updates"
    else:
        steps = f"{config['train']['steps']:,}"
    return obs, steps, str(config.get("preset"))


def _planned(grids: dict[Path, dict], runs: list[Run], backbone_model: str, suite: str
             ) -> dict[str, set[int]]:  # fmt: skip
    """method -> seeds the sweeps holding `runs` set out to run for this row."""
    planned: dict[str, set[int]] = defaultdict(set)
    for folder in {r.path.parent for r in runs}:
        grid = grids.get(folder)
        if grid and suite in grid["suites"] and backbone_model in (grid["models"] or []):
            for method in grid["methods"]:
                planned[method] |= set(grid["seeds"])
    return planned


def _status(planned: dict[str, set[int]], done: dict[str, set[int]]) -> str:
    if not planned:
        return "as published (no sweep record)"
    missing = []
    for method in ordered_methods(set(planned) | set(done)):
        want = planned.get(method, set()) | done.get(method, set())
        have = done.get(method, set())
        if not have:
            missing.append(f"{method} not run")
        elif have != want:
            missing.append(f"{method} {len(have)} of {len(want)} seeds")
    return "complete" if not missing else "partial: " + ", ".join(missing)


def headline_table(run_groups: dict, groups: dict, root: Path) -> list[str]:
    """The page's first table (see the module's docstring) and the notes under it."""
    grids = sweep_grids(root)
    methods = ordered_methods(
        {k[2] for k in groups} | {m for g in grids.values() for m in g["methods"]}
    )
    rows: dict[Row, dict[str, tuple]] = defaultdict(dict)
    for key, g in groups.items():
        rows[(key[0], key[1], key[3])][key[2]] = (g, run_groups[key])
    suite_order = {s: i for i, s in enumerate(SUITES)}
    for backbone in PAPER_DESIGN:
        for suite in SUITES:
            if not any(b == backbone and s == suite for b, s, _ in rows):
                rows[(backbone, suite, "")] = {}
    order = sorted(rows, key=lambda r: (r[0].endswith("-offline"), suite_order.get(r[1], 99),
                                        not rows[r], r[0], r[2]))  # fmt: skip
    header = ["suite", "backbone", "observation", "track", "steps / task", "preset", "seeds",
              "status", *methods]  # fmt: skip
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    reasons: dict[str, int] = {}
    for backbone, suite, variant in order:
        cells = rows[(backbone, suite, variant)]
        track = "offline" if backbone.endswith("-offline") else "online"
        model = backbone.removesuffix("-offline").split("+")[0]
        if not cells:
            obs = PAPER_DESIGN[backbone] + (", frozen encoder" if "+" in backbone else "")
            lines.append(f"| {suite} | {model} | {obs} | {track} | | | | not run |"
                         + " |" * len(methods))  # fmt: skip
            continue
        all_runs = [r for _, runs in cells.values() for r in runs]
        obs, steps, preset = _settings(all_runs)
        if variant:
            obs += f" ({variant})"
        done = {m: {r.seed for r in runs} for m, (_, runs) in cells.items()}
        planned = _planned(grids, all_runs, model, suite)
        counts = sorted({len(s) for s in done.values()})
        seeds = str(counts[0]) if len(counts) == 1 else "-".join(map(str, (counts[0], counts[-1])))
        row = [suite, model, obs, track, steps, preset, seeds, _status(planned, done)]
        for method in methods:
            if method not in cells:
                row.append("not run" if method in planned else "")
                continue
            g = cells[method][0]
            text = f"{_interval(g, 'bwt')} / {_interval(g, 'fwt')}"
            if g["bwt"] is None and g.get("bwt_reason"):
                mark = reasons.setdefault(g["bwt_reason"], len(reasons) + 1)
                text += f" ({mark})"
            row.append(text)
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    if reasons:
        lines += [f"({n}) BWT undefined: {reason}." for reason, n in reasons.items()] + [""]
    return lines


SEES_TASK_R2 = 0.5
"""Below this held-out R^2 on every goal and object coordinate, a probed encoder's latent is
said not to hold them (its rows then measure what the arm alone tells)."""


def encoder_notes(run_groups: dict, root: Path) -> list[str]:
    """A line per frozen encoder the runs read whose probe (`ccfit probe-encoder`) is published:
    how well its latent gives the hand and the task's other positions."""
    lines = []
    for probe in sorted(root.glob("probe/*/probe.json")):
        found = json.loads(probe.read_text())
        if found.get("encoder") not in frozen_encoders(run_groups):
            continue
        hand = [v for r in found["rows"] if r["position"] == "hand" for v in r["latent_r2"]]
        task = [v for r in found["rows"] if r["position"] != "hand" for v in r["latent_r2"]]
        where = probe.parent.relative_to(root) / "probe.md"
        text = (
            f"Rows through the frozen encoder `{found['encoder']}`: its latent gives the "
            f"hand with held-out R^2 >= {min(hand):.2f} and the goals and objects with R^2 "
        )
        if max(task) < SEES_TASK_R2:
            text += (
                f"<= {max(task):.2f} ([probe]({where})), so they measure what the arm alone tells"
            )
        else:
            median, share = _spread(task)
            text += (f"{median:.2f} at the median, {share:.0%} of their coordinates >= "
                     f"{SEES_TASK_R2} ([probe]({where}))")  # fmt: skip
            text += _on_their_own(found["rows"])
        lines += [text + ".", ""]
    return lines


def _spread(r2: list[float]) -> tuple[float, float]:
    """(median, share >= SEES_TASK_R2) of probe R^2 values."""
    return float(np.median(r2)), float(np.mean(np.array(r2) >= SEES_TASK_R2))


def _on_their_own(rows: list[dict]) -> str:
    """The goal and object coordinates that the task's other positions do not give (a cube
    under a goal that floats over it does): where a latent's score is evidence of its own. An
    older probe without `others_r2` adds nothing."""
    if not all("others_r2" in r for r in rows):
        return ""
    own = [latent for r in rows if r["position"] != "hand"
           for latent, others in zip(r["latent_r2"], r["others_r2"], strict=True)
           if others is not None and others < SEES_TASK_R2]  # fmt: skip
    if not own:
        return ""
    median, share = _spread(own)
    return (
        f"; of the {len(own)} coordinates that the task's other positions do not give (R^2 < "
        f"{SEES_TASK_R2} from them), {median:.2f} at the median, {share:.0%} >= {SEES_TASK_R2}"
    )


def paper_table(groups: dict) -> list[str]:
    """Ours beside the figures the paper's text gives: its composition-axis table and the
    frozen-encoder comparison's six-suite averages."""
    lines = ["| backbone | averaged over | BWT | FWT | paper BWT | paper FWT |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for c in axis_cells(groups):
        if c["paper"] is None or c["variant"]:
            continue
        suites = sorted({s for s, _ in c["members"]}, key=list(SUITES).index)
        over = f"{c['axis']} axis: {', '.join(suites)}, {len(c['members'])} groups"
        lines.append(f"| {c['backbone']} | {over} | {_num(c['bwt'])} | {_num(c['fwt'])} | "
                     f"{c['paper'][0]:.2f} | {c['paper'][1]:.2f} |")  # fmt: skip
    for (backbone, method), (bwt, fwt) in PAPER_FROZEN.items():
        here = [(k[1], g) for k, g in groups.items()
                if k[0] == backbone and k[2] == method and not k[3]]  # fmt: skip
        if not here:
            continue
        values = {x: [g[x] for _, g in here if g[x] is not None] for x in ("bwt", "fwt")}
        ours = {x: sum(v) / len(v) if v else None for x, v in values.items()}
        over = f"{method}: {', '.join(s for s, _ in here)} (the paper: six suites)"
        lines.append(f"| {backbone} | {over} | {_num(ours['bwt'])} | {_num(ours['fwt'])} | "
                     f"{bwt:.2f} | {fwt:.2f} |")  # fmt: skip
    return lines


AGGREGATE_TEXT = (
    "rliable's interquartile mean (IQM) of each method's per-seed BWT and FWT over the suites "
    "it ran on the same seeds (seeds x suites, the middle half of the values), with its 95% "
    "stratified-bootstrap CI: one number per method and backbone that one suite or one seed "
    "cannot swing. Over the most suites that share two seeds or more, on those seeds (a suite "
    "run on more seeds counts on the shared ones only)."
)


def _shared_seeds(seeds_of: dict[str, list[int]]) -> tuple[list[str], list[int]]:
    """The most suites of `seeds_of` (suite -> its seeds) that share two seeds or more, and
    the seeds they share (most shared seeds among as many suites; suites in `SUITES` order).
    A suite run on more seeds than the others counts on the shared ones only."""
    names = [s for s in SUITES if s in seeds_of]
    best: tuple[list[str], list[int]] = ([], [])
    for n in range(len(names), 1, -1):
        for chosen in itertools.combinations(names, n):
            shared = sorted(set.intersection(*(set(seeds_of[s]) for s in chosen)))
            if len(shared) >= 2 and len(shared) > len(best[1]):
                best = (list(chosen), shared)
        if best[0]:
            return best
    return best


def aggregate_table(groups: dict) -> list[str]:
    """The IQM of every online backbone's methods over suites (`AGGREGATE_TEXT`)."""
    lines = ["| backbone | method | suites | seeds | IQM BWT [95% CI] | IQM FWT [95% CI] |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    cells = defaultdict(dict)
    for (backbone, suite, method, variant), g in groups.items():
        if not backbone.endswith("-offline") and not variant:
            cells[(backbone, method)][suite] = g
    for (backbone, method), by_suite in sorted(
        cells.items(), key=lambda kv: (kv[0][0], method_rank(kv[0][1]))
    ):
        defined = {s: g for s, g in by_suite.items()
                   if all(v is not None for x in ("bwt", "fwt")
                          for v in g[f"{x}_per_seed"].values())}  # fmt: skip
        suites, seeds = _shared_seeds({s: g["seeds"] for s, g in defined.items()})
        if len(suites) < 2:
            continue
        cell = []
        for x in ("bwt", "fwt"):
            scores = np.array([[defined[s][f"{x}_per_seed"][seed] for s in suites]
                               for seed in seeds])  # fmt: skip
            iqm = iqm_interval(scores)
            cell.append(f"{_num(iqm.value)} [{_num(iqm.lo)}, {_num(iqm.hi)}]")
        lines.append(f"| {backbone} | {method} | {', '.join(suites)} | {len(seeds)} | "
                     f"{cell[0]} | {cell[1]} |")  # fmt: skip
    return lines if len(lines) > 2 else []


def orderings_summary(groups: dict) -> list[str]:
    """The online orderings' verdicts (the values and the offline rows: `orderings.md`)."""
    header = ("ordering", "backbone", "suite", "holds (seed-averaged curves)",
              "holds (mean of per-seed metrics)", "on every seed", "P(holds) [95% CI]")  # fmt: skip
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, row in ordering_rows(groups):
        if not is_offline(row):
            lines.append(f"| {name} | {' | '.join(row[:6])} |")
    return lines


def plot_intervals(groups: dict, out: Path) -> Path | None:
    """rliable's interval plot of every online group: BWT and FWT with their 95% CIs; None
    (nothing drawn) without an online group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rliable import plot_utils

    suite_order = list(SUITES)
    online = sorted(((k, g) for k, g in groups.items() if not k[0].endswith("-offline")),
                    key=lambda kg: (suite_order.index(kg[0][1]), kg[0][0], kg[0][3],
                                    method_rank(kg[0][2])))  # fmt: skip
    if not online:
        return None
    names, points, intervals, colors = [], {}, {}, {}
    for (backbone, suite, method, variant), g in online:
        name = f"{suite} {backbone} {method}" + (f" [{variant}]" if variant else "")
        names.append(name)
        colors[name] = METHOD_COLORS.get(method, "0.5")
        points[name] = np.array([np.nan if g[x] is None else g[x] for x in ("bwt", "fwt")])
        bounds = [[g[x] if g[f"{x}_lo"] is None else g[f"{x}_{end}"] for x in ("bwt", "fwt")]
                  for end in ("lo", "hi")]  # fmt: skip
        intervals[name] = np.array(bounds, dtype=float)
    # rliable draws its first algorithm at the bottom: reversed, the figure reads as the table
    fig, _ = plot_utils.plot_interval_estimates(
        points, intervals, metric_names=["BWT (lower: less forgetting)", "FWT (higher)"],
        algorithms=names[::-1], colors=colors, xlabel="score points", subfigure_width=4.0,
    )  # fmt: skip
    path = out / INTERVALS_PNG
    fig.savefig(path, dpi=90, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    return path


INTRO = (
    "The toolkit's published numbers, generated by `ccfit report results/` from the runs under "
    "this folder (do not edit by hand). Each cell is **BWT / FWT** (BWT: lower forgets less; "
    "FWT: higher transfers more) of the seed-averaged curves, the paper's convention, with its "
    "95% stratified-bootstrap CI over seeds (rliable). Online the curves are normalised returns "
    "(0 = failure, 100 = the scripted oracle); offline they are the world model's open-loop "
    "prediction score on held-out dataset episodes, a measure of fidelity, not of returns. "
    "Status: complete (every run its sweep's grid names is here), partial (what is missing), "
    "not run (a row of the paper's design with no run here)."
)
PAPER_TEXT = (
    "The paper's text gives its composition-axis table (each backbone's BWT and FWT averaged "
    "over FT, ER, EWC and PackNet and the two suites of an axis) and the frozen-encoder "
    "comparison's averages over six suites; its per-suite figures are bars only. Its numbers "
    "are from pixels at its own scale, ours from the settings in each row: they compare in "
    "direction more than in size. [axes.md](axes.md) lists each axis cell's groups."
)
ORDERINGS_TEXT = (
    "Each of the paper's findings, checked where the runs it needs are here, under both "
    "conventions (the metric of the seed-averaged curves; the mean of the per-seed metrics), on "
    "every seed, and as rliable's probability of improvement of the ordering's weakest pair. "
    f"The values with their CIs, the offline rows and the reasons a metric is undefined: "
    f"[{ORDERINGS_MD}]({ORDERINGS_MD})."
)
REPRODUCE_TEXT = (
    "A published run made again by the same code on the same kind of CPU (model and vector "
    "instruction set; `cost.json` records the machine of each segment) equals it evaluation for "
    "evaluation: `ccfit compare PUBLISHED RERUN` says so or names the first record that "
    "differs. Elsewhere a rerun's records part after the first updates; its group's BWT and FWT "
    "should then land within the CIs above. A sweep resumes where it stopped, and a folder "
    "copied here to its `--out` counts as done, so only what is missing runs "
    f"([{NOTES}]({NOTES}#reproducing-and-resuming-a-sweep) says more). The commands that made "
    "every sweep published here:"
)


def _reports(root: Path) -> list[str]:
    folders = [f.relative_to(root) for f in published_folders(root)]
    return [f"[{f}]({f}/{REPORT}/)" for f in folders]


def page_text(run_groups: dict, groups: dict, root: Path, figure: bool = True) -> str:
    """The page (module docstring); `figure`: whether `INTERVALS_PNG` was drawn beside it."""
    aggregate = aggregate_table(groups)
    lines = ["# Reference results", "", INTRO, ""]
    lines += headline_table(run_groups, groups, root) + encoder_notes(run_groups, root)
    lines += ["## Beside the paper", "", PAPER_TEXT, "", *paper_table(groups), ""]
    lines += ["## The paper's orderings", "", ORDERINGS_TEXT, "", *orderings_summary(groups), ""]
    lines += [
        "## Figures", "",
        *([f"![BWT and FWT with 95% CIs, every online group]({INTERVALS_PNG})", ""]
          if figure else []),
        *([AGGREGATE_TEXT, "", *aggregate, ""] if aggregate else []),
        "Each published folder's `report/` holds its tables (with Continual World's "
        "forgetting F), bars, every task's curves, and `stages.md`: each task's score stage "
        "by stage, every end-of-task score C_i with its standard error where its records "
        "hold the episodes' returns. " + ", ".join(_reports(root)) + ".", "",
        "## Reproducing", "", REPRODUCE_TEXT, "", "```bash",
        *setup_commands(run_groups, root), *sweep_commands(root),
        f"ccfit report {root.name}/   # this page", "```", "",
        "## Also here", "",
        f"- [{NOTES}]({NOTES}): what each sweep showed beyond its numbers, the diagnostics "
        "and what is not published yet.",
        "- [cost.md](cost.md): CPU-hours per run and group, and the machines that ran them.",
        "- [axes.md](axes.md), [orderings.md](orderings.md): the tables above in full.",
    ]  # fmt: skip
    for name, what in (("single-task", "single-task runs and the learnability tables"),
                       ("probe", "what the frozen encoder's latent holds"),
                       ("diagnostics", "the scripts and outputs the notes cite")):  # fmt: skip
        if (root / name).is_dir():
            lines.append(f"- [{name}/]({name}/): {what}.")
    return "\n".join(lines) + "\n"


def write_page(root: Path) -> list[Path]:
    """The results page over every finished run under `root`, with the overview it links to
    (`orderings.md`, `axes.md`, `cost.md`) and the interval plot. Returns the files written."""
    run_groups, groups = grouped([root])
    written = write_overview(run_groups, groups, root)
    figure = plot_intervals(groups, root)
    path = root / PAGE
    atomic_write_text(path, page_text(run_groups, groups, root, figure is not None))
    return [*written, *([figure] if figure else []), path]
