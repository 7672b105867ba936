"""`ccfit report`'s `orderings.md`: the paper's four findings, checked on the runs at hand.

The paper states (Sec. 5, Appendix B) that PackNet forgets least and FT most, that ER
transfers most, that DreamerV3 forgets less than TD-MPC2 under every method, and that PWM
with progressive experts forgets far less than TD-MPC2 under the same frozen encoder. Each is
checked where the groups it needs exist (`ccfit.report.load_groups`), on BWT (forgetting) or
FWT (transfer) as the paper does, under both conventions (the metric of the seed-averaged
curves, the mean of per-seed metrics), on every seed, and as rliable's probability of
improvement of its weakest pair. A comparison with an undefined metric is 'n/a' with the
metric code's reason. Offline rows (prediction fidelity) are kept apart from online ones.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from ccfit.io import atomic_write_text
from ccfit.report.plots import metric_cell, ordered_methods, row_label
from ccfit.report.stats import probability_of_improvement

Group = dict
Key = tuple[str, str, str, str]  # backbone, suite, method, variant
Row = tuple[str, ...]
"""backbones, suite [variant], then one cell per `COLUMNS` entry."""

ORDERINGS_MD = "orderings.md"
TRACK_SUFFIXES = ("", "-offline")
"""Backbone label endings of the two tracks (`ccfit.report.runs.Run.backbone`): a comparison
across backbones stays inside one track."""
CONVENTIONS = {"": "seed-averaged curves", "_seed_mean": "mean of per-seed metrics"}
"""How a group's metric is read (`ccfit.report.stats`): the paper's convention first."""
COLUMNS = ("holds (seed-averaged curves)", "holds (mean of per-seed metrics)", "on every seed",
           "P(holds) [95% CI]", "values (seed-averaged curves [95% CI])",
           "per-seed means [95% CI]")  # fmt: skip


@dataclass(frozen=True)
class Check:
    """One place an ordering can be checked: `members` (name -> group) and the (better,
    worse) pairs of member names it asserts on `metric`, each pair strictly."""

    backbone: str
    scope: str
    metric: str
    members: dict[str, Group]
    pairs: list[tuple[str, str]]
    describe: Callable[[str], str]
    """convention -> the members' values as the row prints them."""

    @property
    def lower_is_better(self) -> bool:
        return self.metric != "fwt"

    def _better(self, a: float, b: float) -> bool:
        return a < b if self.lower_is_better else a > b

    def _holds(self, value: Callable[[str], float]) -> bool:
        return all(self._better(value(a), value(b)) for a, b in self.pairs)

    def _involved(self) -> list[str]:
        return list(dict.fromkeys(name for pair in self.pairs for name in pair))

    def verdict(self, convention: str) -> str:
        key = f"{self.metric}{convention}"
        if any(self.members[m][key] is None for m in self._involved()):
            return "n/a"
        return "yes" if self._holds(lambda m: self.members[m][key]) else "no"

    def every_seed(self) -> str:
        """Whether it holds on each seed all its members ran (their seeds' own metrics)."""
        per_seed = {m: self.members[m][f"{self.metric}_per_seed"] for m in self._involved()}
        seeds = set.intersection(*(
            {s for s, v in values.items() if v is not None} for values in per_seed.values()
        ))  # fmt: skip
        if not seeds:
            return "n/a"
        held = sum(self._holds(lambda m, s=s: per_seed[m][s]) for s in seeds)
        return f"{'yes' if held == len(seeds) else 'no'} ({held} of {len(seeds)})"

    def probability(self) -> str:
        """The probability of improvement of the weakest pair (rliable): a seed of the better
        member beats a seed of the worse one; the ordering holds at most as often."""
        weakest = None
        for a, b in self.pairs:
            values = [[v for v in self.members[m][f"{self.metric}_per_seed"].values()
                       if v is not None] for m in (a, b)]  # fmt: skip
            p = probability_of_improvement(*values, lower_is_better=self.lower_is_better)
            if p is None:
                return "n/a"
            if weakest is None or p.value < weakest[0].value:
                weakest = (p, a, b)
        p, a, b = weakest
        sign = " < " if self.lower_is_better else " > "
        return f"{p.cell()} ({a}{sign}{b})"

    def row(self) -> Row:
        undefined = [m for m in self._involved() if self.members[m][self.metric] is None]
        if undefined:
            by_reason: dict[str, list[str]] = {}
            for m in undefined:
                reason = self.members[m].get(f"{self.metric}_reason") or "no reason recorded"
                by_reason.setdefault(reason, []).append(m)
            values = f"{self.metric.upper()} undefined for " + "; ".join(
                f"{', '.join(ms)}: {reason}" for reason, ms in by_reason.items()
            )
        else:
            values = self.describe("")
        return (
            self.backbone,
            self.scope,
            *(self.verdict(c) for c in CONVENTIONS),
            self.every_seed(),
            self.probability(),
            values,
            self.describe("_seed_mean"),
        )


