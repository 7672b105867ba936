"""`--train.compile`: a model's hot paths compiled compute what the eager methods compute.

For every registered model at its smoke size: the same seed gives the same loss, the same
parameters after an update (loss, backward, optimiser step, `head_update`) and the same
actions, compiled or eager, within floating-point tolerance (Inductor reassociates sums).
"""

from __future__ import annotations

import json
import types
import uuid

import numpy as np
import pytest
import torch

from ccfit.models import make_model
from ccfit.models.registry import config_class, model_class
from ccfit.train.compiled import compile_choice, compile_hot_paths, compiled_paths
from ccfit.train.inductor_cache import pin_inductor_threads, pin_inductor_vector_width

try:
    from replay_data import random_buffer
    from shipped import shipped_models
except ImportError:  # tests/ imported as a package
    from tests.replay_data import random_buffer
    from tests.shipped import shipped_models


SHORT_UNROLL = {
    "dreamerv3": dict(seq_len=4, horizon=2),
    "pwm": dict(seq_len=3, horizon=2),
    "tdmpc2": dict(seq_len=2, horizon=1),
}
"""Fewer unrolled steps than the smoke preset's: Dynamo unrolls the model's window and its
imagination or plan, and with a cold Inductor cache (CI) code generation per step dominates.
The compiled-equals-eager test below, cold, one process, 2-core EPYC: DreamerV3 208 -> 153 s,
PWM 190 -> 154 s, TD-MPC2 162 -> 110 s."""

FAST = {"tdmpc2"}
"""Models whose hot paths `make test` compiles through 'aot_eager' (Dynamo's capture and
AOTAutograd's forward and backward graphs, run eagerly: ~20 s per model), which is what capture
alone can break, and whose Inductor compile (the backend runs use; minutes with a cold cache, as
on CI) runs after it (`integration`). TD-MPC2's covers the layers PWM shares and Inductor's
random numbers. The other models' capture is `integration` too; their Inductor code generation
costs minutes per model with a cold cache (above), so it runs under `make test-slow`."""


def _backends(fast_capture: set[str], later_inductor: set[str]) -> list:
    """(model, backend) for every model and both backends: 'aot_eager' in `make test` for the
    models of `fast_capture`, else `integration`; 'inductor' `integration` for the models of
    `later_inductor`, else slow."""
    params = []
    for name in shipped_models():
        capture = () if name in fast_capture else (pytest.mark.integration,)
        inductor = pytest.mark.integration if name in later_inductor else pytest.mark.slow
        for backend, marks in (("aot_eager", capture), ("inductor", (inductor,))):
            params.append(pytest.param(name, backend, id=f"{name}-{backend}", marks=marks))
    return params


def _run(name: str, setting: str, device: str = "cpu", backend: str = "inductor",
         **overrides) -> dict:  # fmt: skip
    """Two updates and two acts, the second warm-started from the first's state (setting
    "graphs" replays CUDA graphs: what a call keeps from the last one must survive)."""
    overrides = {**SHORT_UNROLL.get(name, {}), **overrides}
    cfg = config_class(name).preset("smoke", **overrides)
    if hasattr(cfg, "num_elites"):
        # Every sample an elite: the plan is then a continuous function of the values, not a
        # top-k choice that float reassociation can flip.
        cfg = config_class(name).preset("smoke", num_elites=cfg.num_samples, **overrides)
    torch.manual_seed(0)
    model = make_model(cfg, device)
    model.begin_task(0, 100)
    heads = model.new_heads()
    assert compile_hot_paths(model, setting, backend=backend) == compiled_paths(
        type(model), setting, torch.device(device)
    )
    opt, head_opts = model.world_model_optimizer(heads), model.head_optimizers(heads)
    batch = random_buffer(cfg, seed=1, steps=(10, 20)).sample(cfg.batch_size, cfg.seq_len)
    batch = batch.to(device)
    torch.manual_seed(1)
    losses = []
    for _ in range(2):
        out = model.loss(batch, heads)
        losses.append(float(out.total.detach()))
        opt.zero_grad(set_to_none=True)
        out.total.backward()
        opt.step()
        model.head_update(batch, heads, out, head_opts)
    obs = {k: v[0, :3] for k, v in batch.obs.items()}
    torch.manual_seed(2)
    with torch.no_grad():
        first, state = model.act(obs, heads, model.initial_state(heads, 3), eval_mode=True)
        second, _ = model.act(obs, heads, state, eval_mode=True)
    action = np.concatenate([first, second])
    params = {k: v.detach().cpu().clone() for k, v in [*model.state_dict().items(),
                                                       *heads.state_dict().items()]}  # fmt: skip
    return {"losses": losses, "action": action, "params": params}


