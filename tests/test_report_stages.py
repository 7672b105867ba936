"""`stages.md` / `stages.csv`: each task's evaluations per stage, read as the metrics read them
(the later of two records of one step stands), with the successes counted where records have
them."""

from __future__ import annotations

import csv
import json

from ccfit.report.stages import CSV_HEADER, STAGES_CSV, STAGES_MD, stage_cells

try:
    from stage_ends import assert_stage_ends_are_the_metrics
    from test_report import config, write_run
except ImportError:
    from tests.stage_ends import assert_stage_ends_are_the_metrics
    from tests.test_report import config, write_run


def _record(stage, task, step, score, success=None, episodes=5):
    r = {"stage": stage, "task_index": task, "global_step": step, "normalized_return": score}
    return r if success is None else {**r, "success_rate": success, "episodes": episodes}


def test_cells_per_stage_and_task_in_order_with_successes():
    records = [
        _record(0, 0, 0, 10.0, 0.0),
        _record(0, 0, 100, 90.0, 0.8),
        _record(0, 0, 100, 30.0, 0.2),  # logged again after the end-of-task step: it stands
        _record(1, 1, 100, 5.0, 0.0),
        _record(1, 0, 200, 20.0, 0.4),
        _record(1, 1, 200, 60.0, 1.0),
        {"global_step": 200, "loss": 1.0},  # a training record: no score
    ]
    cells = stage_cells(records, "normalized_return")
    assert [(c.stage, c.task) for c in cells] == [(0, 0), (1, 0), (1, 1)]
    first, earlier, own = cells
    assert first.scores == (10.0, 30.0) and first.end == 30.0 and first.mean == 20.0
    assert (first.successes, first.episodes) == (1, 10)
    assert (earlier.successes, earlier.episodes, earlier.end) == (2, 5, 20.0)
    assert own.scores == (5.0, 60.0) and own.successes == 5


def test_records_without_success_counts_have_none():
    offline = [{"stage": 0, "task_index": 0, "global_step": s, "score": float(s)} for s in (0, 1)]
    (cell,) = stage_cells(offline, "score")
    assert (cell.successes, cell.episodes, cell.mean) == (None, None, 0.5)


def test_a_scored_record_without_its_stage_is_one_line_and_exit_2(tmp_path, capsys):
    from ccfit.cli import main

    run = write_run(tmp_path / "runs", "s0", config(), 1.0)
    lines = (run / "metrics.jsonl").read_text().splitlines()
    lines[1] = json.dumps({k: v for k, v in json.loads(lines[1]).items() if k != "stage"})
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    where = run / "metrics.jsonl"
    assert err.startswith(f"ccfit: error: {where}: the evaluation record at step 50")
    assert "names no stage" in err and err.count("\n") == 1


def test_the_ends_are_the_end_of_task_and_final_scores(tmp_path):
    from ccfit.report import group_runs
    from ccfit.report.runs import find_runs
    from ccfit.report.stages import write_stages

    for seed in (0, 1):
        write_run(tmp_path / "runs", f"ft-s{seed}", config(seed=seed), 1.0 + seed / 10)
    run_groups = group_runs(find_runs([tmp_path / "runs"]))
    written = write_stages(run_groups, {"online": "normalized_return"}, tmp_path / "report")
    assert [p.name for p in written] == [STAGES_MD, STAGES_CSV]
    rows = list(csv.DictReader((tmp_path / "report" / STAGES_CSV).open()))
    assert list(rows[0]) == CSV_HEADER
    for run in [r for runs in run_groups.values() for r in runs]:
        mine = [r for r in rows if r["run"] == run.path.name]
        assert_stage_ends_are_the_metrics(mine, run.metrics)
    text = (tmp_path / "report" / STAGES_MD).read_text()
    assert "## tdmpc2, Reach, ft, seed 0 (`ft-s0`)" in text and "seed 1 (`ft-s1`)" in text
    assert text.index("seed 0") < text.index("seed 1")


def test_an_end_carries_its_standard_error_where_its_record_holds_each_episodes_return():
    """SE of an end: the sample std of its episodes' normalised returns / sqrt(episodes).
    Returns -10, -20, -30 have std 10; normalising scales a return by 100 / (oracle - floor)."""
    from ccdata.scoring import normalize

    per_return = float(normalize("reach-xy", 1.0) - normalize("reach-xy", 0.0))
    own = {**_record(0, 0, 100, 50.0, 0.4, 3), "task": "reach-xy", "returns": [-10.0, -20.0, -30.0]}
    older = {**_record(0, 0, 0, 10.0, 0.0, 3), "task": "reach-xy"}  # kept no returns
    (cell,) = stage_cells([older, own], "normalized_return")
    assert abs(cell.end_se - per_return * 10.0 / 3**0.5) < 1e-9
    (cell,) = stage_cells([own, {**own, "global_step": 200, "returns": None}], "normalized_return")
    assert cell.end_se is None  # the end's own record says nothing of its episodes
    (cell,) = stage_cells([{**own, "score": 1.0}], "score")  # offline scores: no episodes
    assert cell.end_se is None
