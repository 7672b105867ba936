"""Routing analysis and expert ablation of a continual PWM run (the paper's Sec. V-B).

Routing record (`routing.jsonl` in the run directory, one line per curriculum stage): after
task t is learnt and its heads are stored, every task i <= t replays its evaluation episodes
(the same layouts as evaluation, `eval_seeds(seed, i, episodes)`) with its stored heads, and
the record keeps the mean routing weight of every expert (all K * max_tasks of them, inactive
ones exactly 0) over all visited (z, a) of those episodes, routed as task i.

Fig. 5 (`figure_data`, `plot_routing`), all panels read the routing of the task being learnt:
- composition matrix: the suite's (task i reuses a component of task j);
- relative change [s][j], j <= s: mean weight on task j's K experts when routing task s after
  stage s, divided by the same quantity when routing task j right after stage j (so the
  diagonal is exactly 1). Row s therefore says how much the router reuses task j's experts for
  task s, comparable row by row with the composition matrix (the paper's middle panel: its
  BinPnP example, "on the third task the router increases the weight on an overlapping prior
  task's experts to 1.20x", is a statement about routing the current task). The ratio is raw,
  as in the paper: adding groups dilutes it, uniform routing gives (j + 1) / (s + 1);
- per-expert weights of task s after stage s, times K_active (1 = uniform allocation);
- top expert stays top: for each primitive j, the argmax over its own K experts when routing
  task j after stage j, against the argmax over the same K experts when routing the
  composition task after the last stage ("k of n", the paper's 13 of 14).
A group of experts belongs to task j only when it was activated for it (K_active = (j+1) K at
stage j, the 'experts' method); under other methods a PWM keeps one group, owned by task 0.

Fig. 6 (`ablate`): on the composition task with its stored heads, the closed-loop normalised
return over the evaluation layouts and the open-loop latent prediction error, under routing
'full' (learnt), 'prior' (earlier tasks' experts only), 'new' (the composition's own experts
only) and 'uniform'. The open-loop error rolls the dynamics H steps from encode(o_t) with the
recorded actions of the full mixture's evaluation episodes (one shared set of trajectories for
every mode) and compares with encode(o_{t+k}): squared error averaged over latent dimensions,
k = 1..H and every start t. Ratios are to the full mixture: return_ratio (1 = as good),
latent_error_ratio (above 1 = worse) and its inverse, fidelity_ratio (the plot's, below 1 =
worse, like the return).

Replaying episodes draws MPPI noise; it runs under a forked torch RNG seeded from the run's
seed, so recording does not change the training that follows and results are reproducible.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ccdata.env import make_env
from ccdata.scoring import GAMMA, discounted_return
from ccfit.models.pwm import PWM
from ccfit.obs import obs_to_arrays
from ccfit.train import (
    CONFIG,
    atomic_write_text,
    derived_seed,
    eval_seeds,
    normalized_or_none,
    resolve_device,
)

ROUTING = "routing.jsonl"
ABLATION_JSON = "ablation.json"
ABLATION_PNG = "ablation.png"
ABLATION_MODES: dict[str, str | None] = {
    "full": None, "prior": "prior", "new": "new", "uniform": "uniform",
}  # fmt: skip
"""Ablation name -> `PWM.routing_override` mode."""
_ROUTING_TAG, _ABLATION_TAG = 10, 11  # seed streams beside ccfit.train's 0..3


# ====================================================================== playing episodes


@dataclass
class Episode:
    """One evaluation episode as played."""

    obs: dict[str, np.ndarray]
    """Observation arrays (T + 1, ...), as stored in replay."""
    action: np.ndarray
    """Actions (T, action_dim)."""
    rewards: list[float]
    """Rewards of the T steps."""
    success: bool
    """Whether the task was solved at some step."""


def play_episodes(env, model, heads, *, obs_mode: str, seeds: list[int],
                  device: torch.device) -> list[Episode]:  # fmt: skip
    """`ccfit.train.evaluate`'s episodes (eval-mode planning, one per layout seed), recorded."""
    episodes = []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        frames = [obs_to_arrays(obs, obs_mode)]
        actions, rewards, success, done = [], [], False, False
        state = model.initial_state(heads)
        while not done:
            x = {k: torch.from_numpy(v).to(device) for k, v in frames[-1].items()}
            action, state = model.act(x, heads, state, eval_mode=True)
            action = np.asarray(action, np.float32)
            obs, reward, terminated, truncated, info = env.step(action)
            frames.append(obs_to_arrays(obs, obs_mode))
            actions.append(action)
            rewards.append(float(reward))
            success = success or bool(info["success"])
            done = terminated or truncated
        stacked = {k: np.stack([f[k] for f in frames]) for k in frames[0]}
        episodes.append(Episode(stacked, np.stack(actions), rewards, success))
    return episodes