def _assert_same(compiled: dict, eager: dict) -> None:
    assert compiled["losses"] == pytest.approx(eager["losses"], rel=1e-4, abs=1e-5)
    np.testing.assert_allclose(compiled["action"], eager["action"], rtol=1e-3, atol=1e-4)
    for k, v in eager["params"].items():
        torch.testing.assert_close(compiled["params"][k], v, rtol=1e-3, atol=1e-4, msg=k)


@pytest.mark.parametrize("name, backend", _backends(FAST, FAST))
def test_compiled_hot_paths_compute_what_the_eager_ones_do(name, backend, device="cpu",
                                                           setting="on"):  # fmt: skip
    if not model_class(name).hot_paths:
        pytest.skip(f"{name} declares no hot path")
    _assert_same(_run(name, setting, device, backend), _run(name, "off", device))


# The dynamic-shape variants cost Inductor minutes more with a cold cache (DreamerV3 353 s and
# PWM 183 s at the smoke preset's unroll, 164 s and 138 s at SHORT_UNROLL's): every model's run
# under `make test-slow`; TD-MPC2's capture (the shared quantile path) with 'aot_eager' after
# `make test`.
@pytest.mark.parametrize("name, backend", _backends(set(), set()))
def test_one_process_compiles_models_of_two_sizes(name, backend):
    # Compiled code is shared by every instance of a class, so a second batch size makes
    # Dynamo trace the hot paths again with dynamic shapes: torch.quantile could not be
    # traced then, and DreamerV3's actor step (retain_graph) met a backward that had donated
    # its buffers. A notebook that trains two presets in turn did exactly this.
    if not model_class(name).hot_paths:
        pytest.skip(f"{name} declares no hot path")
    size = config_class(name).preset("smoke").batch_size
    for batch_size in (size, size + 2):
        _assert_same(_run(name, "on", backend=backend, batch_size=batch_size),
                     _run(name, "off", batch_size=batch_size))  # fmt: skip


def test_a_kernel_compiled_for_one_thread_count_is_not_served_to_another():
    # torch 2.11 leaves the thread count its CPU kernels are written for out of its on-disk
    # cache key: unpinned, the 1-thread compile below loads the 2-thread kernels (0, 1, 1)
    import torch._inductor.config
    from torch._dynamo.utils import counters

    scale = 1.0 + uuid.uuid4().int % 10**6 / 10**7  # a graph no cache holds yet
    threads, pinned = torch.get_num_threads(), torch._inductor.config.cpp.threads
    hits = []
    try:
        for count in (2, 1, 2):
            torch._dynamo.reset()
            torch.set_num_threads(count)
            assert pin_inductor_threads() == count
            before = counters["inductor"]["fxgraph_cache_hit"]
            torch.compile(lambda x: (x.sin() * scale).sum(0))(torch.randn(256, 256))
            hits.append(counters["inductor"]["fxgraph_cache_hit"] - before)
    finally:
        torch.set_num_threads(threads)
        torch._inductor.config.cpp.threads = pinned
        torch._dynamo.reset()
    assert hits == [0, 0, 1]  # the cache still serves the same thread count


