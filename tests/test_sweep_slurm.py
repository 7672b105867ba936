"""`ccfit sweep --launcher slurm` on a real SLURM (marked `slurm`: skipped unless sbatch and
sacct answer).

The toy world model of test_seam.py runs in the jobs (`--plugins test_seam`, tests/ on the
jobs' PYTHONPATH). The preemption test needs the one-node cluster of .ci/slurm-up.sh: a `low`
partition whose jobs a `high` partition's job preempts (requeue).
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from ccfit.cli import main
from ccfit.sweep.grid import load_sweep
from ccfit.sweep.launch import wait_report
from ccfit.sweep.status import sweep_status

try:
    from slurm_helpers import bin_with, partitions, sacct, when
except ImportError:  # tests/ imported as a package
    from tests.slurm_helpers import bin_with, partitions, sacct, when

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.slurm


@pytest.fixture(autouse=True)
def job_env(monkeypatch):
    """sbatch exports the environment: the jobs import this checkout and the toy model."""
    monkeypatch.setenv("PYTHONPATH", f"{ROOT}:{ROOT / 'tests'}")
    monkeypatch.setenv("MUJOCO_GL", "egl")


def toy_args(root: Path, methods: str, *run: str) -> list[str]:
    return ["sweep", "--suites", "Reach", "--models", "toy", "--methods", methods, "--seeds",
            "0", "--preset", "smoke", "--plugins", "test_seam", "--out", str(root),
            "--launcher", "slurm", "--time", "30", "--seed_dataset", "null", *run]  # fmt: skip


def test_smoke_sweep_through_slurm(tmp_path, capsys):
    root = tmp_path / "runs"
    args = toy_args(root, "ft,er", "--train.steps=100", "--train.seed_steps=50",
                    "--train.eval_interval=100", "--wait")  # fmt: skip
    assert main(args) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert f"logs in {root / 'slurm'}" in out
    sweep, record = load_sweep(root)
    [entry] = record["submissions"]
    jobs = entry["jobs"]
    assert sorted(jobs) == sorted(["report", f"scratch:{sweep.runs[0].scratch_key}",
                                   *(f"run:{r.name}" for r in sweep.runs)])  # fmt: skip
    # one reference, trained before either run started (afterany dependency)
    rows = sacct(list(jobs.values()))
    scratch_end = when(rows[jobs[f"scratch:{sweep.runs[0].scratch_key}"]]["end"])
    for run in sweep.runs:
        assert scratch_end <= when(rows[jobs[f"run:{run.name}"]]["start"])
        result = json.loads((sweep.run_dir(run) / "metrics.json").read_text())
        assert result["method"] == run.config["method"]["type"] and result["fwt"] is not None
    status = json.loads((root / "report" / "status.json").read_text())
    assert sorted(status["done"]) == sorted(r.name for r in sweep.runs) and not status["missing"]
    assert {s["state"] for s in sweep_status(root).values()} == {"done"}

    assert main(args) == 0
    assert "nothing to submit" in capsys.readouterr().out
    assert len(load_sweep(root)[1]["submissions"]) == 1


def _log(root: Path, job: str) -> str:
    return (root / "slurm" / job / f"{job}_0_log.out").read_text()


@pytest.mark.skipif(not {"low", "high"} <= partitions(), reason="needs low and high partitions")
def test_a_preempted_run_is_requeued_and_ends_as_an_uninterrupted_one(tmp_path, capsys):
    from ccfit.curriculum import Curriculum

    root = tmp_path / "runs"
    train = ["--train.steps=300", "--train.seed_steps=100", "--train.eval_interval=300",
             "--train.checkpoint_interval=100"]  # fmt: skip
    assert main(toy_args(root, "ft", "--partition", "low", *train)) == 0
    sweep, record = load_sweep(root)
    [run] = sweep.runs
    job = record["submissions"][0]["jobs"][f"run:{run.name}"]
    deadline = time.monotonic() + 240
    while not list(sweep.run_dir(run).glob("tasks/*/checkpoint.pt")):
        assert time.monotonic() < deadline, "the run wrote no checkpoint"
        time.sleep(0.5)
    status = sweep_status(root)
    assert status[f"run:{run.name}"] == {"state": "running", "job": job, "detail": "RUNNING"}
    assert status[f"scratch:{run.scratch_key}"]["state"] == "done"
    assert status["report"]["state"] == "pending"
    # all of the node's CPUs in the high partition: the low job must give way
    subprocess.run(["sbatch", "--partition", "high", "--cpus-per-task", "2", "--time", "2",
                    "--job-name", "ccfit-preempt", "--output", "/dev/null", "--wrap", "sleep 3"],
                   check=True, capture_output=True)  # fmt: skip

    # meanwhile the same config uninterrupted, here
    from ccfit.sweep.jobs import config_from_dict

    cfg = config_from_dict(run.config)
    reference = Curriculum(cfg, tmp_path / "ref", tmp_path / "ref-scratch", progress=False).run()

    wait_report(load_sweep(root)[1]["submissions"][0], timeout_s=300)
    log = _log(root, job)
    assert log.count("starting fresh") == 1 and "requeued" in log
    assert "resuming from tasks/" in log or "resuming from curriculum.pt" in log
    states = subprocess.run(["sacct", "-n", "-X", "-D", "-P", "-j", job, "-o", "State"],
                            capture_output=True, text=True).stdout.split()  # fmt: skip
    assert "PREEMPTED" in states or "REQUEUED" in states, states
    result = json.loads((sweep.run_dir(run) / "metrics.json").read_text())
    result.pop("scratch_dir")
    reference = json.loads(json.dumps(reference))
    reference.pop("scratch_dir")
    assert result == reference


def test_no_accounting_is_one_line(tmp_path, capsys, monkeypatch):
    # the real sbatch, sinfo and squeue, but no sacct
    monkeypatch.setenv("PATH", str(bin_with(tmp_path / "bin", "sbatch", "sinfo", "squeue")))
    code = main(toy_args(tmp_path / "runs", "ft"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "sacct not available (sacct is not on PATH)" in err
    assert not (tmp_path / "runs").exists()