@contextlib.contextmanager
def _eval_mode(model: torch.nn.Module) -> Iterator[None]:
    was = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was)


@contextlib.contextmanager
def _seeded(seed: int, device: torch.device) -> Iterator[None]:
    """A private torch RNG stream: the caller's RNG state is untouched afterwards."""
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


@torch.no_grad()
def _encode(model: PWM, ep: Episode, device: torch.device) -> torch.Tensor:
    with _eval_mode(model):
        return model.encode({k: torch.from_numpy(v).to(device) for k, v in ep.obs.items()})


@torch.no_grad()
def mean_routing(model: PWM, episodes: list[Episode], task: int,
                 device: torch.device) -> np.ndarray:  # fmt: skip
    """Mean routing weights (K * max_tasks,) over every visited (z_t, a_t) of `episodes`."""
    z = torch.cat([_encode(model, ep, device)[:-1] for ep in episodes])
    a = torch.cat([torch.from_numpy(ep.action).to(device) for ep in episodes])
    w = model.routing_weights(z, a, task)
    return w.double().mean(0).cpu().numpy()


@torch.no_grad()
def latent_error(model: PWM, episodes: list[Episode], task: int, horizon: int,
                 device: torch.device) -> float:  # fmt: skip
    """Open-loop latent prediction error: from encode(o_t), `horizon` dynamics steps with the
    recorded actions; squared error to encode(o_{t+k}) averaged over latent dims, k and t."""
    errors = []
    with _eval_mode(model), model.routing_task(task):
        for ep in episodes:
            steps = len(ep.action)
            if steps < horizon:
                continue
            target = _encode(model, ep, device)
            starts = steps - horizon + 1
            actions = torch.from_numpy(ep.action).to(device)
            z = target[:starts]
            per_k = []
            for k in range(1, horizon + 1):
                z = model.next(z, actions[k - 1 : k - 1 + starts])
                per_k.append((z - target[k : k + starts]).pow(2).mean(-1))
            errors.append(torch.stack(per_k).mean(0))
    if not errors:
        raise ValueError(f"no evaluation episode is at least {horizon} steps long")
    return float(torch.cat(errors).double().mean())


# ===================================================================== routing record


def routing_record(model: PWM, stored_heads: list, task_ids: list[str], *, stage: int, seed: int,
                   episodes: int, obs_mode: str, image_size: int = 64,
                   device: torch.device | str = "cpu",
                   view: Callable[[int], contextlib.AbstractContextManager] | None = None,
                   ) -> dict:  # fmt: skip
    """Routing after stage `stage`: for every task i <= stage, its evaluation episodes played
    with `stored_heads[i]` and the mean weight of every expert over the visited (z, a).

    `view(i)`: the continual method's evaluation context of task i (PackNet's masks)."""
    if not isinstance(model, PWM):
        raise ValueError(f"routing records need a PWM model, got {type(model).__name__}")
    if len(stored_heads) <= stage or len(task_ids) <= stage:
        raise ValueError(f"stage {stage}: need heads and task ids of tasks 0..{stage}")
    device = torch.device(device)
    mixture = model.dynamics
    tasks = []
    with _eval_mode(model):
        for i in range(stage + 1):
            heads = stored_heads[i]
            routed = int(heads.task_index)
            env = make_env(task_ids[i], render=obs_mode == "pixels", image_size=image_size)
            try:
                ctx = view(i) if view is not None else contextlib.nullcontext()
                with ctx, _seeded(derived_seed(seed, _ROUTING_TAG, stage, i), device):
                    eps = play_episodes(env, model, heads, obs_mode=obs_mode, device=device,
                                        seeds=eval_seeds(seed, i, episodes))  # fmt: skip
                    weights = mean_routing(model, eps, routed, device)
            finally:
                env.close()
            ret = float(np.mean([discounted_return(e.rewards, GAMMA) for e in eps]))
            tasks.append({
                "task_index": i, "task": task_ids[i], "routed_as": routed,
                "samples": int(sum(len(e.action) for e in eps)),
                "normalized_return": normalized_or_none(task_ids[i], ret),
                "weights": [float(w) for w in weights],
            })  # fmt: skip
    return {
        "stage": stage, "task": task_ids[stage], "episodes": episodes,
        "num_active": mixture.num_active, "experts_per_task": mixture.k,
        "max_experts": mixture.max_experts, "tasks": tasks,
    }  # fmt: skip


