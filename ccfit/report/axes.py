"""`ccfit report`'s `axes.md`: the paper's Table "Performance by composition axis" on the
runs at hand.

The paper averages BWT and FWT over the four continual methods (FT, ER, EWC, PackNet) and the
two suites of each composition axis (action: Reach and Grasp; perception: BinPnP and
PnPBlock; full: DrawerPnP and PnPBoxClose), per backbone. Here each cell averages the groups
present of one online backbone and variant (`ccfit.report.load_groups`: the metrics of
seed-averaged curves) and names what it averaged, so that a cell made of one suite, or of
fewer methods, reads as such; the paper's figure stands beside it. A group whose metric is
undefined (BWT with no earlier task learnt above the floor) is left out of that metric's mean
and named, and so is a suite whose runs from state meet one task again where the suite changes
only a colour (`Suite.same_from_state`): there they do not measure the perception axis.
"""

from __future__ import annotations

from pathlib import Path

from ccdata.suites import AXES, SUITES
from ccfit.io import atomic_write_text
from ccfit.report.plots import row_label

AXES_MD = "axes.md"
AXIS_METHODS = ("ft", "er", "ewc", "packnet")
"""The methods the paper's table averages over."""
PAPER_AXES: dict[tuple[str, str], tuple[float, float]] = {
    ("dreamerv3", "action"): (5.94, 21.56),
    ("dreamerv3", "perception"): (11.79, 24.52),
    ("dreamerv3", "full"): (30.12, 15.54),
    ("tdmpc2", "action"): (32.15, 16.76),
    ("tdmpc2", "perception"): (57.81, -1.88),
    ("tdmpc2", "full"): (68.68, 1.54),
}
"""(backbone, axis) -> (BWT, FWT) in the paper's Table "Performance by composition axis"
(pixels, the paper's scale, each the mean over four methods and two suites)."""


def axis_suites(axis: str) -> list[str]:
    return [name for name, suite in SUITES.items() if suite.axis == axis]


def axis_cells(groups: dict) -> list[dict]:
    """One cell per (online backbone, variant, axis) with a group of the paper's methods on a
    suite of that axis: the mean BWT and FWT over those groups and what went into each."""
    cells = []
    scopes = sorted({(k[0], k[3]) for k in groups if not k[0].endswith("-offline")})
    for backbone, variant in scopes:
        for axis in AXES:
            members = {(suite, method): groups[(backbone, suite, method, variant)]
                       for suite in axis_suites(axis) for method in AXIS_METHODS
                       if (backbone, suite, method, variant) in groups}  # fmt: skip
            if not members:
                continue
            cell = {
                "backbone": backbone, "variant": variant, "axis": axis,
                "members": list(members), "paper": PAPER_AXES.get((backbone, axis)),
                "same_from_state": sorted({s for (s, _), g in members.items()
                                           if g.get("obs") == "state"
                                           and SUITES[s].same_from_state}),
            }  # fmt: skip
            for metric in ("bwt", "fwt"):
                values = [g[metric] for g in members.values() if g[metric] is not None]
                cell[metric] = sum(values) / len(values) if values else None
                cell[f"{metric}_undefined"] = [k for k, g in members.items() if g[metric] is None]
            cells.append(cell)
    return cells


def _number(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _averaged(cell: dict) -> str:
    """'Reach: ft, er, ewc, packnet; Grasp: ft, er (2 of 2 suites, 6 of 8 groups)'."""
    suites = axis_suites(cell["axis"])
    by_suite = {s: [m for t, m in cell["members"] if t == s] for s in suites}
    parts = [f"{s}: {', '.join(ms)}" for s, ms in by_suite.items() if ms]
    present = sum(1 for ms in by_suite.values() if ms)
    text = (f"{'; '.join(parts)} ({present} of {len(suites)} suites, {len(cell['members'])} of "
            f"{len(suites) * len(AXIS_METHODS)} groups)")  # fmt: skip
    for metric in ("bwt", "fwt"):
        if cell[f"{metric}_undefined"]:
            left = ", ".join(f"{s} {m}" for s, m in cell[f"{metric}_undefined"])
            text += f"; {metric.upper()} undefined for {left}"
    for suite in cell["same_from_state"]:
        text += f"; {suite} from state: {SUITES[suite].same_from_state_text()} are one task"
    return text


def write_axes(groups: dict, out: Path) -> Path:
    """`axes.md` over `groups`: the composition-axis table, each cell beside the paper's."""
    lines = [
        "# BWT and FWT by composition axis, beside the paper's",
        "",
        'The paper\'s Table "Performance by composition axis": per backbone, BWT (lower '
        "forgets less) and FWT (higher transfers more) averaged over FT, ER, EWC and PackNet "
        "and the two suites of each axis. Here each value averages the groups these runs hold "
        "(the metric of each group's seed-averaged curves), and the last column says which; "
        "the paper's figures are from pixels at its own scale, so they compare in direction "
        "more than in size.",
        "",
        "| backbone | axis | BWT | FWT | paper BWT | paper FWT | averaged over |",
        "|---|---|---|---|---|---|---|",
    ]
    cells = axis_cells(groups)
    for c in cells:
        paper = c["paper"] or (None, None)
        lines.append(f"| {row_label(c['backbone'], c['variant'])} | {c['axis']} | "
                     f"{_number(c['bwt'])} | {_number(c['fwt'])} | {_number(paper[0])} | "
                     f"{_number(paper[1])} | {_averaged(c)} |")  # fmt: skip
    if not cells:
        lines.append("| (no online run of FT, ER, EWC or PackNet here) | | | | | | |")
    path = out / AXES_MD
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
