"""Routing records per curriculum stage and the paper's Fig. 5 from them (models offering
'routing')."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ccfit.analysis.episodes import _ROUTING_TAG, ROUTING, _eval_mode, mean_routing
from ccfit.analysis.hooks import register_analysis
from ccfit.io import atomic_write_text, derived_seed, save_figure, seeded
from ccfit.models.base import Routing
from ccfit.train import CONFIG, EnvPool, eval_seeds, normalized_or_none, play_episodes

# ===================================================================== routing record


def routing_record(model: Routing, stored_heads: list, task_ids: list[str], *, stage: int,
                   seed: int,
                   episodes: int, episode_steps: int, obs_mode: str, image_size: int = 64,
                   device: torch.device | str = "cpu",
                   view: Callable[[int], contextlib.AbstractContextManager] | None = None,
                   ) -> dict:  # fmt: skip
    """Routing after stage `stage`: for every task i <= stage, its evaluation episodes played
    with `stored_heads[i]` and the mean weight of every expert over the visited (z, a).

    `view(i)`: the continual method's evaluation context of task i (PackNet's masks)."""
    if not isinstance(model, Routing):
        raise ValueError(f"routing records need a model offering 'routing', got "
                         f"{type(model).__name__}")  # fmt: skip
    if len(stored_heads) <= stage or len(task_ids) <= stage:
        raise ValueError(f"stage {stage}: need heads and task ids of tasks 0..{stage}")
    device = torch.device(device)
    layout = model.expert_layout()
    tasks = []
    pool = EnvPool(obs_mode, image_size, episode_steps=episode_steps)
    with _eval_mode(model):
        for i in range(stage + 1):
            heads = stored_heads[i]
            routed = model.routed_task(heads)
            seeds = eval_seeds(seed, i, episodes)
            try:
                ctx = view(i) if view is not None else contextlib.nullcontext()
                with ctx, seeded(derived_seed(seed, _ROUTING_TAG, stage, i), device):
                    eps = play_episodes(pool.get(task_ids[i], len(seeds)), model, heads,
                                        obs_mode=obs_mode, seeds=seeds, record=True)  # fmt: skip
                    weights = mean_routing(model, eps, routed, device)
            finally:
                pool.close()
            ret = float(np.mean([e.discounted_return for e in eps]))
            tasks.append({
                "task_index": i, "task": task_ids[i], "routed_as": routed,
                "samples": int(sum(len(e.action) for e in eps)),
                "normalized_return": normalized_or_none(task_ids[i], ret),
                "weights": [float(w) for w in weights],
            })  # fmt: skip
    return {
        "stage": stage, "task": task_ids[stage], "episodes": episodes,
        "num_active": layout.num_active, "experts_per_task": layout.experts_per_task,
        "max_experts": layout.max_experts, "tasks": tasks,
    }  # fmt: skip


def read_routing(run_dir: str | Path) -> list[dict]:
    """The records of `routing.jsonl`, by stage (they must be stages 0, 1, ...)."""
    path = Path(run_dir) / ROUTING
    if not path.is_file():
        raise ValueError(f"no {ROUTING} in {run_dir} (only curricula of a model offering "
                         "'routing' write one)")  # fmt: skip
    records = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    records.sort(key=lambda r: r["stage"])
    if [r["stage"] for r in records] != list(range(len(records))):
        raise ValueError(f"{path}: stages {[r['stage'] for r in records]} are not 0, 1, ...")
    return records


def append_routing(run_dir: str | Path, record: dict) -> None:
    """Add a stage's record, replacing that stage and later ones (left by a killed run that
    is now redoing them), so a resumed run never duplicates a stage."""
    path = Path(run_dir) / ROUTING
    text = path.read_text() if path.is_file() else ""
    old = [json.loads(x) for x in text.splitlines() if x.strip()]
    keep = [r for r in old if r["stage"] < record["stage"]] + [record]
    atomic_write_text(path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in keep))


@register_analysis("routing")
def routing_callback(stage) -> None:
    """The curriculum's `StageCallback` for routed models: after a task's heads are stored,
    appends the routing of stage len(stored_heads) - 1 to `routing.jsonl`."""
    cfg, model, method = stage.cfg, stage.model, stage.method
    record = routing_record(
        model, stage.stored_heads, cfg.tasks, stage=len(stage.stored_heads) - 1, seed=cfg.seed,
        episodes=cfg.train.eval_episodes, episode_steps=cfg.train.episode_steps,
        obs_mode=cfg.obs, image_size=cfg.image_size,
        device=stage.device, view=lambda i: method.evaluating(i, model.backbone),
    )  # fmt: skip
    append_routing(stage.run_dir, record)


# ======================================================================= Fig. 5 data


def _owned_groups(records: list[dict]) -> list[bool]:
    """Stage j's group of experts was activated for task j (the 'experts' method)."""
    return [r["num_active"] == (j + 1) * r["experts_per_task"] for j, r in enumerate(records)]


