"""On a CUDA device (skipped without one): every model's smoke curriculum (also replayed as
CUDA graphs, and under bf16 autocast), a run killed and resumed under EWC and PackNet (whose
state is saved from the GPU and loaded on the CPU first), compiled hot paths (also as CUDA
graphs) equal to eager ones, and `bench/update_rate.py` on the GPU. `bench/device_check.sh`
runs these on a lent GPU machine. On an H200 (2026-11-27) the 12 tests before the graphs and
bf16 smoke curricula were added passed in 194 s, one worker each."""

from __future__ import annotations

import json
import os
import subprocess
import time

import pytest

from ccfit.models.registry import model_class

try:
    from shipped import shipped_models
    from short_episodes import ccfit_command, smoke_curriculum
    from test_bench import update_rate
    from test_compile import test_compiled_hot_paths_compute_what_the_eager_ones_do as compiled
except ImportError:  # tests/ imported as a package
    from tests.shipped import shipped_models
    from tests.short_episodes import ccfit_command, smoke_curriculum
    from tests.test_bench import update_rate
    from tests.test_compile import (
        test_compiled_hot_paths_compute_what_the_eager_ones_do as compiled,
    )

pytestmark = pytest.mark.gpu
TRAIN = {"steps": 100, "seed_steps": 50, "eval_interval": 50, "checkpoint_interval": 50,
         "device": "cuda"}  # fmt: skip


@pytest.mark.parametrize("compile, autocast", [("auto", "off"), ("graphs", "off"),
                                               ("auto", "bf16")])  # fmt: skip
@pytest.mark.parametrize("name", shipped_models())
def test_smoke_curriculum_on_cuda(name, compile, autocast, tmp_path):
    # graphs: the loop keeps what hot paths return (logs, warm starts, latents) across calls;
    # bf16: what the `paper` preset's autocast=auto resolves to on a GPU
    method = "experts" if "experts" in model_class(name).capabilities else "ewc"
    train = {**TRAIN, "compile": compile, "autocast": autocast}
    result, saved = smoke_curriculum(tmp_path, name, method, train)
    assert saved["resolved_device"].startswith("cuda")
    assert saved["resolved_autocast"] == autocast
    if compile == "graphs":
        assert saved["resolved_compile"] == list(model_class(name).hot_paths)
    assert result["fwt"] is not None and len(result["end_of_task"]) == 4
    # cost.json names the GPU the segment ran on
    import torch

    from ccfit.train.cost import read_cost

    (machine,) = read_cost(tmp_path / "run")["machines"]
    assert machine["gpu"] == torch.cuda.get_device_name()


@pytest.mark.parametrize("method", ["ewc", "packnet"])
def test_killed_cuda_run_resumes_to_the_uninterrupted_result(method, tmp_path):
    def argv(out):
        args = ["run", "--suite", "Grasp", "--preset", "smoke", "--seed_dataset", "null",
                f"--method.type={method}", "--out", str(out), "--scratch-root",
                str(tmp_path / "scratch"), "--quiet"]  # fmt: skip
        return args + [f"--train.{k}={v}" for k, v in TRAIN.items()]

    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    full = subprocess.run(ccfit_command(argv(tmp_path / "full")), env=env, capture_output=True,
                          text=True, timeout=900)  # fmt: skip
    assert full.returncode == 0, full.stderr[-2000:]
    out = tmp_path / "killed"
    ckpt = out / "tasks" / "1-place-cube" / "checkpoint.pt"
    proc = subprocess.Popen(ccfit_command(argv(out)), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None and ckpt.exists()
        proc.kill()
    finally:
        proc.kill()
        proc.communicate()
    done = subprocess.run(ccfit_command(argv(out)), env=env, capture_output=True, text=True,
                          timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / "metrics.jsonl").read_text() == (tmp_path / "full" / "metrics.jsonl").read_text()


@pytest.mark.parametrize("name", shipped_models())
def test_compiled_equals_eager_on_cuda(name):
    compiled(name, "inductor", device="cuda")


@pytest.mark.parametrize("name", shipped_models())
def test_cuda_graphs_equal_eager(name):
    # What `bench/update_rate.py --modes graphs` times must compute the same function.
    compiled(name, "inductor", device="cuda", setting="graphs")


def test_update_rate_bench_on_cuda():
    modes = ("eager", "graphs")  # the CUDA-only path; the others are the CPU test's
    done = update_rate("--presets", "smoke", "--variants", "state", "--modes", ",".join(modes),
                       "--repeats", "2", "--device", "cuda", timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["device"].startswith("cuda") and report["device_name"]
    rows = {(r["model"], r["mode"]): r for r in report["results"]}
    assert set(rows) == {(m, x) for m in shipped_models() for x in modes}
    assert all(r["update_s_median"] > 0 and r["act_s_median"] > 0 for r in rows.values())
