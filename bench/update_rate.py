"""Seconds per update and per acting step of the world models (TD-MPC2, DreamerV3) in state and
pixel modes at their presets, with a frozen encoder and with its latents cached in replay (what
`ccfit run --encoder frozen:PATH` does); DreamerV3 also at the sizes the dreamerv3-torch anchor
times. Prints one JSON object.

One update is what the training loop does (`ccfit.train.update.UpdateStep`, the loop's own
object, without replay sampling): loss, backward, global-norm clip, world-model step,
`head_update`, on a fixed synthetic batch with replay's shapes. One act is `model.act` on one
observation (TD-MPC2: a warm-started MPPI plan; DreamerV3: a posterior step and the actor).
Each is the median of --repeats calls after --warmup calls, as wall time and as CPU time of
this process (on a shared machine wall time inflates with other load; CPU time much less so).
Every row is timed per --modes: `eager` (`--train.compile=off`), `compiled` (every hot path
compiled, `--train.compile=on`), `auto` (what `--train.compile=auto` compiles on this device),
`bf16` (eager under `--train.autocast=bf16`), `auto-bf16` (both), `compile:PATH+PATH` (those
hot paths compiled, the rest eager: what decides `compile_pays`) and, on CUDA only, `graphs`
and `graphs-bf16` (`--train.compile=graphs`: every hot path replayed as CUDA graphs, as the
official TD-MPC2's `compile=true`); the first compiled calls (the compilation, and for CUDA
graphs the recording) are part of the warmup, not of the median.

--device picks where (default `auto`: CUDA when available, as `--train.device`): the model,
its optimisers and the synthetic batch live there, as replay on the GPU hands batches over.
On CUDA each timed call ends with a synchronisation, so the wall time is the device's work.

The roof: every row also counts the GFLOP of the matrix products in one update
(`update_gflop`, forward and backward, by torch's FLOP formulas; `act_gflop` for one act) and
divides it by the time (`update_gflop_per_s`) and by this machine's float32 matmul rate at the
same thread count (`matmul_peak_gflop_per_s`, square products;
`update_fraction_of_matmul_peak`; bf16 rows against the bf16 rate). A speed-up
target is only reachable while that fraction has room: an update that is all matmuls cannot
run faster than the peak. TD-MPC2 rows with an official reference time also give the official
update's rate on the same arithmetic (`official_update_gflop_per_s`).

    python bench/update_rate.py                          # default set, minutes on 2 cores
    python bench/update_rate.py --models tdmpc2,pwm,dreamerv3 --presets cpu --variants state \
        --modes eager,compiled,auto --threads 1
    python bench/update_rate.py --models dreamerv3 --presets cpu,paper --variants state,pixels
    python bench/update_rate.py --models dreamerv3 --presets none --threads 2 --repeats 5 \\
        --warmup 2 --sizes anchor-small,anchor-default,anchor-pixels --anchor-json dv3-torch.json

References on this machine (2 threads):
- official TD-MPC2 (e9f5932, eager, episodic), batch 256, quiet, in two rounds alternating with
  this script (../shared/tools/anchors/tdmpc2_official.py): 1M state 0.1145 s/update and
  0.170 s/plan; 5M state 0.3915 and 0.449 (our `paper` preset is the official 5M); 5M 64 px
  1.21 s/update (an earlier, single measurement).
- dreamerv3-torch (object814 fork), batch 16 x 64, imagination from all 1024 starts:
  ../shared/tools/anchors/run_dreamerv3.sh; pass its JSON as --anchor-json to get the ratio
  anchor / ours per size (> 1: ours is faster). Anchor sizes (`ANCHOR_SIZES`): anchor-small =
  its `cpu` (0.74M parameters), anchor-default = its defaults (18.7M), anchor-pixels = defaults
  with 64 px 9-channel images + 7-D proprio (28.4M).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

from ccfit.config_base import ConfigError, resolve_device
from ccfit.models import make_model
from ccfit.models.base import Batch, select_state
from ccfit.models.encoders import load_frozen_encoder, save_encoder
from ccfit.models.registry import config_class, model_class
from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config
from ccfit.settings import cpu_info
from ccfit.train.compiled import autocast, compile_hot_paths
from ccfit.train.update import UpdateStep

MODELS = ("tdmpc2", "pwm", "dreamerv3")
CPU = torch.device("cpu")
DEFAULT_PRESETS = {"tdmpc2": ("cpu", "1M", "paper"), "pwm": ("cpu",), "dreamerv3": ("cpu",)}
"""Presets timed when --presets is not given (DreamerV3 `paper`, ~128M parameters, takes
minutes per update on a CPU: ask for it)."""
VARIANTS = {  # name -> (obs mode, frozen encoder, latents cached in replay)
    "state": ("state", False, False),
    "pixels": ("pixels", False, False),
    "frozen": ("pixels", True, False),
    "cached": ("pixels", True, True),
}
OFFICIAL_TDMPC2_S = {  # medians of two rounds alternating with ours, quiet (the docstring)
    ("1M", "state"): {"update": 0.1145, "act": 0.170},
    ("paper", "state"): {"update": 0.3915, "act": 0.449},
    ("paper", "pixels"): {"update": 1.21},
}
_ANCHOR_SMALL = dict(deter=256, hidden=64, stoch=16, classes=8, units=128, layers=2)
_ANCHOR_DEFAULT = dict(deter=512, hidden=512, stoch=32, classes=32, units=512, layers=2,
                       vector_units=1024, vector_layers=5, cnn_depth=32)  # fmt: skip
ANCHOR_SIZES: dict[str, tuple[str, str, dict]] = {
    # name -> (anchor config name, obs mode, DreamerV3Config fields). Common to all: batch
    # 16 x 64, horizon 15, imagination from every posterior (imag_last 0), 64 px images.
    "anchor-small": ("cpu", "state", _ANCHOR_SMALL),
    "anchor-default": ("default", "state", _ANCHOR_DEFAULT),
    "anchor-pixels": ("default-rgb", "pixels", _ANCHOR_DEFAULT),
}
_ANCHOR_COMMON = dict(batch_size=16, seq_len=64, horizon=15, imag_last=0, image_size=64)


def synthetic_batch(cfg, generator: torch.Generator) -> Batch:
    """Random data with replay's shapes and dtypes; every window starts an episode (values do
    not affect timing)."""
    steps, size = cfg.seq_len, cfg.batch_size
    if cfg.obs_mode == "state":
        obs = {"state": torch.randn(steps, size, cfg.state_dim, generator=generator)}
    else:
        s = cfg.image_size
        obs = {
            "pixels": torch.randint(0, 256, (steps, size, 9, s, s), generator=generator,
                                    dtype=torch.uint8),
            "proprio": torch.randn(steps, size, cfg.proprio_dim, generator=generator),
        }  # fmt: skip
    is_first = torch.zeros(steps, size, 1)
    is_first[0] = 1.0
    return Batch(
        obs=obs,
        action=torch.rand(steps, size, cfg.action_dim, generator=generator) * 2 - 1,
        reward=-torch.rand(steps, size, 1, generator=generator),
        terminated=torch.zeros(steps, size, 1),
        is_first=is_first,
        task=torch.zeros(steps, size, dtype=torch.long),
    )


def frozen_encoder(cfg, preset: str):
    """A frozen pixel encoder as `ccfit pretrain-encoder` makes it: the TD-MPC2 encoder of the
    preset of the same name (random weights; only its cost matters here)."""
    enc_cfg = TDMPC2Config.preset(preset if preset in TDMPC2Config.PRESETS else "cpu",
                                  obs_mode="pixels", image_size=cfg.image_size)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "encoder.pt"
        save_encoder(TDMPC2(enc_cfg, device="cpu").backbone.encoder, enc_cfg, path)
        return load_frozen_encoder(path)[0]


def count_parameters(model, heads) -> dict[str, int]:
    """Trainable parameters of backbone and heads (target / slow copies excluded)."""
    if hasattr(model, "num_parameters"):
        return model.num_parameters(heads)
    out = {
        "backbone": sum(p.numel() for p in model.backbone.parameters() if p.requires_grad),
        "heads": sum(p.numel() for p in heads.parameters() if p.requires_grad),
    }
    out["total"] = out["backbone"] + out["heads"]
    return out


def _median_times(fn, repeats: int, warmup: int, device: torch.device = CPU,
                  budget_s: float | None = None) -> dict[str, float]:  # fmt: skip
    """Medians of `repeats` calls after `warmup`; on CUDA each call's time includes waiting
    for the work it queued (a call returns before the device has done it). `budget_s`: stop
    timing once the timed calls took this long, after three at least."""

    def call() -> None:
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(warmup):  # allocator, first-call overheads
        call()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        call()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
        if budget_s is not None and len(wall) >= 3 and sum(wall) > budget_s:
            break
    return {"wall": statistics.median(wall), "cpu": statistics.median(cpu)}


MODES = {  # name -> (--train.compile, --train.autocast)
    "eager": ("off", "off"), "compiled": ("on", "off"), "auto": ("auto", "off"),
    "bf16": ("off", "bf16"), "auto-bf16": ("auto", "bf16"),
    "graphs": ("graphs", "off"), "graphs-bf16": ("graphs", "bf16"),
}  # fmt: skip
GRAPH_MODES = ("graphs", "graphs-bf16")
"""Modes replayed as CUDA graphs (`--train.compile=graphs`), CUDA only."""


def _compiled_paths_of(mode: str) -> list[str] | None:
    """`compile:loss+head_update` -> ['loss', 'head_update'] (those hot paths compiled, the
    rest eager); None for the named modes."""
    return mode.removeprefix("compile:").split("+") if mode.startswith("compile:") else None


def batch_act(model, heads, cfg, n: int, precision: str):
    """One act on n observations from a warm acting state (what several training envs
    stepping together would ask of the model per step)."""
    many = dataclasses.replace(cfg, batch_size=n)
    obs = {k: v[0, :n].to(model.device)
           for k, v in synthetic_batch(many, torch.Generator()).obs.items()}  # fmt: skip
    with torch.no_grad(), autocast(model.device, precision):
        state = model.act(obs, heads, model.initial_state(heads, n), eval_mode=False)[1]
    # A copy (indexing copies): replayed as a CUDA graph, the next act overwrites this one's
    # outputs.
    state = select_state(state, torch.arange(n))

    def act() -> None:
        with torch.no_grad(), autocast(model.device, precision):
            model.act(obs, heads, state, eval_mode=False)

    return act


def time_model(cfg, preset: str, frozen: bool, cached: bool, repeats: int, warmup: int,
               mode: str = "eager", act_batches: list[int] = (),
               device: torch.device = CPU) -> dict:  # fmt: skip
    """Times one update and one act of the model of `cfg` on `device`, run as `mode` says;
    and one act on each batch of `act_batches` observations (episodes acting together)."""
    compile_setting, precision = MODES.get(mode, ("on", "off"))
    paths = _compiled_paths_of(mode)
    torch.manual_seed(0)
    model = make_model(cfg, device, encoder=frozen_encoder(cfg, preset) if frozen else None)
    model.begin_task(0, 1000)
    heads = model.new_heads()
    batch = synthetic_batch(cfg, torch.Generator().manual_seed(0)).to(device)
    if cached:  # replay then holds latents, encoded once when the episode was stored
        batch = dataclasses.replace(batch, obs=model.replay_obs(batch.obs))
    # a warm-started plan / a mid-episode recurrent state is timed
    act = batch_act(model, heads, cfg, 1, precision)

    # Counted eager, before compiling: the same arithmetic.
    gflop = {"update": matmul_gflop(lambda: UpdateStep(model, heads)(batch)),
             "act": matmul_gflop(act)}  # fmt: skip
    compiled = compile_hot_paths(model, compile_setting, paths)
    step = UpdateStep(model, heads, autocast=precision, graphs=mode in GRAPH_MODES)
    update = functools.partial(step, batch)
    result = {
        "mode": mode,
        "compiled": compiled,
        "autocast": precision,
        "parameters": count_parameters(model, heads),
        "update_gflop": gflop["update"],
        "act_gflop": gflop["act"],
    }
    for name, fn in (("update", update), ("act", act)):
        t = _median_times(fn, repeats, warmup, device)
        result[f"{name}_s_median"] = t["wall"]
        result[f"{name}_cpu_s_median"] = t["cpu"]
    if act_batches:
        acts = {n: batch_act(model, heads, cfg, n, precision) for n in act_batches}
        result["act_s_median_by_batch"] = {
            n: _median_times(act_n, repeats, warmup, device)["wall"] for n, act_n in acts.items()
        }
    # The names run_tdmpc2.sh reads (an MPPI plan is TD-MPC2's act).
    result["plan_s_median"] = result["act_s_median"]
    result["updates_per_s"] = 1.0 / result["update_s_median"]
    for name in ("update", "act"):
        result[f"{name}_gflop_per_s"] = result[f"{name}_gflop"] / result[f"{name}_s_median"]
    return result


def matmul_gflop(fn) -> float:
    """GFLOP of the matrix products (mm, addmm, bmm, convolutions; forward and backward) one
    call of `fn` does: the arithmetic no implementation of the same update can skip. Counted
    with torch's FLOP formulas by a dispatch mode of its own: `FlopCounterMode`'s module tracker
    fails on DreamerV3's imagination."""
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils.flop_counter import flop_registry

    class Count(TorchDispatchMode):
        flop = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            formula = flop_registry.get(func._overloadpacket)
            if formula is not None:
                self.flop += formula(*args, **(kwargs or {}), out_val=out)
            return out

    with Count() as counter:
        fn()
    return counter.flop / 1e9