def figure_data(records: list[dict], num_tasks: int | None = None) -> dict:
    """The numbers of Fig. 5 from the routing records (see the module docstring).

    relative_change[s][j] (None above the diagonal or when group j is not task j's),
    normalized_weights[s][e] for the experts activated over the run (None while inactive),
    top_expert: per primitive its top expert before and after composition, and k / n
    (None when the records do not reach the composition stage, `num_tasks` - 1)."""
    k = records[0]["experts_per_task"]
    stages = len(records)
    # Routing of the task being learnt, read right after its stage.
    current = [np.asarray(r["tasks"][s]["weights"], np.float64) for s, r in enumerate(records)]
    owned = _owned_groups(records)

    def group(w: np.ndarray, j: int) -> np.ndarray:
        return w[j * k : (j + 1) * k]

    rel: list[list[float | None]] = []
    for s in range(stages):
        row = []
        for j in range(stages):
            ok = j <= s and owned[j] and records[s]["num_active"] >= (j + 1) * k
            row.append(float(group(current[s], j).mean() / group(current[j], j).mean())
                       if ok else None)  # fmt: skip
        rel.append(row)
    width = max(r["num_active"] for r in records)
    normalized = [
        [float(w[e] * r["num_active"]) if e < r["num_active"] else None for e in range(width)]
        for w, r in zip(current, records, strict=True)
    ]
    num_tasks = stages if num_tasks is None else num_tasks
    top: dict[str, Any] = {"primitives": [], "k": None, "n": None}
    if stages == num_tasks and num_tasks >= 2:
        last = current[-1]
        for j in range(num_tasks - 1):
            if not owned[j]:
                continue
            before = int(np.argmax(group(current[j], j)))
            after = int(np.argmax(group(last, j)))
            top["primitives"].append({"task_index": j, "task": records[j]["task"],
                                      "top_before": j * k + before, "top_after": j * k + after,
                                      "stays": before == after})  # fmt: skip
        top["k"] = sum(p["stays"] for p in top["primitives"])
        top["n"] = len(top["primitives"])
    return {"tasks": [r["task"] for r in records], "experts_per_task": k,
            "num_active": [r["num_active"] for r in records], "relative_change": rel,
            "normalized_weights": normalized, "top_expert": top}  # fmt: skip


def top_statement(data: dict) -> str:
    top = data["top_expert"]
    if top["n"] is None:
        return "top expert after composition: n/a (run not finished)"
    return f"top expert stays top after composition in {top['k']}/{top['n']} cases"


def _annotate(ax, values: np.ndarray, fmt: str) -> None:
    from matplotlib.patheffects import withStroke

    halo = [withStroke(linewidth=2, foreground="white")]  # readable on dark cells too
    for (r, c), v in np.ndenumerate(values):
        if np.isfinite(v):
            ax.text(c, r, fmt.format(v), ha="center", va="center", fontsize=7,
                    path_effects=halo)  # fmt: skip


