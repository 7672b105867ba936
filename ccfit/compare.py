"""`ccfit compare A B`: does run B reproduce run A, and where not, where do they part and what
differs between them.

Example:
    ccfit compare results/online/reach-tdmpc2/Reach-tdmpc2-ft-state-cpu-s0 runs/my-ft-s0

One config and seed give the same records on one kind of machine from the same data; where two
runs' records differ, the files beside them say what else did: config.json (the settings, and
what the datasets held: `content_sha256`) and cost.json (the code and the machine of each
segment). This reads both runs' and prints, in this order:
- the settings that differ (flattened config.json keys; `out` and the dataset records aside;
  a setting newer than a run, at the value the run had, `LEGACY_VALUES`, is no difference),
  those that say only how a run was executed or why it chose what it did marked as such; a
  path is compared as `ccfit publish` writes it (`ccfit.portable`: a dataset by where it lies
  under the LeRobot home, a file outside the run by its name), so a published run and the same
  run where it was made have the same settings;
- the code commits and machine kinds each run's segments ran on;
- the datasets' content digests, where either run recorded them;
- the records: how many the runs share (an evaluation is keyed by stage, task and global step)
  and how many of those are equal, the first that differs, with every field that differs in
  it, and how many only one run holds (a run still going, or stopped). Records are compared
  on the fields both hold: a field one run's code did not record yet (e.g. `returns`, each
  episode's return) is named, not counted as a difference.
Any kind of run compares: curricula, single-task runs, offline runs (their evaluations are
records too). `ccfit compare` exits 0 when the runs share records and every one is equal, 1
when one differs or none is shared, 2 on bad input (a directory without config.json or
metrics.jsonl)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ccfit.config_base import DATASET_RECORDS, NOT_IDENTITY, drop_legacy_values
from ccfit.config_parse import flatten
from ccfit.io import read_run_json
from ccfit.portable import same_as_published
from ccfit.report.cost import counted, machines_cell, run_cost
from ccfit.train import CONFIG, METRICS

LEFT_ASIDE = ("out", *DATASET_RECORDS)
"""config.json keys (and their subkeys) the settings comparison leaves out: where each run
lies, and the dataset records, compared by content below."""


@dataclass
class Comparison:
    settings: dict[str, tuple]
    """Flattened config key -> (A's value, B's value), for the keys that differ."""
    segments: dict[str, tuple[str, str]]
    """'code' and 'machines' -> each run's segments, counted per commit or machine kind."""
    datasets: dict[str, tuple]
    """Dataset record -> (A's content_sha256, B's), where either recorded one."""
    shared: int
    """Records both runs hold."""
    equal: int
    """Shared records that are equal, field for field."""
    first_difference: dict | None
    """The first shared record that differs: its key and the fields that differ."""
    only: tuple[int, int]
    """Records only A holds, only B holds."""
    one_sided: tuple[list[str], list[str]] = ([], [])
    """Record fields only A's shared records hold, only B's (left out of the comparison)."""

    @property
    def reproduces(self) -> bool:
        """Some records in common, and all of those equal."""
        return self.shared > 0 and self.equal == self.shared


def _same(x, y) -> bool:
    """Equal as JSON holds them (NaN equals NaN: a record written twice is the same)."""
    return json.dumps(x, sort_keys=True) == json.dumps(y, sort_keys=True)


def _key(record: dict) -> tuple:
    return record.get("stage", 0), record.get("task_index", 0), record["global_step"]


def _segments(run: Path) -> dict[str, str]:
    cost = run_cost(run)
    commits = [c.get("git") or str(c.get("commit"))[:7] for c in cost["code"]]
    return {"code": counted(commits, cost["segments"]), "machines": machines_cell([cost])}


def _digests(config: dict) -> dict[str, dict | None]:
    return {key: (config.get(key) or {}).get("content_sha256") for key in DATASET_RECORDS}


