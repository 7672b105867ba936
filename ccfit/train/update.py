"""One update of a world model, as the loop makes it (the model contract's order, see
`ccfit.models.base`): the loss with this task's heads plus the continual method's penalty,
backward, global-norm clip, the world-model optimiser's step, the method's `after_step`, then
`head_update`. `bench/update_rate.py` times this same object."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from ccfit.continual.base import ContinualMethod, ReplayLosses
from ccfit.models.base import Batch, WorldModel
from ccfit.train.compiled import autocast


class UpdateStep:
    """The optimisers of one task's training and what an update needs besides the batch.

    stored_heads_loss: the loss of a batch through an earlier task's stored heads, offered to
    the method's penalty (`ReplayLosses`); autocast: `--train.autocast`."""

    def __init__(self, model: WorldModel, heads: nn.Module, method: ContinualMethod | None = None,
                 stored_heads_loss: Callable[[Batch, int], torch.Tensor] | None = None,
                 autocast: str = "off") -> None:  # fmt: skip
        self.model, self.heads, self.method, self.autocast = model, heads, method, autocast
        self.optim = model.world_model_optimizer(heads)
        self.clip_params = [p for g in self.optim.param_groups for p in g["params"]]
        self.head_optims = model.head_optimizers(heads)
        self.losses = ReplayLosses(model.backbone_loss, stored_heads_loss)

    def __call__(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One update on `batch` (on the model's device); the logs, as tensors (reading them
        back would make the host wait for the device)."""
        model, method = self.model, self.method
        model.train()
        with autocast(model.device, self.autocast):
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
        with autocast(model.device, self.autocast):
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
