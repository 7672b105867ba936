"""`ccfit report` groups runs by their whole config: runs that differ in anything but the seed
(and seed-derived values, output paths) are never averaged, and the tables and plots name what
differs. Run directories are written in the layout `ccfit run` leaves (config.json,
metrics.jsonl, metrics.json, the from-scratch reference's done.json), with metrics computed by
the same `ccfit.curriculum.compute_metrics` a run uses."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ccfit.config_parse import flatten
from ccfit.metrics import compute_metrics
from ccfit.report import group_metrics, group_runs, load_groups, write_report
from ccfit.report.runs import find_runs

SUITE, TASKS, STEPS = "Reach", 4, 100


def curve_records(task_scores: list[list[float]]) -> list[dict]:
    """Evaluation records: task t's score list is sampled every 50 steps from its start. As a
    run logs them, an evaluation at a stage's last step belongs to that stage, except the one
    that opens the next task's stage."""
    records = []
    for t, scores in enumerate(task_scores):
        for i, score in enumerate(scores):
            step = t * STEPS + 50 * i
            records.append({"task_index": t, "global_step": step, "normalized_return": score,
                            "stage": max(t, (step - 1) // STEPS)})  # fmt: skip
    return records


def write_run(root: Path, name: str, config: dict, scale: float) -> Path:
    """A finished run whose task t scores rise to 80 * scale then fall by 10 * t afterwards."""
    run = root / name
    run.mkdir(parents=True)
    scores = []
    for t in range(TASKS):
        points = (TASKS - t) * 2 + 1
        scores.append(
            [min(80.0, 40.0 * i) * scale - (10.0 * t if i > 2 else 0.0) for i in range(points)]
        )
    records = curve_records(scores)
    scratch_dir = root / "scratch" / f"{name}-scratch"
    scratch_dir.mkdir(parents=True)
    scratch = [
        {"task_index": TASKS - 1, "global_step": 50 * i, "normalized_return": 30.0 * i}
        for i in range(3)
    ]
    (scratch_dir / "done.json").write_text(json.dumps(scratch))
    metrics = compute_metrics(records, scratch, TASKS, STEPS)
    metrics["scratch_dir"] = str(scratch_dir)
    (run / "config.json").write_text(json.dumps(config))
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    (run / "metrics.json").write_text(json.dumps(metrics))
    return run


def config(obs: str = "state", seed: int = 0, **top) -> dict:
    return {
        "suite": SUITE,
        "model": "tdmpc2",
        "method": "ft",
        "method_options": {},
        "preset": "smoke",
        "obs": obs,
        "seed": seed,
        "encoder": None,
        **top,
        "train": {"steps": STEPS, "seed": seed, "obs": obs, "buffer_capacity": 1000},
        "model_config": {"latent_dim": 64, "obs_mode": obs},
    }


def test_flatten_makes_dotted_hashable_keys():
    flat = flatten({"a": 1, "b": {"c": [1, 2], "d": {"e": None}}, "f": {}})
    assert flat == {"a": 1, "b.c": "[1, 2]", "b.d.e": None}


def test_report_refuses_to_average_runs_differing_in_obs_mode(tmp_path):
    root = tmp_path / "runs"
    state0 = write_run(root, "state-s0", config("state", 0), 1.0)
    state1 = write_run(root, "state-s1", config("state", 1), 0.5)
    pixels = write_run(root, "pixels-s0", config("pixels", 0), 0.25)

    runs = find_runs([root])
    with pytest.raises(
        ValueError,
        match=r"refusing to average runs whose configs differ in "
        r"\['model_config.obs_mode', 'obs', 'train.obs'\]",
    ):
        group_metrics(runs)
    groups = group_runs(runs)
    # Seeds of the same config average; the other observation mode is a group of its own,
    # named by the one setting that tells them apart (not by its echoes in train/model_config).
    assert {k: sorted(r.path.name for r in v) for k, v in groups.items()} == {
        ("tdmpc2", SUITE, "ft", "obs=pixels"): ["pixels-s0"],
        ("tdmpc2", SUITE, "ft", "obs=state"): ["state-s0", "state-s1"],
    }
    metrics = load_groups([root])
    pix = metrics[("tdmpc2", SUITE, "ft", "obs=pixels")]
    assert pix["seeds"] == [0] and pix["runs"] == [str(pixels)]
    single = json.loads((pixels / "metrics.json").read_text())
    assert pix["bwt"] == pytest.approx(single["bwt"]) and pix["fwt"] == pytest.approx(single["fwt"])
    st = metrics[("tdmpc2", SUITE, "ft", "obs=state")]
    assert st["seeds"] == [0, 1] and sorted(st["runs"]) == sorted(map(str, (state0, state1)))
    per_seed = [json.loads((r / "metrics.json").read_text())["bwt"] for r in (state0, state1)]
    assert st["bwt_min"] == pytest.approx(min(per_seed))
    assert st["bwt_max"] == pytest.approx(max(per_seed))
    # The mean curve of the two state seeds (scales 1 and 0.5) is the scale-0.75 curve.
    mean_run = write_run(tmp_path / "probe", "mean", config("state", 0), 0.75)
    assert st["bwt"] == pytest.approx(json.loads((mean_run / "metrics.json").read_text())["bwt"])
    # Forgetting (Continual World's) the same way: of the mean curve, min/max per seed.
    forgetting = [json.loads((r / "metrics.json").read_text())["cw_forgetting"]
                  for r in (state0, state1, mean_run)]  # fmt: skip
    assert forgetting == pytest.approx([10.0] * 3)  # every curve loses 10 points, any scale
    assert (st["forgetting"], st["forgetting_min"], st["forgetting_max"]) == pytest.approx(
        (10.0, 10.0, 10.0)
    )

    out = tmp_path / "report"
    written = {p.name for p in write_report([root], out)}
    md = (out / "table_tdmpc2.md").read_text()
    assert "Runs differ in `obs`" in md
    rows = [line for line in md.splitlines() if line.startswith(f"| {SUITE}")]
    assert [r.split("|")[1].strip() for r in rows] == [
        f"{SUITE} [obs=pixels]",
        f"{SUITE} [obs=state]",
    ]
    with (out / "table_tdmpc2.csv").open() as f:
        table = {r["variant"]: r for r in csv.DictReader(f)}
    assert set(table) == {"obs=pixels", "obs=state"}
    assert table["obs=state"]["seeds"] == "2" and table["obs=pixels"]["seeds"] == "1"
    assert float(table["obs=pixels"]["bwt"]) == pytest.approx(single["bwt"])
    assert {
        "curves_tdmpc2_Reach_ft_obs=pixels.png",
        "curves_tdmpc2_Reach_ft_obs=state.png",
    } <= written
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary) == [f"tdmpc2/{SUITE}/ft [obs=pixels]", f"tdmpc2/{SUITE}/ft [obs=state]"]


def test_step_budget_and_method_options_split_groups_but_output_paths_and_as_run_records_do_not(
    tmp_path,
):
    root = tmp_path / "runs"
    write_run(root, "a", config(out="/x/a", derived_seed=11, resolved_compile=["loss"],
                                resolved_compile_reason="auto: loss measured faster",
                                resolved_seed_dataset="/here/Reach",
                                resolved_seed_dataset_meta={"total_episodes": 8}), 1.0)  # fmt: skip
    write_run(root, "b", config(out="/y/b", derived_seed=12, seed=1, resolved_compile=["plan"],
                                resolved_seed_dataset="/there/Reach"), 1.0)  # fmt: skip
    write_run(root, "e", config(resolved_autocast="bf16"), 1.0)  # what it computed in: splits
    longer = config()
    longer["train"]["steps"] = 2 * STEPS
    write_run(root, "c", longer, 1.0)
    write_run(root, "d", config(method_options={"lam": 10}), 1.0)
    groups = group_runs(find_runs([root]))
    names = {k[3]: sorted(r.path.name for r in v) for k, v in groups.items()}
    assert names == {
        "train.steps=100": ["a", "b"],
        "train.steps=200": ["c"],
        "method_options.lam=10, train.steps=100": ["d"],
        "resolved_autocast=bf16, train.steps=100": ["e"],
    }
    assert all(np.isfinite(g["bwt"]) for g in load_groups([root]).values())


def test_a_published_copy_reads_the_reference_beside_it(tmp_path):
    # metrics.json names where the sweep wrote the reference; a copy of the tree (what
    # `ccfit publish` makes) reads its own copy, even where the original still exists.
    from ccfit.report.runs import scratch_dir_of

    write_run(tmp_path / "sweep", "a", config(), 1.0)
    shutil.copytree(tmp_path / "sweep", tmp_path / "published")
    metrics = json.loads((tmp_path / "published" / "a" / "metrics.json").read_text())
    assert Path(metrics["scratch_dir"]).is_dir()  # the original is still here
    found = scratch_dir_of(tmp_path / "published" / "a", metrics)
    assert found == tmp_path / "published" / "scratch" / "a-scratch"


@pytest.mark.parametrize("damage", ["corrupt metrics.json", "missing metrics.jsonl",
                                    "corrupt cost.json", "list metrics.json",
                                    "list config.json", "number metrics.jsonl"])  # fmt: skip
def test_a_damaged_run_directory_is_one_line_and_exit_2(damage, tmp_path, capsys):
    """A run copied in part or cut short is bad input: `ccfit report` names the file in one
    line (a corrupt metrics.json gave a JSONDecodeError traceback, a missing metrics.jsonl a
    FileNotFoundError one, valid JSON of another shape a TypeError or AttributeError)."""
    from ccfit.cli import main

    run = write_run(tmp_path / "runs", "s0", config(), 1.0)
    if damage.startswith("corrupt"):
        broken = run / damage.split()[1]
        broken.write_text('{"bwt": ')
    elif damage.startswith(("list", "number")):
        broken = run / damage.split()[1]
        broken.write_text("[1]\n" if damage.startswith("list") else "1\n")
    else:
        broken = run / "metrics.jsonl"
        broken.unlink()
    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ccfit: error: {broken}: missing or corrupt (") and err.count("\n") == 1


@pytest.mark.parametrize("lost", [(0, 100), (3, 300), (2, 400), ("scratch", 100)])
def test_an_evaluation_the_metrics_read_lost_is_refused_not_interpolated(lost, tmp_path, capsys):
    """Records that lack a score the metrics read at a stage boundary (C_0 at b_0, the last
    task's at its stage's start, a final score, the reference's at the budget) were cut: the
    metrics would interpolate there (C_0 between steps 50 and 150 of the records below), so
    `compute_metrics` refuses them and `ccfit report` names the run in one line, exit 2."""
    from ccfit.cli import main

    run = write_run(tmp_path / "runs", "s0", config(), 1.0)
    task, step = lost
    if task == "scratch":
        done = tmp_path / "runs" / "scratch" / "s0-scratch" / "done.json"
        kept = [r for r in json.loads(done.read_text()) if r["global_step"] != step]
        done.write_text(json.dumps(kept))
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        with pytest.raises(
            ValueError, match="from-scratch reference has no evaluation at step 100"
        ):
            compute_metrics(records, kept, TASKS, STEPS)
    else:
        lines = (run / "metrics.jsonl").read_text().splitlines()
        kept = [r for r in map(json.loads, lines) if (r["task_index"], r["global_step"]) != lost]
        assert len(kept) == len(lines) - 1
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in kept))
        scratch = json.loads(
            (tmp_path / "runs" / "scratch" / "s0-scratch" / "done.json").read_text()
        )
        with pytest.raises(
            ValueError, match=f"task {task} has no evaluation at global step {step}"
        ):
            compute_metrics(kept, scratch, TASKS, STEPS)
    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ccfit: error: {run}: ") and "(records lost?)" in err
    assert err.count("\n") == 1


def test_cost_md_counts_each_groups_hours_and_machines_and_each_reference_once(tmp_path):
    from ccfit.report.cost import COST_MD

    machine = {"cpu": "Some CPU", "cpu_capability": "AVX2", "cores": 2}
    runs = [write_run(tmp_path, f"s{seed}", config(seed=seed), 1.0) for seed in range(3)]
    er = write_run(tmp_path, "er-s0", config(method="er"), 1.0)  # a second group, for the total
    (er / "cost.json").write_text(json.dumps({"wall_s": 1.0, "cpu_s": 900.0, "segments": 1,
                                              "machines": [machine]}))  # fmt: skip
    # seed 0: two segments, the first from before machines were recorded; seed 1: one; seed 2
    # has no cost.json. Every run shares one reference, trained as a job of its own.
    costs = {0: {"cpu_s": 7200.0, "segments": 2, "machines": [machine]},
             1: {"cpu_s": 3600.0, "segments": 1, "machines": [machine]}}  # fmt: skip
    for seed, cost in costs.items():
        (runs[seed] / "cost.json").write_text(json.dumps({"wall_s": 1.0, **cost}))
    shared = tmp_path / "scratch" / "s0-scratch"
    for run in (runs[1], runs[2], er):
        metrics = json.loads((run / "metrics.json").read_text())
        (run / "metrics.json").write_text(json.dumps({**metrics, "scratch_dir": str(shared)}))
    (shared / "cost.json").write_text(json.dumps({"wall_s": 1.0, "cpu_s": 1800.0, "segments": 1,
                                                  "machines": [machine]}))  # fmt: skip
    write_report([tmp_path], tmp_path / "out")
    lines = (tmp_path / "out" / COST_MD).read_text().splitlines()
    label = "Some CPU (AVX2, 2 cores)"
    assert (
        f"| tdmpc2 | Reach | ft | 3 | 1.50 [1.00, 2.00] | 3.00 (1 without cost.json) | "
        f"{label} x2; not recorded x1 |"
    ) in lines
    assert f"| tdmpc2 | Reach | er | 1 | 0.25 | 0.25 | {label} x1 |" in lines
    assert "| all | | | 4 | | 3.25 (1 without cost.json) | |" in lines
    assert f"| tdmpc2 | Reach | 1 | 0.50 | 0.50 | {label} x1 |" in lines
    assert "| all | | 1 | | 0.50 | |" in lines
    # the one reference has its cost.json; without it, the report says so
    assert not any("without a cost.json" in line for line in lines)
    (shared / "cost.json").unlink()
    write_report([tmp_path], tmp_path / "out")
    text = (tmp_path / "out" / COST_MD).read_text()
    assert "From-scratch references without a cost.json: 1 of 1" in text


def test_cost_md_counts_a_shared_first_task_a_job_trained_once(tmp_path):
    """A seed's first task that a sweep's job trained is in no run's cost.json: cost.md counts
    it once from the record of the runs that started from it; one a run trained is not counted
    again (that run's cost.json holds it)."""
    from ccfit.report.cost import COST_MD

    machine = {"cpu": "Some CPU", "cpu_capability": "AVX2", "cores": 2}
    by_job = {
        "shared": "Reach-tdmpc2-s0",
        "trained_by": "job",
        "state_sha256": "a",
        "cost": {"wall_s": 1.0, "cpu_s": 1800.0, "segments": 1, "machines": [machine]},
    }
    by_run = {**by_job, "shared": "Reach-tdmpc2-s1", "trained_by": "run",
              "cost": {**by_job["cost"], "cpu_s": 7200.0}}  # fmt: skip
    for name, record in (("ft-s0", by_job), ("er-s0", by_job), ("ft-s1", by_run)):
        method, seed = name.split("-s")
        run = write_run(tmp_path, name, config(method=method, seed=int(seed)), 1.0)
        (run / "first_task.json").write_text(json.dumps(record))
    write_report([tmp_path], tmp_path / "out")
    text = (tmp_path / "out" / COST_MD).read_text()
    table = text.split("## Shared first tasks trained by a job of their own")[1].splitlines()
    assert "| tdmpc2 | Reach | 1 | 0.50 | 0.50 | Some CPU (AVX2, 2 cores) x1 |" in table
    assert "| all | | 1 | | 0.50 | |" in table
    # none trained by a job: no table
    for name in ("ft-s0", "er-s0"):
        (tmp_path / name / "first_task.json").write_text(json.dumps(by_run))
    write_report([tmp_path], tmp_path / "out")
    assert "Shared first tasks" not in (tmp_path / "out" / COST_MD).read_text()


def test_curve_plot_keeps_green_and_red_for_forward_transfer(tmp_path, monkeypatch):
    """The composed task's FWT shading is green/red; no task curve or forgetting shading may use
    those colours (the default colour cycle gives the third task green and the fourth red)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_hex

    root = tmp_path / "runs"
    write_run(root, "s0", config(), 1.0)
    figures = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    write_report([root], tmp_path / "report")
    (ax,) = [f for f in figures if f is not None and f.axes[0].get_xlabel() == "global step"][
        0
    ].axes  # the curve plot (the bar plots have no step axis)
    fwt = {to_hex("tab:green"), to_hex("tab:red")}
    tasks = [
        line
        for line in ax.lines  # '_' labels: the task boundaries
        if not line.get_label().startswith("_") and "(scratch)" not in line.get_label()
    ]
    assert len(tasks) == TASKS
    task_colours = {to_hex(line.get_color()) for line in tasks}
    assert len(task_colours) == TASKS and not task_colours & fwt
    shading = {c.get_label(): to_hex(c.get_facecolor()[0][:3]) for c in ax.collections}
    assert {shading["FWT +"], shading["FWT -"]} == fwt
    forgetting = {v for k, v in shading.items() if not k.startswith("FWT")}
    assert forgetting and forgetting <= task_colours


def test_a_seed_given_twice_is_one_line_and_exit_2(tmp_path, capsys):
    """The same run under two of the paths given (a sweep and its published copy) would count
    its seed twice in the mean: refused, naming both."""
    from ccfit.cli import main

    write_run(tmp_path / "sweep", "s0", config(), 1.0)
    write_run(tmp_path / "sweep", "s1", config(seed=1), 0.5)
    shutil.copytree(tmp_path / "sweep", tmp_path / "copy")
    shutil.rmtree(tmp_path / "copy" / "s1")
    assert main(["report", str(tmp_path / "sweep"), str(tmp_path / "copy"),
                 "--out", str(tmp_path / "out")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.startswith("ccfit: error: refusing to average seed(s) [0] more than once")
    assert str(tmp_path / "sweep" / "s0") in err and str(tmp_path / "copy" / "s0") in err
    assert err.count("\n") == 1


def test_a_cell_gives_the_ci_and_how_many_seeds_define_the_metric():
    from ccfit.report.plots import metric_cell

    group = {"seeds": [0, 1], "bwt": 75.0, "bwt_lo": 50.0, "bwt_hi": 80.0,
             "bwt_seed_mean": 60.0, "bwt_seed_mean_lo": 55.0, "bwt_seed_mean_hi": 65.0}  # fmt: skip
    assert (
        metric_cell({**group, "bwt_seeds_defined": 1}, "bwt")
        == "75.00 [50.00, 80.00; 1 of 2 seeds]"
    )
    assert metric_cell({**group, "bwt_seeds_defined": 2}, "bwt") == "75.00 [50.00, 80.00]"
    assert metric_cell({**group, "bwt_seeds_defined": 2}, "bwt", "_seed_mean") == (
        "60.00 [55.00, 65.00]"
    )
    undefined = {"seeds": [0, 1], "bwt": None, "bwt_reason": "no task learnt above 0"}
    assert metric_cell(undefined, "bwt") == "n/a (no task learnt above 0)"


def test_bar_whiskers_span_the_ci_of_the_bar_even_where_it_lies_outside_the_seeds_range(
    tmp_path, monkeypatch
):
    """The bar is the seed-averaged curves' metric, which may fall outside the per-seed [min,
    max] (BWT clips each curve's drop at 0 before averaging): the whisker is its bootstrap CI."""
    import matplotlib.pyplot as plt

    from ccfit.report.plots import plot_bars

    group = {"seeds": [0, 1, 2], "track": "online", "bwt": 0.04, "bwt_min": 0.07,
             "bwt_max": 1.33, "bwt_lo": 0.0, "bwt_hi": 0.9, "fwt": 10.0, "fwt_min": 5.0,
             "fwt_max": 12.0, "fwt_lo": 6.0, "fwt_hi": 11.5}  # fmt: skip
    figures = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    plot_bars({("tdmpc2", SUITE, "packnet", ""): group}, tmp_path)
    (fig,) = figures
    for ax, name in zip(fig.axes, ("bwt", "fwt"), strict=True):
        (bar,) = ax.patches
        assert bar.get_height() == pytest.approx(group[name])
        (whisker,) = [c for c in ax.collections if len(c.get_segments()) == 1]
        (segment,) = whisker.get_segments()
        assert sorted(segment[:, 1]) == pytest.approx([group[f"{name}_lo"], group[f"{name}_hi"]])


def test_publish_with_root_rewrites_the_overview_over_every_published_folder(tmp_path, capsys):
    """`ccfit publish --root`: the overview (orderings, axes, cost) at the root counts the runs
    of every folder published under it, not only the one just published; a root that does not
    hold --out is bad input."""
    from ccfit.cli import main
    from ccfit.report.cost import COST_MD
    from ccfit.report.orderings import ORDERINGS_MD

    write_run(tmp_path / "sweep-ft", "ft-s0", config(), 1.0)
    write_run(tmp_path / "sweep-er", "er-s0", config(method="er"), 0.5)
    results = tmp_path / "results"
    for method in ("ft", "er"):
        argv = ["publish", str(tmp_path / f"sweep-{method}"), "--out", str(results / method),
                "--root", str(results)]  # fmt: skip
        assert main(argv) == 0
    cost = (results / COST_MD).read_text()
    assert f"| tdmpc2 | {SUITE} | er | 1 |" in cost and f"| tdmpc2 | {SUITE} | ft | 1 |" in cost
    assert "| all | | | 2 |" in cost
    rebuilt = tmp_path / "rebuilt"
    write_report([results], rebuilt)
    for name in (ORDERINGS_MD, COST_MD):
        assert (results / name).read_text() == (rebuilt / name).read_text()
    capsys.readouterr()
    argv = ["publish", str(tmp_path / "sweep-ft"), "--out", str(tmp_path / "elsewhere"),
            "--root", str(results)]  # fmt: skip
    assert main(argv) == 2
    assert "does not hold --out" in capsys.readouterr().err
    assert not (tmp_path / "elsewhere").exists()


def test_a_refused_publish_writes_nothing(tmp_path, capsys, monkeypatch):
    """Every refusal comes before the first file is written: a seed the root already holds in
    the same group (published from another folder), a file over the size limit or a damaged
    cost.json (named where it is, not in --out's copy), leaves
    --out unmade and the root as it was; the same folder published again where it was replaces
    its runs rather than counting them twice."""
    from ccfit import publish
    from ccfit.cli import main

    write_run(tmp_path / "sweep", "ft-s0", config(), 1.0)
    write_run(tmp_path / "again", "ft-s0", config(), 1.0)
    results = tmp_path / "results"

    def argv(runs: str, out: Path) -> list[str]:
        return ["publish", str(tmp_path / runs), "--out", str(out), "--root", str(results)]

    assert main(argv("sweep", results / "ft")) == 0
    before = {p: p.read_bytes() for p in results.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(argv("again", results / "ft-again")) == 2
    assert "seed(s) [0] more than once" in capsys.readouterr().err
    monkeypatch.setattr(publish, "MAX_FILE_BYTES", 100)
    assert main(argv("again", results / "small")) == 2
    assert "too large to publish" in capsys.readouterr().err
    monkeypatch.undo()
    cost = tmp_path / "again" / "ft-s0" / "cost.json"
    cost.write_text('{"wall_s": 1')  # the report reads it: refused before any copy
    alone = tmp_path / "alone"  # no root: nothing else refuses it
    assert main(["publish", str(tmp_path / "again"), "--out", str(alone)]) == 2
    assert f"ccfit: error: {cost}: missing or corrupt" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in results.rglob("*") if p.is_file()} == before
    assert not alone.exists()
    assert main(argv("sweep", results / "ft")) == 0


def test_seeds_run_with_and_without_worker_processes_average_as_one_experiment(tmp_path):
    """How a run spreads over processes is not what it computes (`EXECUTION_SETTINGS`): a seed
    run alone with its workers and one run beside others without them are one group; a setting
    of what is computed still splits."""
    alone = {"parallel": "auto", "env_workers": "auto"}
    beside = {"parallel": "off", "env_workers": "0"}
    for seed, execution in ((0, alone), (1, beside)):
        cfg = config(seed=seed)
        cfg["train"] = {**cfg["train"], **execution}
        write_run(tmp_path, f"s{seed}", cfg, 1.0)
    other = config(seed=2)
    other["train"] = {**other["train"], **beside, "steps": 2 * STEPS}
    write_run(tmp_path, "s2-longer", other, 1.0)
    groups = group_runs(find_runs([tmp_path]))
    assert sorted(sorted(r.seed for r in runs) for runs in groups.values()) == [[0, 1], [2]]


def test_a_run_that_records_a_setting_at_its_legacy_value_groups_with_one_made_before_it(tmp_path):
    """A setting added after runs were made (`LEGACY_VALUES`), recorded at its legacy value by a
    newer run, is the same experiment as an older run without it (a 10-seed sweep resumed across
    the commit that added `model.keypoints` split in two); another value still splits."""
    runs = {"before": config(seed=0), "after": config(seed=1), "other": config(seed=2)}
    runs["after"]["train"]["episode_steps"] = 250  # the legacy value: what "before" ran
    runs["other"]["train"]["episode_steps"] = 100
    for name, cfg in runs.items():
        write_run(tmp_path, name, cfg, 1.0)
    groups = group_runs(find_runs([tmp_path]))
    assert {k[3]: sorted(r.path.name for r in v) for k, v in groups.items()} == {
        "": ["after", "before"],
        "train.episode_steps=100": ["other"],
    }


def test_runs_through_two_frozen_encoders_are_two_rows_named_by_their_files(tmp_path):
    # The encoder is an axis (`+frozen-enc` in the backbone's name), so what tells two encoders'
    # runs apart is the file's SHA-256; the row names the file, with the hash's head.
    from ccfit.report.build import group_runs
    from ccfit.report.runs import find_runs

    for name, sha in (("a", "1" * 64), ("b", "2" * 64)):
        write_run(tmp_path, name, config(obs="pixels", encoder=f"frozen:{name}.safetensors",
                                         resolved_encoder_sha256=sha), 1.0)  # fmt: skip
    groups = group_runs(find_runs([tmp_path]))
    assert sorted(k[3] for k in groups) == ["encoder=a.safetensors (11111111)",
                                            "encoder=b.safetensors (22222222)"]  # fmt: skip


def test_pwm_and_tdmpc2_are_compared_only_through_the_same_frozen_encoder(tmp_path):
    # The paper's comparison holds the encoder fixed: with two encoders' runs of each backbone,
    # each encoder's PWM experts meet its own TD-MPC2 FT, never the other's.
    from ccfit.report.build import grouped
    from ccfit.report.orderings import ordering_rows

    for name, sha in (("a", "1" * 64), ("b", "2" * 64)):
        for model, method in (("pwm", "experts"), ("tdmpc2", "ft")):
            top = dict(model=model, method=method, encoder=f"frozen:{name}.safetensors",
                       resolved_encoder_sha256=sha)  # fmt: skip
            write_run(tmp_path, f"{model}-{name}", config(obs="pixels", **top), 1.0)
    _, groups = grouped([tmp_path])
    rows = [row for name, row in ordering_rows(groups) if name.startswith("PWM with experts")]
    assert len(rows) == 2
    for row in rows:
        assert row[1].count("a.safetensors") in (0, 2) and row[1].count("b.safetensors") in (0, 2)