def test_a_kernel_compiled_for_one_vector_width_is_not_served_to_another(monkeypatch):
    # torch 2.11 leaves the vector instruction set its CPU kernels are written for out of its
    # on-disk cache key: unpinned, on an AVX-512 machine the compile after the AVX2 one loads
    # the AVX2 graph and builds its kernels 16 floats wide (heap corruption, see
    # `pin_inductor_vector_width`). Where AVX2 is this CPU's widest, both are one width: a hit.
    import torch._inductor.config
    from torch._dynamo.utils import counters
    from torch._inductor import cpu_vec_isa

    scale = 1.0 + uuid.uuid4().int % 10**6 / 10**7  # a graph no cache holds yet
    widest = max((isa.bit_width() for isa in cpu_vec_isa.valid_vec_isa_list()), default=0)
    if widest < 256:
        pytest.skip("no AVX2 on this CPU")
    hits, widths = [], []
    with torch._inductor.config.patch({"cpp.simdlen": None}):
        try:
            for capability in ("avx2", None):
                if capability:
                    monkeypatch.setenv("ATEN_CPU_CAPABILITY", capability)
                else:
                    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
                torch._dynamo.reset()
                widths.append(pin_inductor_vector_width())
                assert torch._inductor.config.cpp.simdlen == widths[-1]  # in the key
                before = counters["inductor"]["fxgraph_cache_hit"]
                torch.compile(lambda x: (x.sin() * scale).sum(0))(torch.randn(256, 256))
                hits.append(counters["inductor"]["fxgraph_cache_hit"] - before)
        finally:
            torch._dynamo.reset()
    assert widths == [256, widest]
    assert hits == [0, int(widest == 256)]


def test_auto_compiles_only_what_was_measured_to_pay():
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    for name in shipped_models():
        cls = model_class(name)
        assert compiled_paths(cls, "off", cpu) == []
        assert compiled_paths(cls, "on", cpu) == list(cls.hot_paths)
        assert set(compiled_paths(cls, "auto", cpu)) <= set(cls.hot_paths)
        assert compiled_paths(cls, "auto", cuda) == list(cls.compile_pays.get("cuda", ()))


def test_auto_compiles_only_in_a_run_long_enough_for_compiling_to_pay():
    cpu = torch.device("cpu")
    for name in shipped_models():
        cls = model_class(name)
        assert set(cls.compile_pays_from) <= set(cls.compile_pays), name
        least = cls.compile_pays_from.get("cpu", 0)
        paying = list(cls.compile_pays.get("cpu", ()))
        if least:
            paths, why = compile_choice(cls, "auto", cpu, least - 1)
            assert paths == [] and f"{least - 1} steps per task, fewer than the {least}" in why
        paths, why = compile_choice(cls, "auto", cpu, least)
        assert paths == paying and why.startswith("auto: ")
        assert compile_choice(cls, "on", cpu, 1)[0] == list(cls.hot_paths)  # asked for: done
        assert compile_choice(cls, "off", cpu, 10**9) == ([], "train.compile=off: eager")


