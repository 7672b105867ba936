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

Scope (`routing_scope`, default 'own'): task t routes over the groups 0..t only (the experts
that existed while it trained), in training, replay, planning and evaluation alike, as in the
authors' progressive runs (task j evaluated with experts [0, (j+1)K)). With 'all' a finished
task's softmax takes in every later group's fresh experts (router rows initialised near 0, so
a large share of the weight) and its dynamics change the moment a group is added.

Gate input, `router`:
- 'task' (default, as in the authors' code): the one-hot task identity over `max_tasks`,
  followed by tau. With a bias-free router this is a learnt per-task logit table (one column
  per task) plus a tau column shared by all tasks: training task t moves column t and the tau
  column, so a finished task's routing over its own groups drifts through the tau column
  unless the 'experts' method holds it (`freeze_shared`, its default; the authors' driver
  leaves it trainable by default). A one-hot is used instead of a learnt embedding because it
  needs no extra parameters.
- 'state': [z, a, tau], routing that can change within an episode.
Experts see [z, a]; the authors' code also feeds them the task one-hot (FACTS.md: [z, a]).

The task of every sample is known: batches carry `task` per row and a window routes with
the task of its row 0 (where its rollout starts); heads are stamped with the task they
belong to (`PWMHeads.task_index`), which routes planning. A task's routing therefore never
depends on which task is being trained.

Temperature: one tau per task (a buffer, checkpointed), as the authors' per-task snapshot.
A task's tau starts at `tau_init`, is held for the first max(tau_hold_min, tau_hold_frac *
task steps) dynamics steps of that task's training (each update rolls out seq_len - 1), then
after every training forward of the dynamics moves as tau <- clip(tau + tau_rate *
tanh(H_target - H(w)), tau_min, tau_max), as the authors' router does on every training
forward; H_target = tau_target_frac * log(the experts the task routes over), H(w) that
forward's mean routing entropy. Finished tasks keep their tau.

Continual use, per task i: `model.begin_task(i, task_steps)`, then `model.new_heads()`
(stamped with task i); `with model.routing_override("prior" | "new" | "uniform")` ablates the
routing for analysis, `model.routing_weights(z, a, task)` reads it.
"""

from ccfit.models.pwm.config import PWM_ROUTERS, PWM_SCOPES, PWMConfig
from ccfit.models.pwm.mixture import OVERRIDES, MixtureDynamics, gram_schmidt
from ccfit.models.pwm.model import PWM, PWMHeads

__all__ = [
    "OVERRIDES", "PWM", "PWMConfig", "PWMHeads", "PWM_ROUTERS", "PWM_SCOPES", "MixtureDynamics",
    "gram_schmidt",
]  # fmt: skip
