"""Routing analysis and expert ablation of a continual run of a routed model (the paper's
Sec. V-B; any model offering the 'routing' capability gets them).

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
stage j, the 'experts' method); under other methods a routed model keeps one group, owned
by task 0.

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

from ccfit.analysis.ablation import ablate, load_routed_run, plot_ablation
from ccfit.analysis.episodes import (
    ABLATION_JSON,
    ABLATION_MODES,
    ABLATION_PNG,
    ROUTING,
    latent_error,
    mean_routing,
)
from ccfit.analysis.hooks import register_analysis, stage_callbacks
from ccfit.analysis.routing import (
    append_routing,
    figure_data,
    plot_routing,
    read_routing,
    report_routing,
    routing_callback,
    routing_record,
    top_statement,
)

__all__ = [
    "ABLATION_JSON", "ABLATION_MODES", "ABLATION_PNG", "ROUTING", "ablate",
    "append_routing", "figure_data", "latent_error", "load_routed_run", "mean_routing",
    "plot_ablation", "plot_routing", "read_routing", "register_analysis", "report_routing",
    "routing_callback", "routing_record", "stage_callbacks", "top_statement",
]  # fmt: skip
