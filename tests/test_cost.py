"""cost.json: time summed over a run's segments, and the code that ran each segment."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import torch

from ccfit.train.cost import RunCost, read_cost, running_code

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
                                            "code": []}  # fmt: skip
