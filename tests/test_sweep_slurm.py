"""`ccfit sweep --launcher slurm` on a real SLURM (marked `slurm`: skipped unless sbatch and
sacct answer).

The toy world model of test_seam.py runs in the jobs (`--plugins test_seam`, tests/ on the
jobs' PYTHONPATH). The preemption test needs the one-node cluster of .ci/slurm-up.sh: a `low`
partition whose jobs a `high` partition's job preempts (requeue).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from ccfit.cli import main
from ccfit.sweep.grid import load_sweep, read_record
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


def _last_submission(root: Path) -> dict:
    """The jobs of the sweep's last submission so far (they are recorded as submitted)."""
    submissions = (read_record(root) or {}).get("submissions") or [{}]
    return submissions[-1].get("jobs", {})


def _log(root: Path, job: str) -> str:
    return (root / "slurm" / job / f"{job}_0_log.out").read_text()


@pytest.mark.integration
@pytest.mark.skipif(not {"low", "high"} <= partitions(), reason="needs low and high partitions")
def test_a_sweep_through_slurm_is_preempted_and_ends_as_an_uninterrupted_run(tmp_path, capsys):
    """One scenario (each job costs seconds of imports): a two-run sweep, its reference trained
    before either run, both runs preempted by a job of the `high` partition and requeued, the
    report job at the end, and an uninterrupted run of the same config giving the same
    metrics; a second submission finds nothing to do."""
    from ccfit.curriculum import Curriculum
    from ccfit.sweep.jobs import config_from_dict

    root = tmp_path / "runs"
    # Each run trains its own first task, to be preempted in it.
    args = toy_args(root, "ft,er", "--partition", "low", "--train.steps=300",
                    "--train.seed_steps=100", "--train.eval_interval=300",
                    "--train.checkpoint_interval=100", "--keep-stages",
                    "--no-share-first-task")  # fmt: skip
    # submitted with --wait: it returns once the report job ended, with the status
    waited = []
    submitter = threading.Thread(target=lambda: waited.append(main([*args, "--wait"])))
    submitter.start()
    deadline = time.monotonic() + 120
    while "report" not in _last_submission(root):  # the report job is submitted last
        assert submitter.is_alive() and time.monotonic() < deadline, "nothing was submitted"
        time.sleep(0.2)
    sweep, record = load_sweep(root)
    [entry] = record["submissions"]
    jobs = entry["jobs"]
    scratch = f"scratch:{sweep.runs[0].scratch_key}"
    assert sorted(jobs) == sorted(["report", scratch, *(f"run:{r.name}" for r in sweep.runs)])
    [run] = [r for r in sweep.runs if r.config["method"]["type"] == "ft"]
    job = jobs[f"run:{run.name}"]
    deadline = time.monotonic() + 240
    while not list(sweep.run_dir(run).glob("tasks/*/checkpoint.pt")):
        assert time.monotonic() < deadline, "the run wrote no checkpoint"
        time.sleep(0.5)
    status = sweep_status(root)
    # The controller's state, then where the run is (it has evaluated: it checkpointed).
    assert status[f"run:{run.name}"] == {
        "state": "running",
        "job": job,
        "detail": status[f"run:{run.name}"]["detail"],
    }
    assert status[f"run:{run.name}"]["detail"].startswith("RUNNING; last evaluated reach-")
    assert status[scratch]["state"] == "done"
    assert status["report"]["state"] == "pending"
    # all of the node's CPUs in the high partition: the low jobs must give way
    subprocess.run(["sbatch", "--partition", "high", "--cpus-per-task", "2", "--time", "2",
                    "--job-name", "ccfit-preempt", "--output", "/dev/null", "--wrap", "sleep 3"],
                   check=True, capture_output=True)  # fmt: skip

    # meanwhile the same config uninterrupted, here
    reference = Curriculum(config_from_dict(run.config), tmp_path / "ref",
                           tmp_path / "ref-scratch", progress=False).run()  # fmt: skip

    submitter.join(timeout=300)
    assert waited == [0]
    out = capsys.readouterr().out
    assert f"logs in {root / 'slurm'}" in out and re.search(r"(?m)^report\s+done", out), out
    log = _log(root, job)
    assert log.count("starting fresh") == 1 and "requeued" in log
    assert "resuming from tasks/" in log or "resuming from curriculum.pt" in log
    states = subprocess.run(["sacct", "-n", "-X", "-D", "-P", "-j", job, "-o", "State"],
                            capture_output=True, text=True).stdout.split()  # fmt: skip
    assert "PREEMPTED" in states or "REQUEUED" in states, states
    result = json.loads((sweep.run_dir(run) / "metrics.json").read_text())
    # --keep-stages reached the job and its requeued continuation: a stage after every task
    stages = sorted(p.name for p in (sweep.run_dir(run) / "stages").iterdir())
    assert stages == [f"after-{k}.pt" for k in range(1, len(result["end_of_task"]) + 1)]
    result.pop("scratch_dir")
    reference = json.loads(json.dumps(reference))
    reference.pop("scratch_dir")
    assert result == reference

    # one reference, trained before either run started (afterany dependency)
    rows = sacct(list(jobs.values()))
    for r in sweep.runs:
        assert when(rows[jobs[scratch]]["end"]) <= when(rows[jobs[f"run:{r.name}"]]["start"])
        metrics = json.loads((sweep.run_dir(r) / "metrics.json").read_text())
        assert metrics["method"] == r.config["method"]["type"] and metrics["fwt"] is not None
    status = json.loads((root / "report" / "status.json").read_text())
    assert sorted(status["done"]) == sorted(r.name for r in sweep.runs) and not status["missing"]
    assert {s["state"] for s in sweep_status(root).values()} == {"done"}

    assert main(args) == 0
    assert "nothing to submit" in capsys.readouterr().out
    assert len(load_sweep(root)[1]["submissions"]) == 1