def read_routing(run_dir: str | Path) -> list[dict]:
    """The records of `routing.jsonl`, by stage (they must be stages 0, 1, ...)."""
    path = Path(run_dir) / ROUTING
    if not path.is_file():
        raise ValueError(f"no {ROUTING} in {run_dir} (only PWM curriculum runs write one)")
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


def record_stage_routing(run_dir: str | Path, cfg, model, stored_heads: list, method,
                         device: torch.device) -> dict | None:  # fmt: skip
    """The curriculum's hook after a task's heads are stored: appends the routing of stage
    len(stored_heads) - 1 to `routing.jsonl` (PWM models only; None otherwise)."""
    if not isinstance(model, PWM):
        return None
    stage = len(stored_heads) - 1
    record = routing_record(
        model, stored_heads, cfg.tasks, stage=stage, seed=cfg.seed,
        episodes=cfg.train_config().eval_episodes, obs_mode=cfg.obs,
        image_size=cfg.image_size, device=device,
        view=lambda i: method.evaluating(i, model.backbone),
    )  # fmt: skip
    append_routing(run_dir, record)
    return record


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
    fig.suptitle(f"{config['suite']} / {config['model']} / {config['method']} / seed "
                 f"{config['seed']}: {statement}", fontsize=10)  # fmt: skip
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return {**data, "statement": statement}


def report_routing(runs, out: Path) -> tuple[list[Path], dict[tuple, dict]]:
    """`ccfit report`'s part: Fig. 5 of every run (ccfit.report.Run) with routing.jsonl.

    Returns the PNGs and, per (backbone, suite, method) key, {'s<seed>': top-expert summary}."""
    written, summary = [], {}
    for run in runs:
        if not (run.path / ROUTING).is_file():
            continue
        backbone, suite, method = run.key
        prefix = "routing" if backbone == "pwm" else f"routing_{backbone}"
        path = out / f"{prefix}_{suite}_{method}_s{run.config['seed']}.png"
        data = plot_routing(run.path, path)
        top = data["top_expert"]
        summary.setdefault(run.key, {})[f"s{run.config['seed']}"] = {
            "top_expert_stays_top": top["k"], "of": top["n"], "statement": data["statement"],
        }  # fmt: skip
        written.append(path)
    return written, summary


# ====================================================================== Fig. 6: ablation