def plot_routing(run_dir: str | Path, out: str | Path) -> dict:
    """Fig. 5 for one run into the PNG `out`; returns `figure_data` plus 'statement'."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle

    from ccdata.suites import get_suite

    run_dir = Path(run_dir)
    config = json.loads((run_dir / CONFIG).read_text())
    suite = get_suite(config["suite"])
    records = read_routing(run_dir)
    data = figure_data(records, len(suite.task_ids))
    names = list(suite.task_ids)
    comp = suite.composition_matrix().astype(float)
    rel = np.array([[np.nan if v is None else v for v in row] for row in data["relative_change"]])
    norm_w = np.array([[np.nan if v is None else v for v in row]
                       for row in data["normalized_weights"]])  # fmt: skip
    stages = len(records)

    n, e, cell = len(names), max(norm_w.shape[1], 1), 0.55  # square cells of `cell` inches
    fig, axes = plt.subplots(1, 3, figsize=(cell * (2 * n + e) + 5.5, cell * n + 2.4),
                             width_ratios=[n, n, e], layout="constrained")  # fmt: skip
    ax = axes[0]
    ax.imshow(comp, cmap="Blues", vmin=0, vmax=2.5)
    _annotate(ax, comp, "{:.0f}")
    ax.set_title(f"composition ({suite.axis})", fontsize=9)
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)

    ax = axes[1]
    finite = rel[np.isfinite(rel)]
    lo = min(float(finite.min()), 0.99) if finite.size else 0.5
    hi = max(float(finite.max()), 1.01) if finite.size else 1.5
    ax.imshow(np.ma.masked_invalid(rel), cmap="RdBu_r", norm=TwoSlopeNorm(1.0, lo, hi))
    _annotate(ax, rel, "{:.2f}x")
    ax.set_title("weight on task j's experts / at stage j", fontsize=9)
    ax.set_xticks(range(stages), names[:stages], rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(stages), names[:stages], fontsize=7)
    ax.set_xlabel("experts of task j", fontsize=8)
    ax.set_ylabel("routing of task s after stage s", fontsize=8)

    ax = axes[2]
    finite = norm_w[np.isfinite(norm_w)]
    hi = max(float(finite.max()), 1.01) if finite.size else 2.0
    ax.imshow(np.ma.masked_invalid(norm_w), cmap="RdBu_r", norm=TwoSlopeNorm(1.0, 0.0, hi))
    _annotate(ax, norm_w, "{:.2f}")
    k = data["experts_per_task"]
    ax.set_xticks(range(norm_w.shape[1]), [f"{e // k}.{e % k}" for e in range(norm_w.shape[1])],
                  fontsize=7)  # fmt: skip
    ax.set_yticks(range(stages), names[:stages], fontsize=7)
    ax.set_xlabel("expert (task.index)", fontsize=8)
    ax.set_title("expert weight x K_active (1 = uniform)", fontsize=9)
    if stages == len(names):
        ax.add_patch(Rectangle((-0.5, stages - 1.5), norm_w.shape[1], 1, fill=False, lw=2))
    statement = top_statement(data)
    model, method = (config[k]["type"] for k in ("model", "method"))
    fig.suptitle(f"{config['suite']} / {model} / {method} / seed {config['seed']}: {statement}",
                 fontsize=10)  # fmt: skip
    save_figure(fig, out)
    plt.close(fig)
    return {**data, "statement": statement}


def report_routing(runs, out: Path) -> tuple[list[Path], dict[tuple, dict]]:
    """`ccfit report`'s part: Fig. 5 of every run (ccfit.report.runs.Run) with routing.jsonl.

    Returns the PNGs and, per (backbone, suite, method) key, {'s<seed>': top-expert summary}."""
    written, summary = [], {}
    for run in runs:
        if not (run.path / ROUTING).is_file():
            continue
        backbone, suite, method = run.key
        path = out / f"routing_{backbone}_{suite}_{method}_s{run.seed}.png"
        data = plot_routing(run.path, path)
        top = data["top_expert"]
        summary.setdefault(run.key, {})[f"s{run.seed}"] = {
            "top_expert_stays_top": top["k"], "of": top["n"], "statement": data["statement"],
        }  # fmt: skip
        written.append(path)
    return written, summary
