"""`ccfit compare A B`: the records two runs share, the first that differs and what else
differs between the runs (settings, code, machines, dataset content), exit 0 / 1 / 2. The run
directories are written as a run leaves them (config.json, metrics.jsonl, cost.json); a real
resumed run compared with its uninterrupted twin is in tests/test_loop.py."""

from __future__ import annotations

import json
from pathlib import Path

from ccfit.cli import main
from ccfit.compare import compare_runs

MACHINE = {"cpu": "Some CPU", "cpu_capability": "AVX2", "cores": 2, "gpu": None}


def write_run(root: Path, name: str, scores: list[float], *, seed: int = 0,
              data: str = "aa" * 32, machines: list[dict] | None = None) -> Path:  # fmt: skip
    """A two-stage run evaluated every 100 steps: stage 0 evaluates task 0, stage 1 both."""
    run = root / name
    run.mkdir(parents=True)
    records, i = [], 0
    for stage in (0, 1):
        for step in range(stage * 200, stage * 200 + 200, 100):
            for task in range(stage + 1):
                if i < len(scores):
                    record = {"stage": stage, "task_index": task, "task": f"t{task}"}
                    records.append({**record, "global_step": step, "normalized_return": scores[i]})
                i += 1
    dataset = {"total_episodes": 8, "content_sha256": {"data": data, "videos": None}}
    config = {"suite": "Reach", "seed": seed, "out": str(run), "train": {"steps": 200},
              "resolved_seed_dataset_meta": dataset}  # fmt: skip
    (run / "config.json").write_text(json.dumps(config))
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    machines = [MACHINE] if machines is None else machines
    (run / "cost.json").write_text(json.dumps({
        "wall_s": 1.0, "cpu_s": 1.0, "segments": 1, "machines": machines,
        "code": [{"git": "abc1234", "commit": "abc1234" + "0" * 33}]}))  # fmt: skip
    return run


def test_a_run_that_reproduces_another_so_far_exits_0(tmp_path, capsys):
    a = write_run(tmp_path, "a", [10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    b = write_run(tmp_path, "b", [10.0, 20.0, 30.0])  # still going
    comparison = compare_runs(a, b)
    assert comparison.reproduces and (comparison.shared, comparison.only) == (3, (3, 0))
    assert main(["compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "settings: the same" in out and "B reproduces A's records (3 of the 3 both hold)" in out
    assert "machines: A Some CPU (AVX2, 2 cores) x1; B Some CPU (AVX2, 2 cores) x1" in out
    assert "resolved_seed_dataset_meta.content_sha256: the same" in out
    # a run that has evaluated nothing yet reproduces nothing: exit 1
    fresh = write_run(tmp_path, "fresh", [])
    assert not compare_runs(a, fresh).reproduces
    assert main(["compare", str(a), str(fresh)]) == 1
    assert "no evaluation in common: nothing reproduced yet" in capsys.readouterr().out


def test_the_first_differing_record_and_what_else_differs_exit_1(tmp_path, capsys):
    a = write_run(tmp_path, "a", [10.0, 20.0, 30.0, 40.0, 50.0])
    other = {**MACHINE, "cpu": "Other CPU", "cpu_capability": "AVX512"}
    b = write_run(tmp_path, "b", [10.0, 20.0, 31.0, 40.0, 55.0], seed=1, data="bb" * 32,
                  machines=[])  # fmt: skip
    c = write_run(tmp_path, "c", [10.0, 20.0, 30.0, 40.0, 50.0], machines=[other])
    comparison = compare_runs(a, b)
    assert not comparison.reproduces and comparison.equal == 3 and comparison.shared == 5
    assert comparison.settings == {"seed": (0, 1)}  # `out` and the dataset record aside
    assert comparison.first_difference == {
        "stage": 1, "task": "t0", "global_step": 200,
        "fields": {"normalized_return": (30.0, 31.0)}}  # fmt: skip
    assert main(["compare", str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "first difference: global step 200, t0 (stage 1)" in out
    assert "  normalized_return: 30.0 -> 31.0" in out and "machines: A Some CPU" in out
    assert "B not recorded x1" in out  # b's segment predates the machine record
    assert "content_sha256: differ (A data aaaaaaaaaaaa; B data bbbbbbbbbbbb)" in out
    # equal records from another machine kind: reproduced, and the machines say where
    assert main(["compare", str(a), str(c)]) == 0
    assert "B Other CPU (AVX512, 2 cores) x1" in capsys.readouterr().out


def test_a_directory_that_is_not_a_run_is_one_line_exit_2(tmp_path, capsys):
    a = write_run(tmp_path, "a", [10.0])
    (tmp_path / "empty").mkdir()
    assert main(["compare", str(a), str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ccfit: error: {tmp_path / 'empty' / 'config.json'}: missing")
    assert err.count("\n") == 1


def test_a_field_only_one_runs_records_hold_is_named_and_not_compared(tmp_path, capsys):
    """A run made by code that records each episode's return (`returns`) reproduces one made
    before it recorded them, where their other fields agree; where those differ, it does not."""
    a = write_run(tmp_path, "a", [10.0, 20.0, 30.0])
    b = write_run(tmp_path, "b", [10.0, 20.0, 30.0])
    c = write_run(tmp_path, "c", [10.0, 21.0, 30.0])
    for run in (b, c):
        lines = (run / "metrics.jsonl").read_text().splitlines()
        with_returns = [{**json.loads(x), "returns": [-1.0, -2.0]} for x in lines]
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in with_returns))
    comparison = compare_runs(a, b)
    assert comparison.reproduces and comparison.one_sided == ([], ["returns"])
    assert main(["compare", str(a), str(b)]) == 0
    assert "fields only B's records hold (not compared): returns" in capsys.readouterr().out
    assert compare_runs(b, a).one_sided == (["returns"], [])
    # a setting that only says how a run ran, or why, is named as such
    config = json.loads((b / "config.json").read_text())
    config |= {"resolved_compile_reason": "auto: eager", "train": {"steps": 200, "parallel": "on"}}
    (b / "config.json").write_text(json.dumps(config))
    assert main(["compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "resolved_compile_reason: None -> 'auto: eager' (how it ran or a note: not" in out
    assert "train.parallel: None -> 'on' (how it ran or a note: not part of the run's" in out
    different = compare_runs(a, c)
    assert not different.reproduces
    assert different.first_difference["fields"] == {"normalized_return": (20.0, 21.0)}