def test_a_run_records_what_auto_chose_and_why_and_resumes_with_it(tmp_path):
    from ccfit.config import TaskRunConfig
    from ccfit.config_base import identity
    from ccfit.config_parse import resolve
    from ccfit.train.run import CONFIG, compile_as_begun, resolved_config

    least = model_class("tdmpc2").compile_pays_from["cpu"]

    def resolved(steps):
        cfg = resolve(TaskRunConfig, {"task": "reach-xy", "preset": "cpu", "obs": "state",
                                      "model": {"type": "tdmpc2"},
                                      "train": {"steps": steps, "device": "cpu"}})  # fmt: skip
        return resolved_config(cfg, None)

    short, long = resolved(least // 2), resolved(least)
    assert short["resolved_compile"] == [] and "fewer than" in short["resolved_compile_reason"]
    assert long["resolved_compile"] == list(model_class("tdmpc2").compile_pays["cpu"])
    assert "resolved_compile_reason" not in identity(long)  # a note for the reader
    (tmp_path / CONFIG).write_text(json.dumps(short))
    extended = compile_as_begun(tmp_path, long)  # `ccfit train --train.steps` raised
    assert extended["resolved_compile"] == [] and extended["train"]["steps"] == least
    assert compile_as_begun(tmp_path / "new", long) == long


def test_autocast_auto_is_bf16_where_the_hardware_multiplies_in_bf16():
    from ccfit.config import TrainConfig
    from ccfit.settings import cpu_flags, native_bf16, resolve_autocast

    cpu = torch.device("cpu")
    assert native_bf16(cpu, frozenset({"avx2", "avx512f", "avx512_bf16"}))
    assert native_bf16(cpu, frozenset({"amx_bf16", "amx_tile"}))
    assert not native_bf16(cpu, frozenset({"avx2", "avx512f", "avx512bw"}))  # emulated only
    here = "bf16" if cpu_flags() & {"avx512_bf16", "amx_bf16"} else "off"
    assert resolve_autocast("auto", cpu) == here
    assert resolve_autocast("bf16", cpu) == "bf16" and resolve_autocast("off", cpu) == "off"
    # The paper's scale is matmul-bound, where bf16 pays; the small presets are not.
    assert TrainConfig.preset("paper").autocast == "auto"
    assert TrainConfig.preset("cpu").autocast == TrainConfig.preset("smoke").autocast == "off"


@pytest.mark.slow  # sixteen plan variants: 413 s with a cold Inductor cache, as on CI
def test_a_compiled_plan_stays_compiled_over_the_variants_a_run_meets(caplog):
    # Evaluation batches shrink as episodes end, plans start warm or cold, in eval or train
    # mode, with the heads in either mode: Dynamo's default limit (8) sent the plan back to
    # eager partway through a curriculum.
    cls = config_class("tdmpc2")
    model = make_model(cls(**cls.PRESETS["smoke"]), "cpu")
    model.begin_task(0, 1000)
    heads = model.new_heads()
    assert compile_hot_paths(model, "on")
    torch._dynamo.reset()
    with caplog.at_level("WARNING", logger="torch._dynamo"), torch.no_grad():
        for training in (True, False):
            heads.train(training)
            for eval_mode in (False, True):
                for n in (5, 1):
                    mean = model.plan(torch.randn(n, model.cfg.latent_dim), heads, None,
                                      eval_mode=eval_mode)[1]  # fmt: skip
                    model.plan(torch.randn(n, model.cfg.latent_dim), heads, mean,
                               eval_mode=eval_mode)  # fmt: skip
    assert not [r for r in caplog.records if "recompile_limit" in r.getMessage()]


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=() if n in FAST else pytest.mark.integration)
    for n in shipped_models() if "plan" in model_class(n).hot_paths
])  # fmt: skip
def test_acting_compiles_one_plan_per_mode_and_batch_kind(name):
    # What a run meets: training acts on one episode, from a cold start and then warm;
    # evaluation acts on a batch that shrinks as its episodes end (down to one), its acting
    # state selected per episode. A cold start is a warm start from zero means, the batch
    # size is dynamic above one and the plan means come back in row-major strides, so this
    # compiles three plans (train at 1, eval above 1, eval at 1), not one per start, size
    # and stride pattern (5 before).
    from torch._dynamo.testing import CompileCounter

    from ccfit.models.base import select_state

    cfg = config_class(name).preset("smoke")
    model = make_model(cfg, "cpu")
    model.begin_task(0, 1000)
    heads = model.new_heads()
    counter = CompileCounter()
    torch._dynamo.reset()
    model.plan = types.MethodType(torch.compile(type(model).plan, backend=counter), model)
    rows = random_buffer(cfg, seed=1, steps=(10, 20)).sample(8, cfg.seq_len).obs
    with torch.no_grad():
        state = None
        for _ in range(3):
            obs = {k: v[0, :1] for k, v in rows.items()}
            state = model.act(obs, heads, state, eval_mode=False)[1]
        state = None
        for n in (5, 5, 4, 3, 1):
            if state is not None:
                state = select_state(state, torch.arange(n))
            obs = {k: v[0, :n] for k, v in rows.items()}
            state = model.act(obs, heads, state, eval_mode=True)[1]
    assert counter.frame_count == 3


