"""DreamerV3: parameter counts of the presets and seconds per update. Prints JSON.

One update = `loss` + backward + world-model step + `head_update` (imagination, actor and
critic steps), on a synthetic batch of the preset's size (batch_size x seq_len), one torch
thread by default. Parameter counts of the `paper` preset are taken on the meta device (no
memory). The machine may be shared: timings are indicative only.

    python bench/dreamerv3_update.py --presets cpu --modes state --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from ccfit.models.base import Batch
from ccfit.models.dreamerv3 import DreamerV3, DreamerV3Config


def synthetic_batch(cfg: DreamerV3Config, gen: torch.Generator) -> Batch:
    """Random data with replay's shapes and dtypes; an episode boundary in every window."""
    length, size = cfg.seq_len, cfg.batch_size
    if cfg.obs_mode == "state":
        obs = {"state": torch.randn(length, size, cfg.state_dim, generator=gen)}
    else:
        s = cfg.image_size
        obs = {
            "pixels": torch.randint(
                0, 256, (length, size, 9, s, s), generator=gen, dtype=torch.uint8
            ),
            "proprio": torch.randn(length, size, cfg.proprio_dim, generator=gen),
        }
    is_first = torch.zeros(length, size, 1)
    is_first[length // 2] = 1.0
    return Batch(
        obs,
        torch.rand(length, size, cfg.action_dim, generator=gen) * 2 - 1,
        -torch.rand(length, size, 1, generator=gen),
        torch.zeros(length, size, 1),
        is_first,
        torch.zeros(length, size, dtype=torch.long),
    )


def count(cfg: DreamerV3Config, device: str) -> dict:
    with torch.device(device):
        model = DreamerV3(cfg, device=device)
        heads = model.new_heads()
    trainable = [p for p in heads.parameters() if p.requires_grad]
    return {
        "backbone": sum(p.numel() for p in model.backbone.parameters()),
        "heads": sum(p.numel() for p in trainable),
    }


def time_updates(cfg: DreamerV3Config, repeats: int) -> dict:
    torch.manual_seed(0)
    model = DreamerV3(cfg, device="cpu")
    heads = model.new_heads()
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    params = [p for g in opt.param_groups for p in g["params"]]
    batch = synthetic_batch(cfg, torch.Generator().manual_seed(0))
    world, behave = [], []
    for i in range(repeats + 1):  # the first update warms up allocators
        t0 = time.perf_counter()
        out = model.loss(batch, heads)
        opt.zero_grad()
        out.total.backward()
        torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        t1 = time.perf_counter()
        model.head_update(batch, heads, out, head_opts)
        t2 = time.perf_counter()
        if i:
            world.append(t1 - t0)
            behave.append(t2 - t1)
    w, b = statistics.median(world), statistics.median(behave)
    return {"world_model_s": round(w, 3), "head_update_s": round(b, 3), "update_s": round(w + b, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["smoke", "cpu"])
    ap.add_argument("--modes", nargs="+", default=["state", "pixels"])
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-timing", action="store_true", help="parameter counts only")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for preset in args.presets:
        for mode in args.modes:
            cfg = DreamerV3Config.preset(preset, obs_mode=mode, image_size=args.image_size)
            row = {
                "preset": preset,
                "obs_mode": mode,
                "image_size": args.image_size,
                "batch": [cfg.batch_size, cfg.seq_len],
                "imag_last": cfg.imag_last,
                "threads": args.threads,
                "params": count(cfg, "meta" if preset == "paper" else "cpu"),
            }
            if preset != "paper" and not args.no_timing:
                row.update(time_updates(cfg, args.repeats))
            rows.append(row)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