def test_no_accounting_is_one_line(tmp_path, capsys, monkeypatch):
    # the real sbatch, sinfo and squeue, but no sacct
    monkeypatch.setenv("PATH", str(bin_with(tmp_path / "bin", "sbatch", "sinfo", "squeue")))
    code = main(toy_args(tmp_path / "runs", "ft"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "sacct not available (sacct is not on PATH)" in err
    assert not (tmp_path / "runs").exists()


def test_a_job_the_controller_lists_reads_its_live_state_whatever_accounting_says(
    tmp_path, monkeypatch
):
    """Accounting (sacct) lags behind the controller: a job that already ran could read as
    UNKNOWN (CI saw a running sweep job reported 'pending'). The controller's state comes first;
    here sacct is absent, so any answer but squeue's would fail."""
    from ccdata.slurm import job_states

    sbatch = ["sbatch", "--parsable", "--array=0-1", "--time=2", "-o", "/dev/null"]
    done = subprocess.run([*sbatch, "--wrap", "sleep 120"], capture_output=True, text=True,
                          check=True)  # fmt: skip
    array, scancel = done.stdout.strip().split(";")[0], shutil.which("scancel")
    try:
        monkeypatch.setenv("PATH", str(bin_with(tmp_path / "bin", "squeue")))
        states = job_states(tmp_path / "slurm", [f"{array}_0", f"{array}_1"])
        assert set(states) == {f"{array}_0", f"{array}_1"}
        assert set(states.values()) <= {"PENDING", "RUNNING", "CONFIGURING"}, states
    finally:
        subprocess.run([scancel, array], check=False)


@pytest.mark.integration
def test_a_sweep_through_slurm_shares_the_first_task_of_a_seed(tmp_path, capsys):
    """Sharing the first task on SLURM (the default): a job of its own trains it, the runs'
    array waits for it, both runs start from it, and the FT run equals an uninterrupted run of
    its config trained alone."""
    from ccfit.curriculum import Curriculum
    from ccfit.first_task import FIRST, FIRST_RECORD
    from ccfit.sweep.jobs import config_from_dict

    root = tmp_path / "runs"
    args = toy_args(root, "ft,ewc", "--train.steps=300", "--train.seed_steps=100",
                    "--train.eval_interval=100")  # fmt: skip
    assert main([*args, "--wait"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"(?m)^report\s+done", out) and re.search(r"(?m)^first:\S+\s+done", out)
    sweep, record = load_sweep(root)
    shared = [p for p in (root / FIRST).iterdir() if not p.name.startswith(".")]
    assert len(shared) == 1
    [entry] = record["submissions"]
    assert entry["jobs"][f"first:{shared[0].name}"]  # trained by its own job
    assert "shared first task" in _log(root, entry["jobs"][f"first:{shared[0].name}"])
    for run in sweep.runs:
        record = json.loads((sweep.run_dir(run) / FIRST_RECORD).read_text())
        assert record["shared"] == shared[0].name
    [run] = [r for r in sweep.runs if r.config["method"]["type"] == "ft"]
    alone = Curriculum(config_from_dict(run.config), tmp_path / "alone",
                       tmp_path / "alone-scratch", progress=False).run()  # fmt: skip
    result = json.loads((sweep.run_dir(run) / "metrics.json").read_text())
    for r in (result, alone):
        r.pop("scratch_dir")
    assert result == json.loads(json.dumps(alone))