def test_a_device_check_stays_inside_the_compiled_graph():
    # Reading the check's value back broke PWM's compiled loss in three graphs on a CPU.
    from ccfit.models.base import check_on_device

    def checked(x):
        check_on_device((x >= 0).all(), "negative input")
        return x * 2

    compiled = torch.compile(checked, fullgraph=True)  # a graph break fails here
    assert torch.equal(compiled(torch.ones(3)), torch.full((3,), 2.0))
    with pytest.raises(RuntimeError, match="negative input"):
        compiled(-torch.ones(3))
    with pytest.raises(ValueError, match="negative input"):  # eager on a CPU: the input's fault
        checked(-torch.ones(3))


def test_one_compiled_pwm_plan_and_loss_serve_every_task():
    # PWM routes by the heads' task; read as a Python int it made Dynamo compile the plan and
    # the loss again for every task of a curriculum (24 plans in a 4-task one; a fifth task
    # passed the recompile limit, after which the plan ran eager).
    from torch._dynamo.testing import CompileCounter

    cfg = config_class("pwm").preset("smoke", max_tasks=4)
    model = make_model(cfg, "cpu")
    heads = []
    for task in range(3):
        model.begin_task(task, 1000)
        heads.append(model.new_heads())
    plans, losses = CompileCounter(), CompileCounter()
    torch._dynamo.reset()
    model.plan = types.MethodType(torch.compile(type(model).plan, backend=plans), model)
    model.loss = types.MethodType(torch.compile(type(model).loss, backend=losses), model)
    for task, h in enumerate(heads):
        batch = random_buffer(cfg, seed=1, steps=(10, 20), task=task).sample(4, cfg.seq_len)
        model.loss(batch, h)
        with torch.no_grad():
            model.act({k: v[0, :1] for k, v in batch.obs.items()}, h, None, eval_mode=True)
    assert (plans.frame_count, losses.frame_count) == (1, 1)


def test_cuda_graphs_are_refused_where_there_is_no_cuda(tmp_path, capsys):
    # One line and exit 2 before anything is made: CUDA graphs need a CUDA device.
    from ccfit.cli import main

    out = tmp_path / "run"
    code = main(["train", "--task", "reach-xy", "--preset", "smoke", "--seed_dataset", "null",
                 "--train.device=cpu", "--train.compile=graphs", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "train.compile=graphs replays CUDA graphs" in err and "cpu" in err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("name, method", [("tdmpc2", "er"), ("pwm", "experts"),
                                          ("dreamerv3", "er")])  # fmt: skip
def test_graphs_path_runs_a_curriculum_compiled_plainly(name, method, tmp_path, monkeypatch):
    # On a CPU, mode="reduce-overhead" compiles without CUDA graphs, so the loop's graphs path
    # (outputs copied, a step marked per update, ER's stored-heads losses beside the update's
    # own) runs through every hot path's real return types here. What only CUDA shows, a
    # replay overwriting what the loop kept, is test_gpu's.
    import ccfit.settings

    try:
        from short_episodes import smoke_curriculum
    except ImportError:  # tests/ imported as a package
        from tests.short_episodes import smoke_curriculum

    monkeypatch.setattr(ccfit.settings, "check_compile_device", lambda setting, device: None)
    train = {"steps": 100, "seed_steps": 50, "eval_interval": 50, "checkpoint_interval": 50,
             "device": "cpu", "compile": "graphs", "parallel": "off"}  # fmt: skip
    result, saved = smoke_curriculum(tmp_path, name, method, train)
    assert saved["resolved_compile"] == list(model_class(name).hot_paths)
    assert np.isfinite(result["bwt"]) and np.isfinite(result["fwt"])
