"""Mish forward + backward: torch's `F.mish` against `ccfit.models.layers.mish` (closed form,
one exp), eager and compiled, at the activation shapes of a `cpu`-size TD-MPC2 update
(batch 64 x 128 features; x4 rollout steps; x2 Q members). Prints JSON: median microseconds
per call and the ratio torch / ours (> 1: ours is faster). Without a gradient (planning: the
`smoke` and `cpu` plan's 32 x 64 and 72 x 128 activations) it also times the autograd
Function that `mish` used there before, against the plain closed form it uses now.

    python bench/mish.py --threads 1 --repeats 200

On a CPU torch's tanh costs about four exps, and Mish (tanh of a softplus) was a quarter of
a TD-MPC2 update there; compiled, the closed form fuses into one loop of cheap operations.
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time

import torch
import torch.nn.functional as F

from ccfit.models.layers import _Mish, mish
from ccfit.train.inductor_cache import prepare_inductor_cache

SHAPES = ((64, 128), (256, 128), (2, 256, 128))
PLAN_SHAPES = ((32, 64), (72, 128))


def _median_us(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    prepare_inductor_cache()
    gen = torch.Generator().manual_seed(0)
    rows = []
    for shape in SHAPES:
        x = (3 * torch.randn(*shape, generator=gen)).requires_grad_()
        grad = torch.randn(*shape, generator=gen)
        row = {"shape": list(shape)}
        for mode in ("eager", "compiled"):
            for name, act in (("torch", F.mish), ("ours", mish)):
                fn = torch.compile(act) if mode == "compiled" else act

                def step(fn=fn, x=x, grad=grad) -> None:
                    torch.autograd.grad(fn(x), x, grad)

                row[f"{mode}_{name}_us"] = _median_us(step, args.repeats, args.warmup)
            row[f"{mode}_ratio_torch_over_ours"] = row[f"{mode}_torch_us"] / row[f"{mode}_ours_us"]
        rows.append(row)
    no_grad = []
    for shape in PLAN_SHAPES:
        x = 3 * torch.randn(*shape, generator=gen)
        row = {"shape": list(shape)}
        with torch.no_grad():
            for name, act in (("torch", F.mish), ("function", _Mish.apply), ("ours", mish)):
                call = functools.partial(act, x)
                row[f"{name}_us"] = _median_us(call, args.repeats, args.warmup)
        row["ratio_function_over_ours"] = row["function_us"] / row["ours_us"]
        no_grad.append(row)
    print(json.dumps({"threads": args.threads, "repeats": args.repeats,
                      "torch": torch.__version__, "rows": rows, "no_grad": no_grad},
                     indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