def matmul_peak_gflop_per_s(device: torch.device = CPU,
                            dtype: torch.dtype = torch.float32,
                            repeats: int = 20) -> dict[str, float]:  # fmt: skip
    """`device`'s matmul rate in `dtype` (on a CPU at the current thread count), for square
    products of a few sizes: the roof an update made of matmuls cannot pass (median per
    size). Random operands: zeros multiply faster on some hardware. At most about two seconds
    of timed calls per size: a CPU without bf16 instructions emulates them at ~1 GFLOP/s, and
    its bf16 peak at 20 + 3 products per size took 62 s of a 1-thread run (2-core EPYC)."""
    rates = {}
    sizes = (1024, 4096, 8192) if device.type == "cuda" else (256, 512, 1024)
    for n in sizes:
        a, b = (torch.randn(n, n, device=device, dtype=dtype) for _ in range(2))
        t = _median_times(lambda a=a, b=b: torch.mm(a, b), repeats, 1, device,
                          budget_s=2.0)["wall"]  # fmt: skip
        rates[str(n)] = 2 * n**3 / t / 1e9
    return rates


def rows_to_time(args) -> list[dict]:
    """(model, preset or size, variant, config) of every requested row, in order."""
    rows = []
    for name in args.models:
        cls = config_class(name)
        presets = DEFAULT_PRESETS[name] if args.presets is None else args.presets
        for preset in presets:
            if preset not in cls.PRESETS:
                continue  # e.g. TD-MPC2's '1M' for DreamerV3
            for variant in args.variants:
                mode, frozen, cached = VARIANTS[variant]
                if name == "tdmpc2" and preset == "1M" and mode == "pixels":
                    continue  # the official reference at 1M is state only
                over = {"obs_mode": mode, "image_size": args.image_size}
                if args.batch_size:
                    over["batch_size"] = args.batch_size
                rows.append(
                    dict(
                        model=name,
                        preset=preset,
                        obs=mode,
                        frozen_encoder=frozen,
                        latents_cached=cached,
                        cfg=cls.preset(preset, **over),
                    )
                )
        if name == "dreamerv3":
            for size in args.sizes:
                _, mode, fields = ANCHOR_SIZES[size]
                over = {**_ANCHOR_COMMON, **fields, "obs_mode": mode}
                if args.batch_size:
                    over["batch_size"] = args.batch_size
                rows.append(
                    dict(
                        model=name,
                        preset=size,
                        obs=mode,
                        frozen_encoder=False,
                        latents_cached=False,
                        cfg=cls(**over),
                    )
                )
    return rows


