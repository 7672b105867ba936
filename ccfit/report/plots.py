"""`ccfit report`'s figures: BWT / FWT bars per backbone (the paper's Fig. 4) and each group's
learning curves with the forgetting and forward-transfer regions shaded.

Groups are keyed (backbone, suite, method, variant) as in `ccfit.report`; the variant (the
settings that tell groups apart, '' when none do) is part of every label and file name.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ccfit import metrics as M
from ccfit.io import save_figure


def row_label(suite: str, variant: str) -> str:
    return f"{suite} [{variant}]" if variant else suite


def metric_cell(g: dict, name: str, convention: str = "") -> str:
    """A group's metric as tables print it: the metric of the seed-averaged curves (the paper's
    convention; `convention="_seed_mean"`: the mean of the per-seed metrics) and its 95%
    bootstrap CI over seeds when there are several (naming how many seeds define it where some
    do not), 'n/a' with the reason when undefined."""
    value = g[f"{name}{convention}"]
    if value is None:
        reason = g.get(f"{name}_reason")
        return f"n/a ({reason})" if reason and not convention else "n/a"
    if len(g["seeds"]) == 1:
        return f"{value:.2f}"
    defined = g[f"{name}_seeds_defined"]
    of = "" if defined == len(g["seeds"]) else f"; {defined} of {len(g['seeds'])} seeds"
    lo, hi = g[f"{name}{convention}_lo"], g[f"{name}{convention}_hi"]
    ci = "CI n/a" if lo is None or hi is None else f"{lo:.2f}, {hi:.2f}"
    return f"{value:.2f} [{ci}{of}]"


def slug(variant: str) -> str:
    """A file-name-safe form of a variant label."""
    return re.sub(r"[^A-Za-z0-9.=+-]+", "_", variant).strip("_")


METHOD_ORDER = ("ft", "er", "ewc", "packnet", "experts")
"""Column order of methods in tables and plots (others follow, sorted)."""


def method_rank(method: str) -> int:
    """Where `method` sorts among the methods (`METHOD_ORDER`; others after them)."""
    return METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER)


def ordered_methods(methods) -> list[str]:
    """`methods` in `METHOD_ORDER`, others after it, sorted."""
    present = set(methods)
    return [m for m in METHOD_ORDER if m in present] + sorted(present - set(METHOD_ORDER))


def method_columns(groups: dict, backbone: str) -> list[str]:
    return ordered_methods(k[2] for k in groups if k[0] == backbone)


def plot_bars(groups: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for backbone in sorted({k[0] for k in groups}):
        rows = sorted({(k[1], k[3]) for k in groups if k[0] == backbone})
        methods = method_columns(groups, backbone)
        fig, axes = plt.subplots(
            1, 2, figsize=(4 + 1.6 * len(rows), 3.6 + 0.4 * any(v for _, v in rows))
        )
        width = 0.8 / max(len(methods), 1)
        for ax, name, better in zip(axes, ("bwt", "fwt"), ("lower", "higher"), strict=True):
            for k, m in enumerate(methods):
                xs, ys, lows, highs = [], [], [], []
                for r, (suite, variant) in enumerate(rows):
                    g = groups.get((backbone, suite, m, variant))
                    if g is None or g[name] is None:
                        continue
                    xs.append(r + (k - (len(methods) - 1) / 2) * width)
                    ys.append(g[name])
                    # One seed, or a CI undefined on some resample: no whisker.
                    lows.append(g[name] if g[f"{name}_lo"] is None else g[f"{name}_lo"])
                    highs.append(g[name] if g[f"{name}_hi"] is None else g[f"{name}_hi"])
                ax.bar(xs, ys, width, label=m)
                # The whisker is the 95% bootstrap CI of the bar's value (the seed-averaged
                # curves' metric).
                lows, highs = np.asarray(lows, dtype=float), np.asarray(highs, dtype=float)
                ax.errorbar(xs, (lows + highs) / 2, yerr=(highs - lows) / 2, fmt="none",
                            ecolor="k", elinewidth=0.8, capsize=2)  # fmt: skip
            ax.set_xticks(
                range(len(rows)),
                [row_label(s, v) for s, v in rows],
                rotation=20,
                ha="right",
                fontsize=8,
            )
            ax.set_title(f"{name.upper()} ({better} is better)")
            ax.axhline(0, color="k", lw=0.5)
        axes[1].legend(fontsize=8)
        fig.suptitle(backbone)
        fig.tight_layout()
        path = out / f"bars_{backbone}.png"
        save_figure(fig, path)
        plt.close(fig)
        written.append(path)
    return written


TASK_COLOURS = (
    "tab:blue",
    "tab:orange",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
    "tab:gray",
)
"""Task curves and their forgetting shading; green and red are left to the FWT shading alone."""


def plot_curves(key: tuple, g: dict, task_ids: list[str], out: Path) -> Path:
    """Every task's normalised return over the curriculum for group `key` (backbone, suite,
    method[, variant])."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    backbone, suite, method, *rest = key
    variant = rest[0] if rest else ""
    fig, ax = plt.subplots(figsize=(8, 3.8))
    colours = TASK_COLOURS
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
    bwt, fwt = g["bwt"], g["fwt"]
    title = f"{suite} / {backbone} / {method}" + (f" [{variant}]" if variant else "")
    ax.set_title(f"{title}: BWT {bwt if bwt is None else round(bwt, 2)}, "
                 f"FWT {fwt if fwt is None else round(fwt, 2)} (seeds {g['seeds']})",
                 fontsize=9 if variant else None)  # fmt: skip
    offline = g.get("track") == "offline"
    ax.set_xlabel("global update (offline)" if offline else "global step")
    ax.set_ylabel("prediction score (0 = persistence)" if offline else "normalised return")
    ax.legend(fontsize=7, ncol=2, loc="best")
    fig.tight_layout()
    name = f"curves_{backbone}_{suite}_{method}" + (f"_{slug(variant)}" if variant else "")
    path = out / f"{name}.png"
    save_figure(fig, path)
    plt.close(fig)
    return path
