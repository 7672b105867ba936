"""One update of a world model, as the loop makes it (the model contract's order, see
`ccfit.models.base`): the loss with this task's heads plus the continual method's penalty,
backward, global-norm clip, the world-model optimiser's step, the method's `after_step`, then
`head_update`. `bench/update_rate.py` times this same object."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from ccfit.config_base import check
from ccfit.continual.base import ContinualMethod, ReplayLosses
from ccfit.models.base import Batch, WorldModel
from ccfit.settings import AUTOCAST_MODES, autocast_context


class UpdateStep:
    """The optimisers of one task's training and what an update needs besides the batch.

    stored_heads_loss: the loss of a batch through an earlier task's stored heads, offered to
    the method's penalty (`ReplayLosses`); autocast: the run's precision, resolved ('off' or
    'bf16': `ccfit.settings.Execution.autocast`); graphs: the hot paths replay CUDA graphs
    (`--train.compile=graphs`)."""

    def __init__(self, model: WorldModel, heads: nn.Module, method: ContinualMethod | None = None,
                 stored_heads_loss: Callable[[Batch, int], torch.Tensor] | None = None,
                 autocast: str = "off", graphs: bool = False) -> None:  # fmt: skip
        check(autocast in AUTOCAST_MODES, f"UpdateStep takes a resolved precision "
                                          f"{AUTOCAST_MODES}, got {autocast!r}")  # fmt: skip
        self.model, self.heads, self.method, self.autocast = model, heads, method, autocast
        self.graphs = graphs
        self.optim = model.world_model_optimizer(heads)
        self.clip_params = [p for g in self.optim.param_groups for p in g["params"]]
        self.head_optims = model.head_optimizers(heads)
        self.losses = ReplayLosses(model.backbone_loss, stored_heads_loss)

    def __call__(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One update on `batch` (on the model's device); the logs, as tensors (reading them
        back would make the host wait for the device)."""
        model, method = self.model, self.method
        if self.graphs:
            # Every update a CUDA-graph step of its own, as the official TD-MPC2 marks them: a
            # forward whose backward never ran (none in this loop; a method's may) would
            # otherwise keep later calls in its generation.
            torch.compiler.cudagraph_mark_step_begin()
        model.train()
        with autocast_context(model.device, self.autocast):
            out = model.loss(batch, self.heads)
            total = out.total
            if method is not None:
                total = total + method.penalty(model.backbone, self.losses)
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.clip_params, model.cfg.grad_clip)
        self.optim.step()
        if method is not None:
            method.after_step(model.backbone)
        with autocast_context(model.device, self.autocast):
            head_logs = model.head_update(batch, self.heads, out, self.head_optims)
        return {**out.logs, **head_logs, "total": total.detach(), "grad_norm": grad_norm}

    def state_dict(self) -> dict:
        return {
            "optim": self.optim.state_dict(),
            "head_optims": {k: o.state_dict() for k, o in self.head_optims.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.optim.load_state_dict(state["optim"])
        for k, o in self.head_optims.items():
            o.load_state_dict(state["head_optims"][k])


def backbone_optimizer_state(optim: torch.optim.Optimizer, backbone: nn.Module) -> dict:
    """The per-parameter state `optim` holds for `backbone`'s parameters (Adam: step count and
    both moments), by parameter name: what a task hands the next when the backbone's optimiser
    state is kept across tasks (`keep_backbone_optimizer`). Heads' state is left behind."""
    names = {id(p): n for n, p in backbone.named_parameters()}
    return {names[id(p)]: {k: v.detach().clone() for k, v in optim.state[p].items()}
            for g in optim.param_groups for p in g["params"]
            if id(p) in names and p in optim.state}  # fmt: skip


def load_backbone_optimizer_state(optim: torch.optim.Optimizer, backbone: nn.Module,
                                  state: dict) -> None:  # fmt: skip
    """Give a fresh `optim` the `backbone_optimizer_state` of the previous task's optimiser,
    for the backbone parameters both step. Parameters `optim` does not step (frozen since,
    e.g. PackNet's biases or earlier experts) are skipped; those the previous optimiser did
    not step (new experts) start fresh. Goes through `load_state_dict`, which puts each
    tensor where this optimiser keeps it (device, dtype of the step count)."""
    params = dict(backbone.named_parameters())
    index = {id(p): i for i, p in enumerate(p for g in optim.param_groups for p in g["params"])}
    full = optim.state_dict()
    for name, param_state in state.items():
        param = params.get(name)
        if param is not None and id(param) in index:
            # Copies: Adam steps its state in place, and `state` may be used again.
            full["state"][index[id(param)]] = {k: v.clone() for k, v in param_state.items()}
    optim.load_state_dict(full)
