"""cost.json: time summed over a run's segments, and the code and machine that ran each segment."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest
import torch

from ccfit.train.cost import RunCost, read_cost, running_code, running_machine

ROOT = Path(__file__).resolve().parents[1]


def test_each_segment_records_the_code_that_ran_it(tmp_path):
    # a cost.json written before code was recorded: its segment stays counted, unnamed
    (tmp_path / "cost.json").write_text(json.dumps({"wall_s": 1.0, "cpu_s": 2.0, "segments": 1}))
    for _ in range(2):
        with RunCost(tmp_path):
            sum(range(10_000))
    cost = read_cost(tmp_path)
    assert cost["segments"] == 3 and cost["cpu_s"] >= 2.0 and cost["wall_s"] > 1.0
    assert cost["code"] == [running_code()] * 2
    assert cost["code"][0]["torch"] == torch.__version__
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode == 0:  # a checkout, as in CI
        assert cost["code"][0]["commit"] == head.stdout.strip()
    assert read_cost(tmp_path / "none") == {"wall_s": 0.0, "cpu_s": 0.0, "segments": 0,
                                            "code": [], "machines": []}  # fmt: skip


def test_each_segment_records_the_machine_kind_that_ran_it(tmp_path):
    # The vector kernels torch dispatches to decide the rounding, so a resumed run says where
    # each segment ran; a segment run with ATen's vector kernels off says so too.
    with RunCost(tmp_path):
        pass
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default"}
    script = "import sys\nfrom ccfit.train.cost import RunCost\nwith RunCost(sys.argv[1]): pass"
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], env=env, check=True,
                          capture_output=True, text=True)  # fmt: skip
    assert "(DEFAULT); its last segment ran on" in done.stderr
    first, second = read_cost(tmp_path)["machines"]
    assert first == running_machine() and first["cores"] >= 1
    assert first["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert second == {**first, "cpu_capability": "DEFAULT"}


def test_a_killed_segment_stays_counted_up_to_its_last_flush(tmp_path):
    # a process killed without warning (SIGKILL: no `finally`, no exit hook) keeps its cost
    busy = (
        "import sys\nfrom ccfit.train.cost import RunCost\n"
        "with RunCost(sys.argv[1], flush_s=0.05):\n    while True: sum(range(1000))\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", busy, str(tmp_path)])
    try:
        deadline = time.monotonic() + 60
        while read_cost(tmp_path)["cpu_s"] < 0.3:
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    killed = read_cost(tmp_path)
    assert killed["segments"] == 1 and killed["code"] == [running_code()]
    with RunCost(tmp_path):
        pass
    cost = read_cost(tmp_path)
    assert cost["segments"] == 2 and cost["cpu_s"] >= killed["cpu_s"] >= 0.3
    assert cost["code"] == [running_code()] * 2


def test_a_tree_exported_by_git_archive_records_its_commit(tmp_path):
    # A snapshot or release tarball has no .git: the commit comes from the fields git archive
    # fills in (.gitattributes export-subst on ccdata/archived.py).
    if not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout")

    def git(*args: str) -> bytes:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, check=True).stdout

    # the working tree as a commit object (no ref moves), or HEAD where nothing has changed
    commit = git("stash", "create").decode().strip() or git("rev-parse", "HEAD").decode().strip()
    with tarfile.open(fileobj=io.BytesIO(git("archive", commit, "ccdata"))) as tar:
        tar.extractall(tmp_path, filter="data")
    show = "import json; from ccdata.slurm import code_version; print(json.dumps(code_version()))"
    done = subprocess.run([sys.executable, "-c", show], cwd=tmp_path, capture_output=True,
                          text=True, check=True, env={"PYTHONPATH": str(tmp_path)})  # fmt: skip
    code = json.loads(done.stdout)
    assert Path(code["source"]) == tmp_path
    assert code["commit"] == commit and commit.startswith(code["git"])


def test_a_segment_that_used_cuda_names_its_gpu(tmp_path, monkeypatch):
    # CUDA stands in here (tests/test_gpu.py checks the real name on a GPU): the name is asked
    # only once the run has initialised CUDA.
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Some GPU")
    with RunCost(tmp_path):
        pass
    assert read_cost(tmp_path)["machines"] == [{**running_machine(), "gpu": "Some GPU"}]
    assert running_machine()["gpu"] is None


def test_a_run_resumed_on_another_cpu_kind_says_so(tmp_path, capsys):
    with RunCost(tmp_path):
        pass
    assert capsys.readouterr().err == ""  # the same kind: nothing to say
    cost = read_cost(tmp_path)
    other = {**cost["machines"][0], "cpu": "Another CPU", "cpu_capability": "AVX512"}
    (tmp_path / "cost.json").write_text(json.dumps({**cost, "machines": [other]}))
    with RunCost(tmp_path):
        pass
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "its last segment ran on Another CPU (AVX512)" in err