def attach_references(row: dict, anchor: dict | None, device: torch.device) -> None:
    """The reference times measured on this 2-core CPU, on rows timed on a CPU only (a GPU
    row against them would be a ratio of two machines)."""
    if device.type != "cpu":
        return
    official = OFFICIAL_TDMPC2_S.get((row["preset"], row["obs"]))
    if row["model"] == "tdmpc2" and official and not row["frozen_encoder"]:
        row["official_s"] = official
        row["speedup_vs_official"] = {k: v / row[f"{k}_s_median"] for k, v in official.items()}
        # The same architecture and batch: the same matmul arithmetic per update.
        row["official_update_gflop_per_s"] = row["update_gflop"] / official["update"]
    if anchor is not None and row["preset"] in ANCHOR_SIZES:
        ref = anchor.get(ANCHOR_SIZES[row["preset"]][0])
        if ref is not None:
            row["anchor"] = {"train_step_s": ref["train_step"]["s_median"],
                             "parameters": ref["parameters"]["total_trainable"]}  # fmt: skip
            row["ratio_anchor_over_ours"] = ref["train_step"]["s_median"] / row["update_s_median"]


def device_name(device: torch.device) -> str:
    """The GPU's name, or this CPU's model name (what the figures were measured on)."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return cpu_info().get("model name", "cpu")


def _names(text: str) -> list[str]:
    return [] if text in ("", "none") else text.split(",")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--models",
        default=None,
        help="comma-separated (default: every model that has all of --presets, "
        "so the TD-MPC2 anchor's '--presets 1M,paper' times TD-MPC2 only)",
    )
    parser.add_argument("--presets", default=None,
                        help=f"comma-separated model presets ('none': only --sizes); default "
                             f"per model {DEFAULT_PRESETS}")  # fmt: skip
    parser.add_argument("--sizes", default="", help=f"DreamerV3 anchor sizes: {list(ANCHOR_SIZES)}")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"of {list(VARIANTS)}")
    parser.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="replay windows per update (default: the preset's / size's)",
    )
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument(
        "--modes", default="auto", help=f"of {list(MODES)} (default: what a run does by default)"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="auto",
                        help="auto (CUDA when available), cpu, cuda or cuda:N")  # fmt: skip
    parser.add_argument("--act-batches", default="",
                        help="also time one act on each of these numbers of observations at "
                             "once, e.g. 1,2,4,8 (several envs acting together)")  # fmt: skip
    parser.add_argument(
        "--anchor-json", default=None, help="output of ../shared/tools/anchors/run_dreamerv3.sh"
    )
    args = parser.parse_args()
    args.presets = None if args.presets is None else _names(args.presets)
    if args.models is None:
        args.models = [m for m in MODELS if args.presets is None or args.presets == ["none"]
                       or all(p in config_class(m).PRESETS for p in args.presets)]  # fmt: skip
    else:
        args.models = _names(args.models)
    args.sizes = _names(args.sizes)
    args.variants = _names(args.variants)
    args.modes = _names(args.modes)
    for what, names, valid in (("model", args.models, MODELS), ("size", args.sizes, ANCHOR_SIZES),
                               ("variant", args.variants, VARIANTS),
                               ("mode", args.modes, MODES)):  # fmt: skip
        bad = [
            n for n in names if n not in valid and not (what == "mode" and n.startswith("compile:"))
        ]
        if bad:
            parser.error(f"unknown {what} {bad}; valid: {list(valid)} or compile:PATH+PATH")
    for mode in args.modes:  # each timed model must have the paths a compile: mode names
        for m in args.models + (["dreamerv3"] if args.sizes else []):
            unknown = sorted(set(_compiled_paths_of(mode) or ()) - set(model_class(m).hot_paths))
            if unknown:
                parser.error(f"{mode}: {unknown} are not hot paths of {m} "
                             f"({', '.join(model_class(m).hot_paths)})")  # fmt: skip
    try:
        device = resolve_device(args.device)
    except ConfigError as e:
        parser.error(str(e))
    if device.type != "cuda" and any(m in GRAPH_MODES for m in args.modes):
        parser.error(f"modes {list(GRAPH_MODES)} replay CUDA graphs: they need --device cuda")
    anchor = None
    if args.anchor_json:
        anchor = {r["config"]: r for r in json.loads(Path(args.anchor_json).read_text())["results"]}
    torch.set_num_threads(args.threads)
    peak = {"off": matmul_peak_gflop_per_s(device)}
    if any(MODES.get(m, ("on", "off"))[1] == "bf16" for m in args.modes):
        peak["bf16"] = matmul_peak_gflop_per_s(device, torch.bfloat16)
    results = []
    for spec in rows_to_time(args):
        cfg = spec.pop("cfg")
        for mode in args.modes:
            row = {**spec, "batch": [cfg.batch_size, cfg.seq_len]}
            if spec["model"] == "dreamerv3":
                row.update(imag_last=cfg.imag_last, horizon=cfg.horizon)
            row.update(time_model(cfg, spec["preset"], spec["frozen_encoder"],
                                  spec["latents_cached"], args.repeats,
                                  args.warmup + (mode != "eager") + 2 * (mode in GRAPH_MODES),
                                  mode, [int(n) for n in _names(args.act_batches)],
                                  device))  # fmt: skip
            attach_references(row, anchor, device)
            roof = max(peak[row["autocast"]].values())
            for name in ("update", "act"):
                row[f"{name}_fraction_of_matmul_peak"] = row[f"{name}_gflop_per_s"] / roof
            results.append(row)
    print(json.dumps({
        "batch_size": args.batch_size, "threads": args.threads, "repeats": args.repeats,
        "warmup": args.warmup, "image_size": args.image_size, "cpu_count": os.cpu_count(),
        "loadavg": Path("/proc/loadavg").read_text().split()[:3], "torch": torch.__version__,
        "device": str(device), "device_name": device_name(device),
        "matmul_peak_gflop_per_s": peak["off"],
        **({"matmul_peak_bf16_gflop_per_s": peak["bf16"]} if "bf16" in peak else {}),
        "results": results,
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
