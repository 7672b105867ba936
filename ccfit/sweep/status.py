"""`ccfit sweep --status RUNS`: what is pending, running, done and failed.

Done is read from the outputs (a run's metrics.json, a reference's done.json, the report's
status.json), so it holds whoever produced them. Otherwise the state is that of the job last
submitted for it: for SLURM jobs the controller's (squeue) while it lists them, else sacct's;
for local ones the launcher's record in sweep.json (a record left 'running' by a launcher
that is gone reads 'interrupted'). A last line adds up the CPU-hours left (`hours_to_go`).
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Iterable
from pathlib import Path

from ccdata.slurm import check_slurm, job_states
from ccfit.config_base import suite_tasks
from ccfit.report import SUMMARY_JSON
from ccfit.report.cost import run_cost
from ccfit.run_files import FIRST, REPORT
from ccfit.sweep.grid import STATUS_JSON, Sweep, load_sweep
from ccfit.sweep.jobs import read_report_status
from ccfit.train.records import METRICS

CATEGORIES = ("pending", "running", "done", "failed", "not submitted")
_PENDING = {"PENDING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "SUSPENDED", "PREEMPTED",
            "UNKNOWN"}  # UNKNOWN: in neither squeue nor sacct yet  # fmt: skip
_RUNNING = {"RUNNING", "COMPLETING", "CONFIGURING", "SIGNALING", "STAGE_OUT", "RESIZING"}


def units(sweep: Sweep, submitted: Iterable[str] = ()) -> dict[str, tuple[bool, Path, int | None]]:
    """Every job name of the sweep -> (whether its output exists, its directory, the global
    steps it trains when that is known); the shared first tasks (`ccfit.first_task`) that are
    in `submitted` (job names) or on disk."""
    training = {name: unit[:3] for name, unit in _training_units(sweep).items()}
    keys = {n.split(":", 1)[1] for n in submitted if n.startswith("first:")}
    if (sweep.root / FIRST).is_dir():
        keys |= {p.name for p in (sweep.root / FIRST).iterdir() if p.is_dir()}
    configs = sweep.scratch_configs()
    first = {f"first:{key}": (sweep.first_done(key), sweep.first_dir(key),
                              _total_steps(configs.get(key, {}), reference=True))
             for key in sorted(keys)}  # fmt: skip
    # References, shared first tasks, runs: the order they start in.
    out = {n: u for n, u in training.items() if n.startswith("scratch:")}
    out.update(first)
    out.update((n, u) for n, u in training.items() if not n.startswith("scratch:"))
    # The report's own lines list its gaps. Only the sweep's report job writes status.json; a
    # report that `ccfit report` or `ccfit publish` wrote (a published folder's) has a summary.
    report = sweep.root / REPORT
    out["report"] = (any((report / f).is_file() for f in (STATUS_JSON, SUMMARY_JSON)), report, None)
    return out


def _training_units(sweep: Sweep) -> dict[str, tuple[bool, Path, int | None, tuple[str, str]]]:
    """The references and runs of `units`, each with its kind: (model type, 'reference' or
    'curriculum'), the units whose cost per step is alike."""
    out = {f"scratch:{k}": (sweep.scratch_done(k), sweep.scratch_dir(k),
                            _total_steps(c, reference=True), (_model(c), "reference"))
           for k, c in sweep.scratch_configs().items()}  # fmt: skip
    out.update({f"run:{r.name}": (sweep.run_done(r), sweep.run_dir(r), _total_steps(r.config),
                                  (_model(r.config), "curriculum"))
                for r in sweep.runs})  # fmt: skip
    return out


def _model(config: dict) -> str:
    return str(config.get("model", {}).get("type", "?"))


def _total_steps(config: dict, reference: bool = False) -> int | None:
    """Global steps of an online curriculum (steps per task x tasks) or of its from-scratch
    reference (one task); None for other tracks."""
    steps = config.get("train", {}).get("steps")
    if steps is None or "suite" not in config:
        return None
    return int(steps) * (1 if reference else len(suite_tasks(config["suite"])))


def progress(directory: Path, total: int | None = None) -> str:
    """Where an unfinished run is: its last evaluation's task and global step, of `total`
    when given ('' before the first), read from the tail of its metrics.jsonl; with `total`
    and a recorded cost, the CPU-hours spent and those left at the rate so far (`remaining`)."""
    last = last_evaluation(directory)
    if last is None:
        return ""
    task, step = last
    of = f" of {total}" if total else ""
    where = f"last evaluated {task} at global step {step}{of}"
    return "; ".join(filter(None, (where, remaining(directory, step, total))))


def last_evaluation(directory: Path) -> tuple[str, int] | None:
    """(task, global step) of a run's last evaluation, from the tail of its metrics.jsonl;
    None before the first."""
    try:
        with (directory / METRICS).open("rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 4096))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:  # not started, or its directory is not one
        return None
    for line in reversed(lines):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:  # the first line of the tail may be cut
            continue
        if isinstance(record, dict) and "global_step" in record:
            return str(record.get("task", "?")), int(record["global_step"])
    return None


def remaining(directory: Path, step: int, total: int | None) -> str:
    """'H CPU-hours so far, about R to go' for a run at global step `step` of `total`, from
    its cost.json: the CPU seconds per step so far times the steps left ('' without a cost
    or a step). A rate, not a promise: later stages of a curriculum may cost more per step
    (a replayed or anchored earlier task, PackNet's retraining), and the cost recorded runs
    up to a minute past the last evaluation."""
    spent = run_cost(directory)["cpu_s"] / 3600
    if not total or step <= 0 or spent <= 0:
        return ""
    return f"{spent:.1f} CPU-hours so far, about {spent / step * (total - step):.1f} to go"


def hours_to_go(root: str | Path) -> str:
    """The CPU-hours the sweep's unfinished references and runs still need, in one line ('' when
    none is left or no rate is known yet): a started one at its own rate so far (`remaining`),
    one not started at the median rate of those of its kind (model, reference or curriculum)
    that have a cost, a finished one's counted over all its steps. Units of a kind with no
    rate yet are named as not counted. As rough as `remaining`, and more so for a method
    whose runs have not started (ER's replay and PackNet's retraining cost more per step)."""
    sweep, _ = load_sweep(root)
    rates: dict[tuple[str, str], list[float]] = {}
    left: list[tuple[tuple[str, str], int, float | None]] = []  # kind, steps left, own rate
    for done, directory, total, kind in _training_units(sweep).values():
        if not total:
            continue
        spent = run_cost(directory)["cpu_s"]
        last = None if done else last_evaluation(directory)
        step = total if done else last[1] if last else 0
        rate = spent / step if step > 0 and spent > 0 else None
        if rate is not None:
            rates.setdefault(kind, []).append(rate)
        if not done:
            left.append((kind, total - step, rate))
    if not left or not rates:
        return ""
    seconds, borrowed, uncounted = 0.0, 0, 0
    for kind, steps, rate in left:
        if rate is None and kind in rates:
            rate, borrowed = statistics.median(rates[kind]), borrowed + 1
        if rate is None:
            uncounted += 1
            continue
        seconds += rate * steps
    notes = [f"{borrowed} without a rate of their own at their kind's median"] if borrowed else []
    notes += [f"{uncounted} not counted: no rate of their kind yet"] if uncounted else []
    detail = f" ({'; '.join(notes)})" if notes else ""
    return f"about {seconds / 3600:.1f} CPU-hours to go{detail}"


def latest_jobs(submissions: list[dict]) -> dict[str, tuple[dict, object]]:
    """Job name -> (its last submission entry, the job: an id, or a local state record)."""
    latest: dict[str, tuple[dict, object]] = {}
    for entry in submissions:
        for name, job in entry.get("jobs", {}).items():
            latest[name] = (entry, job)
    return latest


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_status(root: str | Path) -> dict[str, dict]:
    """Job name -> {"state": one of CATEGORIES, "job": id or None, "detail": text}."""
    sweep, record = load_sweep(root)
    latest = latest_jobs(record.get("submissions", []))
    slurm_ids = [job for name, (entry, job) in latest.items() if entry["launcher"] == "slurm"]
    states: dict[str, str] = {}
    if slurm_ids:
        check_slurm()
        states = job_states(sweep.root / "slurm", slurm_ids)
    out = {}
    for name, (done, directory, total) in units(sweep, latest).items():
        entry, job = latest.get(name, ({}, None))
        if done:
            out[name] = {"state": "done", "job": _job_id(entry, job, name), "detail": ""}
        elif job is None:
            out[name] = {"state": "not submitted", "job": None, "detail": ""}
        elif entry["launcher"] == "slurm":
            state = states[job]
            category = ("pending" if state in _PENDING else "running" if state in _RUNNING
                        else "failed")  # fmt: skip
            detail = state if state != "COMPLETED" else "completed without its output"
            if category == "failed":
                detail += f"; log {sweep.root / 'slurm' / job / f'{job}_0_log.err'}"
            out[name] = {"state": category, "job": job, "detail": detail}
        else:
            state = job["state"]
            if state in ("PENDING", "RUNNING") and not _alive(entry["pid"]):
                state = "INTERRUPTED"
            category = {"PENDING": "pending", "RUNNING": "running"}.get(state, "failed")
            detail = job.get("error") or {
                "INTERRUPTED": "interrupted",
                "COMPLETED": "completed without its output",
            }.get(state, "")
            out[name] = {"state": category, "job": _job_id(entry, job, name), "detail": detail}
        if out[name]["state"] != "done":
            where = progress(directory, total)
            out[name]["detail"] = "; ".join(filter(None, (out[name]["detail"], where)))
    out["report"]["detail"] = _report_gaps(sweep)
    return out


def _report_gaps(sweep: Sweep) -> str:
    """'lists N of M runs missing' when the sweep's report job wrote its report before every
    run was done (a report written then is not rewritten until the next launch ends)."""
    status = read_report_status(sweep)
    missing = len(status["missing"]) if status else 0
    return f"lists {missing} of {len(sweep.runs)} runs missing" if missing else ""


def _job_id(entry: dict, job, name: str) -> str | None:
    if job is None:
        return None
    return job if entry["launcher"] == "slurm" else f"local:{entry['pid']}"


def print_status(status: dict[str, dict], to_go: str = "") -> None:
    """One line per unit, the counts per state, then `to_go` (`hours_to_go`) when given."""
    width = max(map(len, status))
    for name, s in status.items():
        job = f"  job {s['job']}" if s["job"] else ""
        detail = f"  ({s['detail']})" if s["detail"] else ""
        print(f"{name:<{width}}  {s['state']}{job}{detail}")
    counts = {c: sum(s["state"] == c for s in status.values()) for c in CATEGORIES}
    print(", ".join(f"{n} {c}" for c, n in counts.items()))
    if to_go:
        print(to_go)