def _scopes(groups: dict[Key, Group]) -> dict[tuple[str, str, str], dict[str, Group]]:
    """(backbone, suite, variant) -> method -> group."""
    out: dict[tuple[str, str, str], dict[str, Group]] = {}
    for (backbone, suite, method, variant), g in sorted(groups.items()):
        out.setdefault((backbone, suite, variant), {})[method] = g
    return out


def _ranked(methods: dict[str, Group], metric: str, descending: bool) -> Callable[[str], str]:
    def describe(convention: str) -> str:
        key = f"{metric}{convention}"
        defined = [m for m in methods if methods[m][key] is not None]
        order = sorted(defined, key=lambda m: methods[m][key], reverse=descending)
        sign = " > " if descending else " < "
        text = f"{metric.upper()} " + sign.join(
            f"{m} {metric_cell(methods[m], metric, convention)}" for m in order
        )
        undefined = [m for m in methods if m not in defined]
        if undefined:
            text += ("; " if defined else "") + f"undefined for {', '.join(undefined)}"
        return text

    return describe


MethodPairs = Callable[[set[str]], list[tuple[str, str]]]
"""A scope's methods -> the (better, worse) pairs an ordering asserts among them."""


def _within_backbones(groups: dict[Key, Group], metric: str, needs: set[str],
                      pairs: MethodPairs) -> Iterator[Check]:  # fmt: skip
    """A check per (backbone, suite, variant) with the methods `needs` and one more at least,
    of the (better, worse) `pairs(methods)`."""
    for (backbone, suite, variant), methods in _scopes(groups).items():
        if not needs <= set(methods) or len(methods) < 2:
            continue
        yield Check(backbone, row_label(suite, variant), metric, methods, pairs(set(methods)),
                    _ranked(methods, metric, descending=metric == "fwt"))  # fmt: skip


def packnet_least_ft_most(groups: dict[Key, Group]) -> Iterator[Check]:
    def pairs(methods: set[str]) -> list[tuple[str, str]]:
        others = ordered_methods(methods - {"packnet", "ft"})
        return ([("packnet", m) for m in others] + [("packnet", "ft")]
                + [(m, "ft") for m in others])  # fmt: skip

    yield from _within_backbones(groups, "bwt", {"ft", "packnet"}, pairs)


def er_transfers_most(groups: dict[Key, Group]) -> Iterator[Check]:
    def pairs(methods: set[str]) -> list[tuple[str, str]]:
        return [("er", m) for m in ordered_methods(methods - {"er"})]

    yield from _within_backbones(groups, "fwt", {"er"}, pairs)


Pairs = Callable[[set[str], set[str]], list[tuple[str, str]]]
"""(methods of one backbone, of the other) -> the (method, method) pairs to compare."""


