"""The paper's Fig. 6: expert ablation of a finished run of a routed model (capability
'routing') on its composition task."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ccdata.errors import InputError
from ccfit.analysis.episodes import (
    _ABLATION_TAG,
    ABLATION_JSON,
    ABLATION_MODES,
    ABLATION_PNG,
    latent_error,
    mean_routing,
)
from ccfit.io import atomic_write_text, derived_seed, save_figure, seeded
from ccfit.models.base import Routing
from ccfit.train import EnvPool, Episode, eval_seeds, normalized_or_none, play_episodes

# ====================================================================== Fig. 6: ablation


def load_routed_run(run_dir: str | Path, device: torch.device | str | None = None):
    """A finished curriculum run of a routed model: (config, model, stored heads, method)."""
    from ccfit.curriculum import load_run

    run = load_run(run_dir, device)
    if not isinstance(run.model, Routing):
        raise InputError(f"{run_dir}: expert ablation needs a model offering 'routing', this "
                         f"is a {run.cfg.model.type} run")  # fmt: skip
    if run.completed < len(run.cfg.tasks):
        raise InputError(f"{run_dir}: run not finished ({run.completed} of "
                         f"{len(run.cfg.tasks)} tasks done)")  # fmt: skip
    run.model.eval()
    return run.cfg, run.model, run.stored_heads, run.method


def ablate(run_dir: str | Path, episodes: int | None = None, horizon: int | None = None,
           device: torch.device | str | None = None) -> dict:  # fmt: skip
    """Fig. 6 for one finished run of a routed model: writes `ablation.json` and
    `ablation.png` in it.

    episodes: evaluation layouts of the composition task (default: the run's eval_episodes);
    horizon: open-loop steps H (default: the model's planning horizon)."""
    run_dir = Path(run_dir)
    cfg, model, stored, method = load_routed_run(run_dir, device)
    train = cfg.train
    if train.torch_threads > 0:
        torch.set_num_threads(train.torch_threads)
    device = model.device
    layout = model.expert_layout()
    if layout.num_groups < 2:
        raise InputError(
            f"{run_dir}: one expert group only (method {cfg.method.type!r}); the ablation compares "
            "prior and new experts of a run with method 'experts'"
        )
    episodes = train.eval_episodes if episodes is None else int(episodes)
    horizon = int(model.cfg.horizon) if horizon is None else int(horizon)
    if episodes < 1 or horizon < 1:
        raise InputError(f"episodes and horizon must be >= 1, got {episodes} and {horizon}")
    comp = len(cfg.tasks) - 1
    task_id, heads = cfg.tasks[comp], stored[comp]
    routed = model.routed_task(heads)
    seeds = eval_seeds(cfg.seed, comp, episodes)
    pool = EnvPool(cfg.obs, cfg.image_size, episode_steps=train.episode_steps)
    modes: dict[str, dict] = {}
    recorded: list[Episode] = []
    try:
        for name, override in ABLATION_MODES.items():
            # The same MPPI noise stream for every mode: differences come from the routing.
            with method.evaluating(comp, model.backbone), model.routing_override(override), \
                    seeded(derived_seed(cfg.seed, _ABLATION_TAG, 0, comp), device):  # fmt: skip
                eps = play_episodes(pool.get(task_id, len(seeds)), model, heads,
                                    obs_mode=cfg.obs, seeds=seeds, record=True)  # fmt: skip
                recorded = recorded or eps  # the full mixture's trajectories (first mode)
                weights = mean_routing(model, eps, routed, device)
                error = latent_error(model, recorded, routed, horizon, device)
            ret = float(np.mean([e.discounted_return for e in eps]))
            k, n = layout.experts_per_task, layout.num_active
            modes[name] = {
                "override": override,
                "discounted_return": ret,
                "normalized_return": normalized_or_none(task_id, ret),
                "success_rate": float(np.mean([e.success for e in eps])),
                "latent_error": error,
                "routing_weights": [float(w) for w in weights],
                "prior_weight": float(weights[: n - k].sum()),
                "new_weight": float(weights[n - k : n].sum()),
            }
    finally:
        pool.close()
    full = modes["full"]
    for m in modes.values():
        nr, base = m["normalized_return"], full["normalized_return"]
        m["return_ratio"] = nr / base if nr is not None and base is not None and base > 0 else None
        e, e0 = m["latent_error"], full["latent_error"]
        m["latent_error_ratio"] = e / e0 if e0 > 0 else None
        m["fidelity_ratio"] = e0 / e if e > 0 else None
    result = {
        "run": str(run_dir), "suite": cfg.suite, "method": cfg.method.type, "seed": cfg.seed,
        "task": task_id, "task_index": comp, "episodes": episodes, "horizon": horizon,
        "num_active": layout.num_active, "experts_per_task": layout.experts_per_task,
        "modes": modes,
    }  # fmt: skip
    atomic_write_text(run_dir / ABLATION_JSON, json.dumps(result, indent=2) + "\n")
    plot_ablation(result, run_dir / ABLATION_PNG)
    return result


def plot_ablation(result: dict, out: str | Path) -> Path:
    """Fig. 6 style: per ablation, closed-loop return and open-loop fidelity relative to the
    full mixture (the dashed line at 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [m for m in ABLATION_MODES if m != "full"]
    metrics = (("return_ratio", "closed-loop return"), ("fidelity_ratio", "open-loop fidelity"))
    fig, ax = plt.subplots(figsize=(5, 3.4))
    width = 0.38
    for i, (key, label) in enumerate(metrics):
        xs = np.arange(len(names)) + (i - 0.5) * width
        ys = [result["modes"][m][key] for m in names]
        bars = ax.bar(xs, [0.0 if y is None else y for y in ys], width, label=label)
        for bar, y in zip(bars, ys, strict=True):
            label = "n/a" if y is None else f"{y:.2f}"
            x = bar.get_x() + bar.get_width() / 2
            ax.text(x, bar.get_height(), label, ha="center", va="bottom", fontsize=7)
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="full mixture")
    ax.set_xticks(range(len(names)), ["prior experts", "new experts", "uniform"])
    ax.set_ylabel("relative to full mixture")
    ax.set_title(f"{result['suite']} / {result['task']} / seed {result['seed']}: expert ablation",
                 fontsize=9)  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out)
    plt.close(fig)
    return Path(out)
