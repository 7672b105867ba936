"""What is measured on recorded evaluation episodes of a routed model (capability 'routing',
e.g. the prismatic world model): mean routing weights and the open-loop latent error."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import torch

from ccfit.models.base import Routing
from ccfit.train.evaluate import Episode

ROUTING = "routing.jsonl"
ABLATION_JSON = "ablation.json"
ABLATION_PNG = "ablation.png"
ABLATION_MODES: dict[str, str | None] = {
    "full": None, "prior": "prior", "new": "new", "uniform": "uniform",
}  # fmt: skip
"""Ablation name -> `Routing.routing_override` mode."""
_ROUTING_TAG, _ABLATION_TAG = 10, 11  # seed streams beside ccfit.train's 0..3


@contextlib.contextmanager
def _eval_mode(model: torch.nn.Module) -> Iterator[None]:
    was = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was)


@torch.no_grad()
def _encode(model: Routing, ep: Episode, device: torch.device) -> torch.Tensor:
    with _eval_mode(model):
        return model.encode({k: torch.from_numpy(v).to(device) for k, v in ep.obs.items()})


@torch.no_grad()
def mean_routing(model: Routing, episodes: list[Episode], task: int,
                 device: torch.device) -> np.ndarray:  # fmt: skip
    """Mean routing weights (K * max_tasks,) over every visited (z_t, a_t) of `episodes`."""
    z = torch.cat([_encode(model, ep, device)[:-1] for ep in episodes])
    a = torch.cat([torch.from_numpy(ep.action).to(device) for ep in episodes])
    w = model.routing_weights(z, a, task)
    return w.double().mean(0).cpu().numpy()


@torch.no_grad()
def latent_error(model: Routing, episodes: list[Episode], task: int, horizon: int,
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
