"""The benchmark scripts still run and report what they say they report (their figures are
quoted in docs/performance.md; a script that rotted would leave those figures unreproducible)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def update_rate(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "update_rate.py"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)  # fmt: skip


@pytest.mark.integration
def test_update_rate_times_every_model_and_mode_on_the_cpu():
    done = update_rate("--models", "tdmpc2,dreamerv3", "--presets", "smoke", "--variants",
                       "state", "--modes", "eager,bf16", "--repeats", "1", "--warmup", "0",
                       "--threads", "1", "--device", "cpu")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["device"] == "cpu" and report["device_name"]
    assert set(report["matmul_peak_bf16_gflop_per_s"]) == set(report["matmul_peak_gflop_per_s"])
    rows = {(r["model"], r["mode"]): r for r in report["results"]}
    assert set(rows) == {(m, x) for m in ("tdmpc2", "dreamerv3") for x in ("eager", "bf16")}
    for (_, mode), row in rows.items():
        assert row["autocast"] == ("bf16" if mode == "bf16" else "off")
        assert row["update_s_median"] > 0 and row["act_s_median"] > 0
        assert row["update_gflop"] > 0
        # each row against the matmul rate of its own precision
        peak = report["matmul_peak_bf16_gflop_per_s" if mode == "bf16"
                      else "matmul_peak_gflop_per_s"]  # fmt: skip
        expected = row["update_gflop_per_s"] / max(peak.values())
        assert row["update_fraction_of_matmul_peak"] == pytest.approx(expected)


def test_update_rate_refuses_cuda_graphs_off_cuda():
    done = update_rate("--presets", "smoke", "--modes", "graphs", "--device", "cpu", timeout=60)
    assert done.returncode == 2
    assert "need --device cuda" in done.stderr.strip().splitlines()[-1]


def test_official_cpu_references_go_on_cpu_rows_only():
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location("update_rate", ROOT / "bench" / "update_rate.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)

    def row() -> dict:
        return {"model": "tdmpc2", "preset": "1M", "obs": "state", "frozen_encoder": False,
                "update_s_median": 0.05, "act_s_median": 0.1, "update_gflop": 1.0}  # fmt: skip

    on_cpu, on_gpu = row(), row()
    bench.attach_references(on_cpu, None, torch.device("cpu"))
    bench.attach_references(on_gpu, None, torch.device("cuda"))
    assert on_cpu["speedup_vs_official"]["update"] == pytest.approx(0.1145 / 0.05)
    assert "official_s" not in on_gpu and "speedup_vs_official" not in on_gpu


@pytest.mark.slow  # compiles TD-MPC2's update in four processes (~2 min)
def test_inductor_threads_times_jobs_with_and_without_the_pin():
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "inductor_threads.py"), "--jobs",
                           "1", "--rounds", "1", "--updates", "3"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert [len(v) for v in report["update_ms"].values()] == [1, 1]
    assert report["ratio_default_over_pinned"] > 0


@pytest.mark.integration
def test_eval_workers_times_evaluations_here_and_in_workers():
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_workers.py"), "--preset",
                           "smoke", "--episodes", "2", "--workers", "0,1", "--repeats", "1",
                           "--compile", "off", "--episode-steps", "20"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert 2 <= report["env_steps_per_evaluation"] <= 40 and report["compiled"] == []
    assert [len(v) for v in report["evaluation_s"].values()] == [1, 1]
    assert report["ratio_here_over_workers"]["1"] > 0


BAD_EVAL_WORKERS = [(["--workers", "0,two"], "counts >= 0, got '0,two'"),
                    (["--task", "reach-w"], "unknown task 'reach-w'"),
                    (["--model", "dreamer"], "unknown model 'dreamer'")]  # fmt: skip


@pytest.mark.parametrize("args, message", BAD_EVAL_WORKERS)
def test_eval_workers_bad_input_is_one_line_and_exit_2(args, message):
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_workers.py"), *args],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)  # fmt: skip
    assert done.returncode == 2 and message in done.stderr.strip().splitlines()[-1]


@pytest.mark.integration  # two short jobs in fresh interpreters, one with its cache filled
def test_startup_times_the_first_steps_and_the_job_and_records_what_auto_chose(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "startup.py"), "--variants",
                           "auto", "--caches", "warm", "--rounds", "1", "--steps", "120",
                           "--seed-steps", "60", "--eval-interval", "60", "--eval-episodes",
                           "1", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=600, cwd=ROOT)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    (run,) = report["runs"]["warm"]["auto"]
    assert 0 < run["first_env_step_s"] < run["first_update_s"] < run["wall_s"]
    assert run["compiled"] == [] and "120 steps per task, fewer than" in run["compile_reason"]
    assert run["end_eval_episodes"] is None  # the task's end plays the job's 1, not the cpu 40
    assert report["medians"]["warm"]["auto"]["wall_s"] == run["wall_s"]
    assert "--train.steps=120" in report["job"]


def test_env_throughput_breaks_a_render_down_by_size_and_the_arms_meshes():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "env_throughput", ROOT / "bench" / "env_throughput.py"
    )
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    report = bench.render_ms("reach-xy", repeats=1)
    cameras = {"topview", "frontview", "gripperPOV"}
    for key in ("16px", "64px", "256px", "64px_arm_meshes_hidden"):
        assert set(report[key]) == cameras and all(v > 0 for v in report[key].values())
    assert report["mesh_faces"] > 10_000  # the Sawyer's meshes are in the scene