def compare_runs(a: Path, b: Path) -> Comparison:
    """What differs between runs `a` and `b` (directories), and whether `b`'s records
    reproduce `a`'s where both have them."""
    configs = [read_run_json(Path(run) / CONFIG, leave_out="the comparison") for run in (a, b)]
    # A setting added after a run was made, at the value that run had, is no difference.
    flat = [{k: v for k, v in flatten(drop_legacy_values(c)).items()
             if k.split(".")[0] not in LEFT_ASIDE} for c in configs]  # fmt: skip
    keys = sorted(flat[0].keys() | flat[1].keys())
    settings = {k: (flat[0].get(k), flat[1].get(k)) for k in keys
                if not same_as_published(flat[0].get(k), flat[1].get(k))}  # fmt: skip
    segments = [_segments(Path(run)) for run in (a, b)]
    digests = [_digests(c) for c in configs]
    datasets = {key: (digests[0][key], digests[1][key]) for key in DATASET_RECORDS
                if digests[0][key] or digests[1][key]}  # fmt: skip
    records = [{_key(r): r for r in read_run_json(Path(run) / METRICS, lines=True,
                                                   leave_out="the comparison")}
               for run in (a, b)]  # fmt: skip
    shared = sorted(records[0].keys() & records[1].keys())
    pairs = {k: _on_common_fields(records[0][k], records[1][k]) for k in shared}
    differing = [k for k in shared if not _same(*pairs[k])]
    held = [{f for k in shared for f in records[side][k]} for side in (0, 1)]
    first = None
    if differing:
        ra, rb = pairs[differing[0]]
        fields = {f: (ra.get(f), rb.get(f)) for f in sorted(ra.keys() | rb.keys())
                  if not _same(ra.get(f), rb.get(f))}  # fmt: skip
        stage, _, step = differing[0]
        first = {"stage": stage, "task": ra.get("task"), "global_step": step, "fields": fields}
    return Comparison(
        settings=settings,
        segments={part: (segments[0][part], segments[1][part]) for part in ("code", "machines")},
        datasets=datasets,
        shared=len(shared),
        equal=len(shared) - len(differing),
        first_difference=first,
        only=(len(records[0].keys() - records[1].keys()),
              len(records[1].keys() - records[0].keys())),
        one_sided=(sorted(held[0] - held[1]), sorted(held[1] - held[0])),
    )  # fmt: skip


def _on_common_fields(a: dict, b: dict) -> tuple[dict, dict]:
    """Two records on the fields both hold."""
    both = a.keys() & b.keys()
    return {k: a[k] for k in both}, {k: b[k] for k in both}


def describe(comparison: Comparison, a: Path, b: Path) -> str:
    """The comparison as `ccfit compare` prints it."""
    c = comparison
    lines = [f"A: {a}", f"B: {b}"]
    if c.settings:
        lines.append("settings that differ (A -> B):")
        lines += [f"  {k}: {va!r} -> {vb!r}{_aside(k)}" for k, (va, vb) in c.settings.items()]
    else:
        lines.append("settings: the same")
    for part, (sa, sb) in c.segments.items():
        lines.append(f"{part}: A {sa}; B {sb}")
    for key, (da, db) in c.datasets.items():
        same = "the same" if da == db else "differ"
        lines.append(f"{key}.content_sha256: {same} (A {_short(da)}; B {_short(db)})")
    lines.append(f"records: {c.shared} in both, {c.equal} equal; only in A {c.only[0]}, "
                 f"only in B {c.only[1]}")  # fmt: skip
    for side, fields in zip("AB", c.one_sided, strict=True):
        if fields:
            lines.append(f"fields only {side}'s records hold (not compared): {', '.join(fields)}")
    if c.first_difference is not None:
        d = c.first_difference
        where = f"global step {d['global_step']}, {d['task']} (stage {d['stage']})"
        lines.append(f"first difference: {where}")
        lines += [f"  {f}: {va!r} -> {vb!r}" for f, (va, vb) in d["fields"].items()]
    if c.shared == 0:
        lines.append("no evaluation in common: nothing reproduced yet")
    else:
        verdict = "B reproduces A's records" if c.reproduces else "B does not reproduce A's records"
        lines.append(f"{verdict} ({c.equal} of the {c.shared} both hold)")
    return "\n".join(lines) + "\n"


def _aside(key: str) -> str:
    """What a differing setting is, where it does not decide what a run computes."""
    if any(key == path or key.startswith(path + ".") for path in NOT_IDENTITY):
        return " (how it ran or a note: not part of the run's identity)"
    return ""


def _short(digests: dict | None) -> str:
    if not digests:
        return "not recorded"
    return ", ".join(f"{part} {value[:12]}" for part, value in digests.items() if value)
