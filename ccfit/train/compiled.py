"""How a model's hot paths run: `--train.compile` (`WorldModel.hot_paths` through
`torch.compile`) and `--train.autocast` (`autocast`).

    off     eager everywhere (the reference)
    on      every hot path compiled
    graphs  every hot path compiled and replayed as CUDA graphs (`mode="reduce-overhead"`, as
            the official TD-MPC2's `compile=true`; CUDA only), its outputs copied out of the
            graphs' memory (`outputs_copied`)
    auto    the hot paths measured to pay on this device type (`WorldModel.compile_pays`),
            in a run long enough for compiling them to pay (`WorldModel.compile_pays_from`);
            nothing on a device type never measured or in a shorter run

The compiled functions are the model's own methods, traced by Dynamo and fused by Inductor;
nothing is rewritten by hand. Random numbers inside compiled code come from torch's eager
generators (`fallback_random`), so compiled and eager draw the same numbers for a seed and
compute the same losses up to floating-point reassociation (tested).
"""

from __future__ import annotations

import dataclasses
import functools
import types

import torch

from ccfit.models.base import WorldModel
from ccfit.settings import autocast_context, resolve_autocast
from ccfit.train.inductor_cache import prepare_inductor_cache


def compiled_paths(model_class: type[WorldModel], setting: str, device: torch.device,
                   steps: int | None = None) -> list[str]:  # fmt: skip
    """The methods `setting` compiles for `model_class` on `device` in a run of `steps` steps
    per task (None: whatever its length); what a run records (`compile_choice`)."""
    return compile_choice(model_class, setting, device, steps)[0]


def compile_choice(model_class: type[WorldModel], setting: str, device: torch.device,
                   steps: int | None = None) -> tuple[list[str], str]:  # fmt: skip
    """What `setting` compiles for `model_class` on `device` in a run of `steps` steps per
    task, and why, in a line (config.json records both). `auto` decides from the device type
    and the run's length: compiling costs seconds (from Inductor's cache) to minutes (without)
    per process, which only a long enough run wins back (`WorldModel.compile_pays_from`).
    A function of the config alone, so a run resumes with what it began with."""
    name = model_class.__name__
    if setting == "off":
        return [], "train.compile=off: eager"
    if setting in ("on", "graphs"):
        return list(model_class.hot_paths), f"train.compile={setting}: every hot path"
    kind = torch.device(device).type
    paths = list(model_class.compile_pays.get(kind, ()))
    if not paths:
        return [], f"auto: no hot path of {name} was measured faster compiled on {kind}"
    least = model_class.compile_pays_from.get(kind, 0)
    if steps is not None and steps < least:
        return [], (f"auto: {steps} steps per task, fewer than the {least} from which "
                    f"compiling {name}'s {', '.join(paths)} measured faster than eager on "
                    f"{kind}, compiling included")  # fmt: skip
    size = f"{steps} steps per task, at least {least}" if steps is not None else "any length"
    return paths, f"auto: {size}: {name}'s {', '.join(paths)} measured faster compiled on {kind}"


def compile_hot_paths(model: WorldModel, setting: str, paths: list[str] | None = None,
                      backend: str = "inductor") -> list[str]:  # fmt: skip
    """Replace `model`'s hot methods by compiled ones (on the instance); returns their names.
    `paths`: these methods instead of those `setting` names (`bench/update_rate.py` times
    them one by one to decide `compile_pays`). `backend`: Dynamo's backend for every setting
    but 'graphs' (Inductor's CUDA graphs); 'aot_eager' captures the same forward and backward
    graphs and runs them eagerly, without Inductor's code generation (minutes per model with a
    cold cache), which is how the fast tests check what capture alone can break."""
    names = compiled_paths(type(model), setting, model.device) if paths is None else paths
    graphs = setting == "graphs"
    if names:
        import torch._dynamo.config
        import torch._functorch.config
        import torch._inductor.config

        torch._inductor.config.fallback_random = True
        prepare_inductor_cache()
        # DreamerV3's actor step differentiates with retain_graph (its critic pass serves the
        # critic's loss too), which a compiled backward that donates its saved buffers
        # refuses; Inductor compiles such a backward when it meets a second model size.
        torch._functorch.config.donated_buffer = False
        # A plan specialises on batch 1 or more (an evaluation batch shrinks as its episodes
        # end), a warm start or none, eval_mode and the heads' train flag: 16 variants, twice
        # Dynamo's default limit, past which it silently runs eager. A run meets 3 of them
        # (test_compile); PWM's plan meets them once per number of active expert groups.
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 32)
    for name in names:
        # Compile the class's function, bound to the model: compiling the bound method would
        # wrap every method in one shared code object, so all of them would share one limit.
        how = {"mode": "reduce-overhead"} if graphs else {"backend": backend}
        fn = torch.compile(getattr(type(model), name), **how)
        setattr(model, name, types.MethodType(outputs_copied(fn) if graphs else fn, model))
    return names


def outputs_copied(fn):
    """`fn` (compiled as CUDA graphs) handing back copies of what it returns. A replay writes
    its outputs into memory the graphs share, and CUDA-graph trees reuse that memory once a
    new generation starts: whatever a caller kept (logs, a plan's warm start, the latents the
    heads' update reads) would be overwritten. Copies may be kept; gradients flow through
    them. A step is marked where an update begins (`UpdateStep`), not per call: a forward
    whose backward is still pending (ER's stored-heads loss beside the update's own) must
    stay in its generation."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        return copied(fn(*args, **kwargs))

    return call


def copied(value):
    """`value` with each tensor in it (through dicts, lists, tuples and dataclasses) cloned;
    gradients still flow through the clones."""
    if isinstance(value, torch.Tensor):
        return value.clone()
    if isinstance(value, dict):
        return {k: copied(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        items = [copied(v) for v in value]
        return type(value)(*items) if hasattr(value, "_fields") else type(value)(items)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = [f.name for f in dataclasses.fields(value) if f.init]
        return dataclasses.replace(value, **{k: copied(getattr(value, k)) for k in fields})
    return value


def autocast(device: torch.device, setting: str):
    """The autocast context of `--train.autocast` on `device` (a no-op context for 'off'),
    resolved on each call: for scripts and benchmarks. A run resolves its precision once
    (`ccfit.settings.Execution.autocast_context`)."""
    device = torch.device(device)
    return autocast_context(device, resolve_autocast(setting, device))
