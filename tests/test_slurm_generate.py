"""`ccdata generate --launcher slurm`: shards as a job array, then a merge job (ccdata.launch).

The tests marked `slurm` submit to the real SLURM of this machine (`.ci/slurm-up.sh` brings one
up) through the real CLI, and compare the result with a dataset that one local worker wrote.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ccdata.cli import main
from ccdata.cli_generate import SLURM_TIME
from ccdata.episode_plan import plan
from ccdata.journal import JournalPaths, finished_pieces
from ccdata.launch import SUBMISSION_RECORD
from ccdata.record import GenerateConfig, generate
from ccdata.slurm import (
    LaunchError,
    SlurmSettings,
    check_array_size,
    max_array_size,
    parse_time,
    settings_from_options,
)
from ccfit.sweep.cli import SLURM_TIME as SWEEP_SLURM_TIME

try:
    from slurm_helpers import JOB_WAIT_S, bin_with, wait_for, when
except ImportError:  # tests/ imported as a package
    from tests.slurm_helpers import JOB_WAIT_S, bin_with, wait_for, when

TINY = dict(suite="Reach", episodes=1, explore_episodes=1, image_size=32, max_steps=12)
TINY_ARGS = [
    "--suite",
    "Reach",
    "--episodes",
    "1",
    "--explore-episodes",
    "1",
    "--image-size",
    "32",
    "--max-steps",
    "12",
]


def generate_cli(*args: str, path: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **({"PATH": path} if path is not None else {})}
    return subprocess.run(
        [sys.executable, "-m", "ccdata.cli", "generate", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def submit(root: Path, *args: str) -> dict:
    done = generate_cli(
        *TINY_ARGS, "--root", str(root), "--launcher", "slurm", "--time", "30", "--json", *args
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def shard_ids(sub: dict) -> list[str]:
    """Job ids of the submitted shards: array tasks, or a plain job when there is one."""
    if len(sub["shards"]) == 1:
        return [sub["array_job"]]
    return [f"{sub['array_job']}_{i}" for i in range(len(sub["shards"]))]


def assert_same_dataset(expected: Path, actual: Path) -> None:
    """Every file the same bytes, but meta/stats.json (LeRobot writes its keys in no fixed
    order), which holds the same numbers."""
    files = sorted(p.relative_to(expected) for p in expected.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(actual) for p in actual.rglob("*") if p.is_file())
    assert any(f.suffix == ".parquet" for f in files) and any(f.suffix == ".mp4" for f in files)
    for rel in files:
        if rel == Path("meta/stats.json"):
            assert json.loads((expected / rel).read_text()) == json.loads(
                (actual / rel).read_text()
            )
        else:
            assert (expected / rel).read_bytes() == (actual / rel).read_bytes(), rel


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory) -> Path:
    root, _ = generate(
        GenerateConfig(**TINY, root=tmp_path_factory.mktemp("w1") / "Reach"), progress=False
    )
    return root


# ── Without SLURM ─────────────────────────────────────────────────────────────────────────


def test_parse_time_reads_slurm_time_limits():
    assert parse_time("45") == 45
    assert parse_time("1:30") == 2  # minutes:seconds, rounded up
    assert parse_time("2:00:00") == 120
    assert parse_time("1-0") == 24 * 60
    assert parse_time("1-02:03") == 26 * 60 + 3
    assert parse_time("0-00:00:30") == 1
    for bad in ("", "1h", "0", "1:2:3:4"):
        with pytest.raises(ValueError, match="--time"):
            parse_time(bad)


def test_no_slurm_is_one_line_and_exit_2(tmp_path):
    empty = tmp_path / "bin"
    empty.mkdir()
    done = generate_cli(
        *TINY_ARGS,
        "--root",
        str(tmp_path / "Reach"),
        "--launcher",
        "slurm",
        "--shards",
        "2",
        path=str(empty),
    )
    assert done.returncode == 2
    assert done.stderr == "ccdata generate: error: no SLURM reachable: sbatch is not on PATH\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin"]  # nothing written


@pytest.mark.parametrize(
    "args, message",
    [
        (["--shards", "2"], "--shards need --launcher slurm"),
        (
            ["--account", "a", "--cpus-per-task", "2"],
            "--account, --cpus-per-job need --launcher slurm",
        ),
        (["--launcher", "slurm", "--workers", "2"], "--workers is for --launcher local"),
        (["--launcher", "slurm", "--time", "1h"], "--time '1h': expected minutes"),
        (["--launcher", "slurm", "--mem", "8GB"], "--mem '8GB': expected a number"),
        (["--launcher", "slurm", "--shards", "0"], "--shards must be >= 1"),
    ],
)
def test_launch_options_are_checked(tmp_path, capsys, args, message):
    assert main(["generate", *TINY_ARGS, "--root", str(tmp_path / "Reach"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ccdata generate: error: ") and message in err
    assert err.count("\n") == 1 and not any(tmp_path.iterdir())


def test_generate_and_sweep_read_the_same_slurm_options():
    """One set of SLURM options (ccdata.slurm) in both commands; only the default time differs."""
    from ccdata.cli import build_parser
    from ccfit.sweep.cli import build_parser as sweep_parser

    def both(*flags: str) -> tuple[SlurmSettings, SlurmSettings]:
        gen = build_parser().parse_args(["generate", "--suite", "Reach", *flags])
        swp, run_args = sweep_parser().parse_known_args(["--suites", "Reach", *flags])
        assert run_args == []
        return (settings_from_options(gen, SLURM_TIME),
                settings_from_options(swp, SWEEP_SLURM_TIME))  # fmt: skip

    flags = ["--partition", "p", "--account", "a", "--qos", "q", "--time", "2:00:00",
             "--cpus-per-task", "3", "--gpus-per-job", "1", "--mem", "4G", "--setup", "x",
             "--setup", "y"]  # fmt: skip
    expected = SlurmSettings(partition="p", account="a", qos="q", time_min=120, cpus_per_job=3,
                             gpus_per_job=1, mem="4G", setup=["x", "y"])  # fmt: skip
    assert both(*flags) == (expected, expected)
    assert expected.executor_parameters() == {
        "time": 120, "partition": "p", "account": "a", "qos": "q", "cpus_per_task": 3,
        "mem": "4G", "gpus_per_node": 1, "setup": ["x", "y"]}  # fmt: skip
    gen, swp = both("--cpus-per-job", "2")
    assert (gen.cpus_per_job, gen.time_min, swp.time_min) == (2, 60, 24 * 60)
    assert gen.executor_parameters() == {"time": 60, "cpus_per_task": 2, "setup": []}
    with pytest.raises(LaunchError, match="--gpus-per-job must be >= 0, got -1"):
        both("--gpus-per-job", "-1")


# ── With SLURM ────────────────────────────────────────────────────────────────────────────


@pytest.mark.slurm
def test_arrays_beyond_max_array_size_are_refused():
    limit = max_array_size()
    out = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True).stdout
    assert re.search(rf"(?m)^MaxArraySize\s*=\s*{limit}$", out)
    check_array_size(limit, "--shards")
    with pytest.raises(
        LaunchError, match=f"--shards: this cluster takes arrays of at most {limit} tasks"
    ):
        check_array_size(limit + 1, "--shards")


@pytest.mark.slurm
def test_sacct_missing_is_one_line_and_exit_2(tmp_path):
    """The real sbatch and sinfo, but no sacct: refused before anything is submitted."""
    tools = bin_with(tmp_path / "bin", "sbatch", "sinfo", "squeue", "scancel")
    done = generate_cli(
        *TINY_ARGS, "--root", str(tmp_path / "Reach"), "--launcher", "slurm", path=str(tools)
    )
    assert done.returncode == 2
    assert done.stderr == (
        "ccdata generate: error: sacct not available (sacct is not on PATH); "
        "submitit needs SLURM accounting\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin"]


@pytest.mark.slurm
def test_unreachable_controller_is_one_line_and_exit_2(tmp_path, monkeypatch):
    """This cluster's configuration, but the controller's port is one where nobody listens."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    conf = Path(os.environ.get("SLURM_CONF", "/etc/slurm/slurm.conf")).read_text()
    conf = re.sub(r"(?m)^(SlurmctldPort|MessageTimeout)=.*$", "", conf)
    (tmp_path / "slurm.conf").write_text(f"{conf}\nSlurmctldPort={port}\nMessageTimeout=1\n")
    monkeypatch.setenv("SLURM_CONF", str(tmp_path / "slurm.conf"))
    root = tmp_path / "Reach"
    done = generate_cli(*TINY_ARGS, "--root", str(root), "--launcher", "slurm")
    assert done.returncode == 2
    assert done.stderr == (
        "ccdata generate: error: no SLURM reachable: slurm_load_partitions: "
        "Unable to contact slurm controller (connect failure)\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slurm.conf"]