def _less_bwt(groups: dict[Key, Group], lower: str, higher: str, pairs: Pairs
              ) -> Iterator[Check]:  # fmt: skip
    """Checks of 'backbone `lower` forgets less than `higher`' for every suite (and pair of
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
                if not compared or _encoder(ma) != _encoder(mb):
                    continue
                label = suite + "".join(f" [{n}: {v}]" for n, v in ((a, va), (b, vb)) if v)
                members = {f"{a} {m}": ma[m] for m, _ in compared}
                members |= {f"{b} {n}": mb[n] for _, n in compared}

                def describe(convention: str, compared=compared, ma=ma, mb=mb) -> str:
                    return "BWT " + "; ".join(
                        f"{m} {metric_cell(ma[m], 'bwt', convention)} vs "
                        f"{n} {metric_cell(mb[n], 'bwt', convention)}"
                        for m, n in compared
                    )

                yield Check(f"{a} vs {b}", label, "bwt", members,
                            [(f"{a} {m}", f"{b} {n}") for m, n in compared], describe)  # fmt: skip


def _encoder(methods: dict[str, Group]):
    """The frozen encoder a scope's groups read (None: none); two backbones compare only
    through the same one."""
    return next(iter(methods.values())).get("encoder")


def _same_methods(a: set[str], b: set[str]) -> list[tuple[str, str]]:
    return [(m, m) for m in ordered_methods(a & b)]


def _experts_against_ft(a: set[str], b: set[str]) -> list[tuple[str, str]]:
    return [("experts", "ft")] if "experts" in a and "ft" in b else []


def dreamerv3_forgets_less(groups: dict[Key, Group]) -> Iterator[Check]:
    """Under every method both backbones ran."""
    yield from _less_bwt(groups, "dreamerv3", "tdmpc2", _same_methods)


def pwm_experts_forgets_less(groups: dict[Key, Group]) -> Iterator[Check]:
    """PWM with experts against TD-MPC2 fine-tuned, both through a frozen encoder: the paper's
    comparison (its Sec. 5 sets PWM's BWT and FWT against TD-MPC2's under fine-tuning)."""
    yield from _less_bwt(groups, "pwm+frozen-enc", "tdmpc2+frozen-enc", _experts_against_ft)


ORDERINGS: dict[str, Callable[[dict[Key, Group]], Iterator[Check]]] = {
    "PackNet forgets least, FT most": packnet_least_ft_most,
    "ER transfers most": er_transfers_most,
    "DreamerV3 forgets less than TD-MPC2 under every method": dreamerv3_forgets_less,
    "PWM with experts forgets far less than TD-MPC2 under the frozen encoder":
        pwm_experts_forgets_less,
}  # fmt: skip
"""The paper's orderings, each with the places it can be checked on a report's groups."""


def is_offline(row: Row) -> bool:
    return row[0].endswith("-offline")


def ordering_rows(groups: dict[Key, Group]) -> list[tuple[str, Row]]:
    return [(name, check.row()) for name, checks in ORDERINGS.items()
            for check in checks(groups)]  # fmt: skip


EXPLAINED = (
    "Each finding of the paper checked where the runs it needs are here (BWT: lower forgets "
    "less; FWT: higher transfers more; 'most', 'least' and 'far less' as the strict order), "
    "under both conventions: the metric of the seed-averaged curves (the paper's) and the mean "
    "of the per-seed metrics. They can disagree, and a seed-averaged value can lie outside its "
    "seeds' range, because BWT clips each drop at 0 and divides it by the end-of-task score: "
    "averaging the curves first lets one seed's rise cancel another's drop. 'On every seed': "
    "the order of each seed's own metrics, on the seeds every member ran. P(holds): rliable's "
    "probability of improvement (a seed of the better member beats a seed of the other) of the "
    "weakest pair the ordering needs, with its 95% stratified-bootstrap CI. Values carry 95% "
    "bootstrap CIs over seeds (one seed: none)."
)
OFFLINE_EXPLAINED = (
    "Offline track (`ccfit fit`): BWT and FWT of the world model's open-loop prediction score "
    "on held-out dataset episodes. These measure prediction fidelity, not returns: they are "
    "reported beside the online findings, never counted as support for them."
)


def orderings_table(rows: list[tuple[str, Row]]) -> list[str]:
    lines = ["| ordering | backbone | suite | " + " | ".join(COLUMNS) + " |",
             "|---|---|---|" + "---|" * len(COLUMNS)]  # fmt: skip
    return lines + [f"| {name} | {' | '.join(row)} |" for name, row in rows]


def write_orderings(groups: dict[Key, Group], out: Path) -> Path:
    """`orderings.md` over `groups`: one line per ordering and place it can be checked, online
    and offline apart, and the orderings no group here can check."""
    rows = ordering_rows(groups)
    lines = ["# The paper's orderings on these runs", "", EXPLAINED]
    online = [(n, r) for n, r in rows if not is_offline(r)]
    offline = [(n, r) for n, r in rows if is_offline(r)]
    parts = (("Online", None, online),
             ("Offline: prediction fidelity", OFFLINE_EXPLAINED, offline))  # fmt: skip
    for title, explained, part in parts:
        if part:
            lines += ["", f"## {title}", ""] + ([explained, ""] if explained else [])
            lines += orderings_table(part)
    unchecked = [name for name in ORDERINGS if name not in {n for n, _ in rows}]
    if unchecked:
        lines += ["", "Not checkable on these runs: " + "; ".join(unchecked) + "."]
    path = Path(out) / ORDERINGS_MD
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
