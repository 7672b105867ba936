"""TD-MPC2 updates/s and MPPI plans/s: state and pixel modes, `cpu` and `paper` sizes (plus the
official 1M size), with and without a frozen encoder, and with the frozen encoder's latents cached
in replay (what `ccfit run --encoder frozen:PATH` does). Prints JSON.

Reference (the official TD-MPC2, eager mode, 2 threads, batch 256, on these machines):
1M state 0.156 s/update and 0.214 s/plan; 5M state 0.546 and 0.558; 5M 64 px 1.21 s/update.
Our `paper` preset is the official 5M configuration.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

from ccfit.models.base import Batch
from ccfit.models.encoders import load_frozen_encoder, save_encoder
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config

OFFICIAL_SECONDS = {
    ("1M", "state"): {"update": 0.156, "plan": 0.214},
    ("paper", "state"): {"update": 0.546, "plan": 0.558},
    ("paper", "pixels"): {"update": 1.21},
}


def synthetic_batch(cfg, batch_size: int, generator: torch.Generator) -> Batch:
    """Random data with the shapes and dtypes replay produces (values do not affect timing)."""
    steps = cfg.seq_len
    if cfg.obs_mode == "state":
        obs = {"state": torch.randn(steps, batch_size, cfg.state_dim, generator=generator)}
    else:
        size = cfg.image_size
        obs = {
            "pixels": torch.randint(
                0, 256, (steps, batch_size, 9, size, size), generator=generator, dtype=torch.uint8
            ),
            "proprio": torch.randn(steps, batch_size, cfg.proprio_dim, generator=generator),
        }
    return Batch(
        obs=obs,
        action=torch.rand(steps, batch_size, 4, generator=generator) * 2 - 1,
        reward=-torch.rand(steps, batch_size, 1, generator=generator),
        terminated=torch.zeros(steps, batch_size, 1),
        is_first=torch.zeros(steps, batch_size, 1),
        task=torch.zeros(steps, batch_size, dtype=torch.long),
    )


def time_model(
    preset: str, mode: str, frozen: bool, cached: bool, batch_size: int, repeats: int
) -> dict:
    torch.manual_seed(0)
    cfg = TDMPC2Config.preset(preset, obs_mode=mode)
    encoder = None
    if frozen:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "encoder.pt"
            save_encoder(TDMPC2(cfg, device="cpu").backbone.encoder, cfg, path)
            encoder, _ = load_frozen_encoder(path)
    model = TDMPC2(cfg, device="cpu", encoder=encoder)
    heads = model.new_heads()
    optim = model.world_model_optimizer(heads)
    head_optims = model.head_optimizers(heads)
    batch = synthetic_batch(cfg, batch_size, torch.Generator().manual_seed(0))
    if cached:  # replay then holds latents, encoded once when the episode was stored
        batch = dataclasses.replace(batch, obs=model.replay_obs(batch.obs))
    obs = {k: v[0, 0] for k, v in synthetic_batch(cfg, 1, torch.Generator()).obs.items()}

    def update() -> None:
        out = model.loss(batch, heads)
        optim.zero_grad(set_to_none=True)
        out.total.backward()
        torch.nn.utils.clip_grad_norm_(
            [p for g in optim.param_groups for p in g["params"]], cfg.grad_clip
        )
        optim.step()
        model.head_update(batch, heads, out, head_optims)

    state = model.act(obs, heads, None, eval_mode=False)[1]  # a warm-started plan is timed

    def plan() -> None:
        model.act(obs, heads, state, eval_mode=False)

    result = {}
    for name, fn in (("update", update), ("plan", plan)):
        fn()  # warm-up (allocator, first-call overheads)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        result[f"{name}_s_median"] = statistics.median(times)
        result[f"{name}s_per_s"] = 1.0 / statistics.median(times)
    result["parameters"] = model.num_parameters(heads)
    official = OFFICIAL_SECONDS.get((preset, mode))
    if official and not frozen:
        result["official_s"] = official
        result["speedup_vs_official"] = {k: official[k] / result[f"{k}_s_median"] for k in official}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--presets", default="cpu,1M,paper")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for preset in args.presets.split(","):
        variants = (("state", False, False), ("pixels", False, False), ("pixels", True, False),
                    ("pixels", True, True))  # fmt: skip
        for mode, frozen, cached in variants:
            if preset == "1M" and mode == "pixels":
                continue  # the official reference at 1M is state only
            row = {
                "preset": preset,
                "obs": mode,
                "frozen_encoder": frozen,
                "latents_cached": cached,
            }
            row.update(time_model(preset, mode, frozen, cached, args.batch_size, args.repeats))
            rows.append(row)
    print(
        json.dumps(
            {
                "batch_size": args.batch_size,
                "threads": args.threads,
                "cpu_count": os.cpu_count(),
                "torch": torch.__version__,
                "results": rows,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