@pytest.mark.integration
@pytest.mark.slurm
def test_missing_shard_fails_the_merge_and_a_rerun_fills_it_to_the_one_worker_dataset(
    one_worker, tmp_path
):
    """One scenario (each submission of tiny shards costs tens of seconds): a sharded
    submission, a shard lost halfway, the merge refusing the gap, and a rerun that fills only
    the gap; the result is the dataset one local worker writes."""
    root = tmp_path / "Reach"
    first = submit(root, "--shards", "2")
    array, shard1 = first["array_job"], first["shards"]["1"]
    keys = [s.key for s in plan(GenerateConfig(**TINY))]
    assert first["planned"] == 12 and list(first["shards"]) == ["0", "1"]
    assert [k for shard in first["shards"].values() for k in shard] == keys  # contiguous
    assert first["code"].startswith("ccbench ")
    # A second submission while these jobs are queued would repair the journal under them.
    again = generate_cli(*TINY_ARGS, "--root", str(root), "--launcher", "slurm")
    assert again.returncode == 2 and "still queued or running" in again.stderr

    # Kill shard 1 once it has written its first episode (of 6): it dies halfway.
    deadline = time.monotonic() + JOB_WAIT_S
    while not any(k in finished_pieces(JournalPaths(root)) for k in shard1):
        assert time.monotonic() < deadline, "shard 1 wrote nothing"
        time.sleep(0.2)
    subprocess.run(["scancel", f"{array}_1"], check=True)
    rows = wait_for([f"{array}_0", f"{array}_1", first["merge_job"]])
    assert rows[f"{array}_0"]["state"] == "COMPLETED"
    assert rows[f"{array}_1"]["state"] == "CANCELLED"
    assert rows[first["merge_job"]]["state"] == "FAILED"  # afterany: it ran, and failed
    assert when(rows[first["merge_job"]]["start"]) >= when(rows[f"{array}_1"]["end"])

    written = finished_pieces(JournalPaths(root))
    missing = [k for k in keys if k not in written]
    assert missing and set(missing) < set(shard1)  # some of shard 1's episodes were written
    assert set(first["shards"]["0"]) <= set(written)
    merge = first["merge_job"]
    err = (Path(first["log_dir"]) / merge / f"{merge}_0_log.err").read_text()
    assert f"ccdata merge: {len(missing)} episode(s) missing:" in err
    assert all(f"\n  {k}" in err for k in missing)
    assert "Run the same `ccdata generate` command again" in err
    assert not root.exists()  # nothing merged
    assert (JournalPaths(root).work / SUBMISSION_RECORD).is_file()

    second = submit(
        root,
        "--shards",
        "2",
        "--partition",
        "low",
        "--cpus-per-task",
        "1",
        "--mem",
        "1G",
        "--setup",
        "echo ccdata-setup-ran",
    )
    assert second["shards"] == {"1": missing}  # only the shard with gaps, only its gaps
    rows = wait_for([*shard_ids(second), second["merge_job"]])
    assert {j: r["state"] for j, r in rows.items()} == {
        j: "COMPLETED" for j in [*shard_ids(second), second["merge_job"]]
    }
    merge_start = when(rows[second["merge_job"]]["start"])
    assert all(merge_start >= when(rows[j]["end"]) for j in shard_ids(second))
    assert_same_dataset(one_worker, root)
    assert not JournalPaths(root).work.exists()  # the merge cleared its journal
    merge_dir = Path(second["log_dir"]) / second["merge_job"]
    script = (merge_dir / f"{second['merge_job']}_submission.sh").read_text()
    for line in (
        "--partition=low",
        "--cpus-per-task=1",
        "--mem=1G",
        "--time=30",
        "--requeue",
        f"--dependency=afterany:{second['array_job']}",
        "\necho ccdata-setup-ran\n",
    ):
        assert line in script
    log = (merge_dir / f"{second['merge_job']}_0_log.out").read_text()
    assert "ccdata-setup-ran" in log and f"submitted with {second['code']}" in log

    third = generate_cli(*TINY_ARGS, "--root", str(root), "--launcher", "slurm")
    assert third.returncode == 0 and "nothing to submit" in third.stdout
    assert not JournalPaths(root).work.exists()
