"""PWM (prismatic world model, Li et al. 2025): TD-MPC2 whose latent dynamics is a mixture of
experts, with the benchmark's progressive (continual) variant in mind; its config `PWMConfig`
(registered as model 'pwm').

Everything but the dynamics is TD-MPC2's (losses, heads, planning are inherited). The dynamics
`MixtureDynamics` computes

    feature_k = expert_k([z, a])                     2 NormedLinear layers per expert
    feature   = GramSchmidt(feature_1..K)            optional, orthonormal, activation order
    w         = softmax(router([gate_input, tau]) / tau)   over the active experts only
    z'        = SimNorm(head(sum_k w_k feature_k))   shared head

Experts come in groups of K = `experts_per_task`, allocated up front for `max_tasks` groups so
the parameter set never changes shape (checkpoints and optimisers stay valid); only the first
`num_groups` groups are active (computed, routable); inactive experts get weight exactly 0
(masked logits) and have requires_grad False. Group 0 is active from the start, so under
FT / ER / EWC / PackNet PWM is a fixed mixture of K experts; the 'experts' continual method
(ccfit.continual.experts) activates one group per task and freezes the earlier ones.

Gate input, `router`:
- 'task' (default, as in the authors' code): the one-hot task identity over `max_tasks`,
  followed by tau. With a bias-free router this is a learnt per-task logit table (one column
  per task) plus a shared tau column: training task t only moves column t (and the tau
  column), so earlier tasks' routing is left alone. A one-hot is used instead of a learnt
  embedding because it keeps that separation exact and needs no extra parameters.
- 'state': [z, a, tau], routing that can change within an episode.

The task of every sample is known: batches carry `task` per row and a window routes with
the task of its row 0 (where its rollout starts); heads are stamped with the task they
belong to (`PWMHeads.task_index`), which routes planning. A task's routing therefore never
depends on which task is being trained.

Temperature: one tau per task (a buffer, checkpointed). A task's tau starts at `tau_init`, is
held for max(tau_hold_min, tau_hold_frac * task steps) training updates of that task, then
after every update moves as tau <- clip(tau + tau_rate * tanh(H_target - H(w)), tau_min,
tau_max), H_target = tau_target_frac * log(active experts), H(w) the mean routing entropy over
the update's batch (all rollout steps). The authors keep a single tau reset at each new task;
as tau enters every task's routing, that silently re-routes finished tasks (they added a
switch to freeze it). One tau per task follows the same schedule while training a task and
keeps finished tasks' routing a function of parameters only (what PackNet protects).

Continual use, per task i: `model.begin_task(i, task_steps)`, then `model.new_heads()`
(stamped with task i); `with model.routing_override("prior" | "new" | "uniform")` ablates the
routing for analysis, `model.routing_weights(z, a, task)` reads it.
"""

from ccfit.models.pwm.config import PWM_ROUTERS, PWMConfig
from ccfit.models.pwm.mixture import OVERRIDES, MixtureDynamics, gram_schmidt
from ccfit.models.pwm.model import PWM, PWMHeads

__all__ = [
    "OVERRIDES", "PWM", "PWMConfig", "PWMHeads", "PWM_ROUTERS", "MixtureDynamics",
    "gram_schmidt",
]  # fmt: skip