def load_run(run_dir: str | Path, device: torch.device | str | None = None):
    """A finished PWM curriculum run: (CurriculumConfig, model, stored heads, method)."""
    from ccfit.continual import make_method
    from ccfit.curriculum import STATE, CurriculumConfig, _build

    run_dir = Path(run_dir)
    if not (run_dir / CONFIG).is_file():
        raise ValueError(f"{run_dir} is not a run directory (no {CONFIG})")
    saved = json.loads((run_dir / CONFIG).read_text())
    names = {f.name for f in dataclasses.fields(CurriculumConfig)}
    cfg = CurriculumConfig(**{k: v for k, v in saved.items() if k in names})
    if cfg.model != "pwm":
        raise ValueError(f"{run_dir}: expert ablation needs a PWM run, this is a {cfg.model} run")
    state_path = run_dir / STATE
    if not state_path.is_file():
        raise ValueError(f"{run_dir}: run not finished (no {STATE})")
    state = torch.load(state_path, map_location="cpu", weights_only=False)
    if int(state["completed"]) < len(cfg.tasks):
        done = int(state["completed"])
        raise ValueError(f"{run_dir}: run not finished ({done} of {len(cfg.tasks)} tasks done)")
    device = torch.device(device) if device is not None else resolve_device(
        cfg.train_config().device
    )  # fmt: skip
    model = _build(cfg, device)
    method = make_method(cfg.method, num_tasks=len(cfg.tasks), **cfg.method_options)
    model.load_state_dict(state["model"])
    method.load_state_dict(state["method"])
    stored = []
    for heads_state in state["heads"]:
        heads = model.new_heads()
        heads.load_state_dict(heads_state)  # restores the stamped task_index too
        stored.append(heads.requires_grad_(False).eval())
    model.eval()
    return cfg, model, stored, method


def ablate(run_dir: str | Path, episodes: int | None = None, horizon: int | None = None,
           device: torch.device | str | None = None) -> dict:  # fmt: skip
    """Fig. 6 for one finished PWM run: writes `ablation.json` and `ablation.png` in it.

    episodes: evaluation layouts of the composition task (default: the run's eval_episodes);
    horizon: open-loop steps H (default: the model's planning horizon)."""
    run_dir = Path(run_dir)
    cfg, model, stored, method = load_run(run_dir, device)
    train = cfg.train_config()
    if train.torch_threads > 0:
        torch.set_num_threads(train.torch_threads)
    device = model.device
    mixture = model.dynamics
    if int(mixture.num_groups) < 2:
        raise ValueError(
            f"{run_dir}: one expert group only (method {cfg.method!r}); the ablation compares "
            "prior and new experts of a run with method 'experts'"
        )
    episodes = train.eval_episodes if episodes is None else int(episodes)
    horizon = int(model.cfg.horizon) if horizon is None else int(horizon)
    if episodes < 1 or horizon < 1:
        raise ValueError(f"episodes and horizon must be >= 1, got {episodes} and {horizon}")
    comp = len(cfg.tasks) - 1
    task_id, heads = cfg.tasks[comp], stored[comp]
    routed = int(heads.task_index)
    seeds = eval_seeds(cfg.seed, comp, episodes)
    env = make_env(task_id, render=cfg.obs == "pixels", image_size=cfg.image_size)
    modes: dict[str, dict] = {}
    recorded: list[Episode] = []
    try:
        for name, override in ABLATION_MODES.items():
            # The same MPPI noise stream for every mode: differences come from the routing.
            with method.evaluating(comp, model.backbone), model.routing_override(override), \
                    _seeded(derived_seed(cfg.seed, _ABLATION_TAG, 0, comp), device):  # fmt: skip
                eps = play_episodes(env, model, heads, obs_mode=cfg.obs, seeds=seeds,
                                    device=device)  # fmt: skip
                recorded = recorded or eps  # the full mixture's trajectories (first mode)
                weights = mean_routing(model, eps, routed, device)
                error = latent_error(model, recorded, routed, horizon, device)
            ret = float(np.mean([discounted_return(e.rewards, GAMMA) for e in eps]))
            k, n = mixture.k, mixture.num_active
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
        env.close()
    full = modes["full"]
    for m in modes.values():
        nr, base = m["normalized_return"], full["normalized_return"]
        m["return_ratio"] = nr / base if nr is not None and base is not None and base > 0 else None
        e, e0 = m["latent_error"], full["latent_error"]
        m["latent_error_ratio"] = e / e0 if e0 > 0 else None
        m["fidelity_ratio"] = e0 / e if e > 0 else None
    result = {
        "run": str(run_dir), "suite": cfg.suite, "method": cfg.method, "seed": cfg.seed,
        "task": task_id, "task_index": comp, "episodes": episodes, "horizon": horizon,
        "num_active": mixture.num_active, "experts_per_task": mixture.k, "modes": modes,
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
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return Path(out)
