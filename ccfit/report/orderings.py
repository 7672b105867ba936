"""`ccfit report`'s `orderings.md`: the paper's four findings, checked on the runs at hand.

The paper states (Sec. 5, Appendix B) that PackNet forgets least and FT most, that ER
transfers most, that DreamerV3 forgets less than TD-MPC2 under every method, and that PWM
with progressive experts forgets far less than TD-MPC2 under the same frozen encoder. Each is
checked where the groups it needs exist (`ccfit.report.load_groups`: metrics of the
seed-averaged curves, [min, max] over seeds), on BWT (forgetting) or FWT (transfer) as the
paper does. A comparison with a BWT that is undefined (no earlier task learnt above the
floor) is 'n/a'. Whether the verdict survives the seed spread is for the reader: every value
is printed with its [min, max].
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

from ccfit.io import atomic_write_text
from ccfit.report.plots import metric_cell, ordered_methods, row_label

Group = dict
Key = tuple[str, str, str, str]  # backbone, suite, method, variant
Row = tuple[str, str, str, str]  # backbones, suite [variant], verdict, evidence

ORDERINGS_MD = "orderings.md"
TRACK_SUFFIXES = ("", "-offline")
"""Backbone label endings of the two tracks (`ccfit.report.runs.Run.backbone`): a comparison
across backbones stays inside one track."""


def _scopes(groups: dict[Key, Group]) -> dict[tuple[str, str, str], dict[str, Group]]:
    """(backbone, suite, variant) -> method -> group."""
    out: dict[tuple[str, str, str], dict[str, Group]] = {}
    for (backbone, suite, method, variant), g in sorted(groups.items()):
        out.setdefault((backbone, suite, variant), {})[method] = g
    return out


def _ranked(methods: dict[str, Group], metric: str, descending: bool) -> str:
    order = sorted(methods, key=lambda m: methods[m][metric], reverse=descending)
    sign = " > " if descending else " < "
    return f"{metric.upper()} " + sign.join(f"{m} {metric_cell(methods[m], metric)}" for m in order)


def _undefined(methods: dict[str, Group], metric: str) -> list[str]:
    return [m for m, g in methods.items() if g[metric] is None]


def _within_backbones(groups: dict[Key, Group], metric: str, needs: set[str],
                      holds: Callable[[dict[str, float]], bool], descending: bool
                      ) -> Iterator[Row]:  # fmt: skip
    """A row per (backbone, suite, variant) with the methods `needs` and one more at least:
    whether `holds(metric per method)`, the methods ranked by `metric`."""
    for (backbone, suite, variant), methods in _scopes(groups).items():
        if not needs <= set(methods) or len(methods) < 2:
            continue
        label = row_label(suite, variant)
        missing = _undefined(methods, metric)
        if missing:
            yield backbone, label, "n/a", f"{metric.upper()} undefined for {', '.join(missing)}"
            continue
        verdict = holds({m: g[metric] for m, g in methods.items()})
        yield backbone, label, "yes" if verdict else "no", _ranked(methods, metric, descending)


def packnet_least_ft_most(groups: dict[Key, Group]) -> Iterator[Row]:
    def holds(bwt: dict[str, float]) -> bool:
        return bwt["packnet"] == min(bwt.values()) and bwt["ft"] == max(bwt.values())

    yield from _within_backbones(groups, "bwt", {"ft", "packnet"}, holds, descending=False)


def er_transfers_most(groups: dict[Key, Group]) -> Iterator[Row]:
    def holds(fwt: dict[str, float]) -> bool:
        return fwt["er"] == max(fwt.values())

    yield from _within_backbones(groups, "fwt", {"er"}, holds, descending=True)


Pairs = Callable[[set[str], set[str]], list[tuple[str, str]]]
"""(methods of one backbone, of the other) -> the (method, method) pairs to compare."""


def _less_bwt(groups: dict[Key, Group], lower: str, higher: str, pairs: Pairs) -> Iterator[Row]:
    """Rows of 'backbone `lower` forgets less than `higher`' for every suite (and pair of
    variants) both have, comparing the methods `pairs(lower's, higher's)` names."""
    scopes = _scopes(groups)
    for suffix in TRACK_SUFFIXES:
        a, b = lower + suffix, higher + suffix
        for (backbone, suite, va), ma in scopes.items():
            if backbone != a:
                continue
            for (other, suite_b, vb), mb in scopes.items():
                if other != b or suite_b != suite:
                    continue
                compared = pairs(set(ma), set(mb))
                if not compared:
                    continue
                label = suite + "".join(f" [{n}: {v}]" for n, v in ((a, va), (b, vb)) if v)
                undefined = [f"{a} {m}" for m, _ in compared if ma[m]["bwt"] is None]
                undefined += [f"{b} {n}" for _, n in compared if mb[n]["bwt"] is None]
                evidence = "; ".join(
                    f"{m} {metric_cell(ma[m], 'bwt')} vs "
                    + ", ".join(f"{n} {metric_cell(mb[n], 'bwt')}" for k, n in compared if k == m)
                    for m in dict.fromkeys(m for m, _ in compared)
                )
                if undefined:
                    verdict = "n/a"
                    evidence = f"BWT undefined for {', '.join(undefined)}; {evidence}"
                else:
                    holds = all(ma[m]["bwt"] < mb[n]["bwt"] for m, n in compared)
                    verdict = "yes" if holds else "no"
                yield f"{a} vs {b}", label, verdict, "BWT " + evidence


def _same_methods(a: set[str], b: set[str]) -> list[tuple[str, str]]:
    return [(m, m) for m in ordered_methods(a & b)]


def _experts_against_ft(a: set[str], b: set[str]) -> list[tuple[str, str]]:
    return [("experts", "ft")] if "experts" in a and "ft" in b else []


def dreamerv3_forgets_less(groups: dict[Key, Group]) -> Iterator[Row]:
    """Under every method both backbones ran."""
    yield from _less_bwt(groups, "dreamerv3", "tdmpc2", _same_methods)


def pwm_experts_forgets_less(groups: dict[Key, Group]) -> Iterator[Row]:
    """PWM with experts against TD-MPC2 fine-tuned, both through a frozen encoder: the paper's
    comparison (its Sec. 5 sets PWM's BWT and FWT against TD-MPC2's under fine-tuning)."""
    yield from _less_bwt(groups, "pwm+frozen-enc", "tdmpc2+frozen-enc", _experts_against_ft)


ORDERINGS: dict[str, Callable[[dict[Key, Group]], Iterator[Row]]] = {
    "PackNet forgets least, FT most": packnet_least_ft_most,
    "ER transfers most": er_transfers_most,
    "DreamerV3 forgets less than TD-MPC2 under every method": dreamerv3_forgets_less,
    "PWM with experts forgets far less than TD-MPC2 under the frozen encoder":
        pwm_experts_forgets_less,
}  # fmt: skip
"""The paper's orderings, each with the rows it yields on a report's groups."""


def ordering_rows(groups: dict[Key, Group]) -> list[tuple[str, Row]]:
    return [(name, row) for name, check in ORDERINGS.items() for row in check(groups)]


def write_orderings(groups: dict[Key, Group], out: Path) -> Path:
    """`orderings.md` over `groups`: one line per ordering and place it can be checked, and
    the orderings no group here can check."""
    rows = ordering_rows(groups)
    lines = [
        "# The paper's orderings on these runs",
        "",
        "Each finding of the paper checked on the metrics of the seed-averaged curves (BWT: "
        "lower forgets less; FWT: higher transfers more), where the runs it needs are here; "
        "[min, max] over seeds beside each value. A verdict is the order of the means: "
        "'most', 'least' and 'far less' are checked as the strict order.",
        "",
        "| ordering | backbone | suite | holds | values |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {name} | {' | '.join(row)} |" for name, row in rows]
    unchecked = [name for name in ORDERINGS if name not in {n for n, _ in rows}]
    if unchecked:
        lines += ["", "Not checkable on these runs: " + "; ".join(unchecked) + "."]
    path = Path(out) / ORDERINGS_MD
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
