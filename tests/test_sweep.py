"""`ccfit sweep` without SLURM: grid expansion, sweep.json, the local launcher, status, errors.

Runs use the toy world model of test_seam.py (`--plugins test_seam` imports it in every job:
pytest puts tests/ on sys.path and spawned workers inherit it), on Reach at tiny budgets.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from ccdata.errors import InputError
from ccfit.branch import stage_path
from ccfit.cli import main
from ccfit.config_base import ConfigError
from ccfit.continual.er import ExperienceReplay
from ccfit.sweep.cli import EXIT_RUNS_MISSING
from ccfit.sweep.grid import (
    Grid,
    check_same_sweep,
    expand,
    import_plugins,
    load_sweep,
    write_record,
)
from ccfit.sweep.jobs import RunJob, ScratchMissing, config_from_dict, write_status
from ccfit.sweep.launch import plan_work
from ccfit.sweep.status import hours_to_go, sweep_status

try:
    from process_tree import PROC, ended, workers
except ImportError:  # tests/ imported as a package
    from tests.process_tree import PROC, ended, workers

TOY_RUN = ("--seed_dataset", "null", "--train.steps=100", "--train.seed_steps=50",
           "--train.eval_interval=100", "--train.checkpoint_interval=100")  # fmt: skip
TOY = ["--models", "toy", "--plugins", "test_seam", "--preset", "smoke", *TOY_RUN]
RUN_ARGS = ("--seed_dataset", "null", "--train.steps=200", "--train.eval_interval=100")


def sweep_cli(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["sweep", *args])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(code: int, err: str) -> str:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_grid_expands_into_resolved_run_configs(tmp_path):
    grid = Grid(("Reach", "Grasp"), ("toy",), ("ft", "er", "ewc"), (0, 1), "smoke", RUN_ARGS,
                ("test_seam",))  # fmt: skip
    root = tmp_path / "runs"
    sweep = expand(grid, root)
    assert len(sweep.runs) == 2 * 3 * 2
    names = [r.name for r in sweep.runs]
    assert len(set(names)) == len(names)
    assert "Grasp-toy-ewc-state-smoke-s1" in names
    points = set()
    for run in sweep.runs:
        cfg = config_from_dict(run.config)
        points.add((cfg.suite, cfg.method.type, cfg.seed))
        assert run.name == f"{cfg.suite}-toy-{cfg.method.type}-state-smoke-s{cfg.seed}"
        assert cfg.out == str(root.resolve() / run.name)
        # the common options reach every run; the rest is the smoke preset's
        assert (cfg.train.steps, cfg.train.eval_interval, cfg.seed_dataset) == (200, 100, None)
        assert cfg.train.seed_steps == 300 and cfg.model.type == "toy"
    assert points == set(itertools.product(("Reach", "Grasp"), ("ft", "er", "ewc"), (0, 1)))
    # one from-scratch reference per (suite, seed): methods share it
    keys = {}
    for run in sweep.runs:
        keys.setdefault((run.config["suite"], run.config["seed"]), set()).add(run.scratch_key)
    assert all(len(k) == 1 for k in keys.values())
    assert len(set.union(*keys.values())) == 4


def test_an_option_of_some_methods_or_models_goes_to_the_points_having_it(tmp_path):
    # --method.retrain_steps is PackNet's, --method.lam EWC's, --model.critic_replay_scale
    # DreamerV3's: runs of the other methods and models would refuse them
    args = (*RUN_ARGS, "--method.retrain_steps", "77", "--method.lam=10",
            "--model.critic_replay_scale=0.3", "--train.seed_steps=60")  # fmt: skip
    grid = Grid(("Reach",), ("tdmpc2", "dreamerv3"), ("ft", "packnet", "ewc"), (0,), "smoke",
                args)  # fmt: skip
    sweep = expand(grid, tmp_path)
    for run in sweep.runs:
        cfg = config_from_dict(run.config)
        assert cfg.train.seed_steps == 60  # options of the run itself reach every run
        assert getattr(cfg.method, "retrain_steps", 77) == 77
        assert getattr(cfg.method, "lam", 10) == 10
        assert getattr(cfg.model, "critic_replay_scale", 0.3) == 0.3
    kinds = {(r.config["model"]["type"], r.config["method"]["type"]) for r in sweep.runs}
    assert len(kinds) == 6
    # the methods without the field share the from-scratch reference of those with it
    assert len({r.scratch_key for r in sweep.runs}) == 2
    # a field no method of the grid has is still an unknown option
    with pytest.raises(ConfigError, match="retrain_steps"):
        expand(Grid(("Reach",), ("tdmpc2",), ("ft", "er"), (0,), "smoke",
                    (*RUN_ARGS, "--method.retrain_steps=5")), tmp_path / "b")  # fmt: skip


def test_grid_refuses_options_it_sets_and_repeated_values():
    with pytest.raises(InputError, match="--seed is set by the sweep grid; use --seeds"):
        Grid(("Reach",), ("toy",), ("ft",), (0,), args=("--seed=3",))
    with pytest.raises(InputError, match="use --methods"):
        Grid(("Reach",), ("toy",), ("ft",), (0,), args=("--method.type", "er"))
    with pytest.raises(InputError, match="--seeds lists 1 more than once"):
        Grid(("Reach",), ("toy",), ("ft",), (1, 1))


def test_sweep_json_is_written_atomically_and_read_back(tmp_path):
    grid = Grid(("Reach",), ("toy",), ("ft", "er"), (0,), "smoke", RUN_ARGS, ("test_seam",))
    sweep = expand(grid, tmp_path)
    write_record(sweep, [{"launcher": "slurm", "jobs": {"report": "7"}}])
    again, record = load_sweep(tmp_path)
    assert again.identity() == sweep.identity() and again.grid == grid
    assert [r.scratch_key for r in again.runs] == [r.scratch_key for r in sweep.runs]
    assert record["submissions"] == [{"launcher": "slurm", "jobs": {"report": "7"}}]
    assert record["code"]["package"] == sweep.code["package"]
    before = (tmp_path / "sweep.json").read_text()
    with pytest.raises(TypeError):  # a write that fails half-way leaves the old record
        write_record(sweep, [{"launcher": "local", "jobs": {"x": object()}}])
    assert (tmp_path / "sweep.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.json"]


def test_a_folder_holding_another_sweep_is_refused(tmp_path, capsys):
    import_plugins(["test_seam"])
    args = ["--suites", "Reach", "--methods", "ft", "--out", str(tmp_path), *TOY]
    write_record(expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", TOY_RUN,
                             ("test_seam",)), tmp_path), [])  # fmt: skip
    code, out, err = sweep_cli(capsys, *args, "--dry-run")
    assert code == 0, err
    code, _, err = sweep_cli(capsys, *args[:-1], "--train.checkpoint_interval=50")
    line = one_line_error(code, err)
    assert "holds a different sweep" in line and "train.checkpoint_interval is 50, was 100" in line
    code, _, err = sweep_cli(capsys, *args, "--methods", "ft,er")
    assert "new runs Reach-toy-er-state-smoke-s0" in one_line_error(code, err)


def test_a_sweep_grows_by_seeds_in_its_own_folder(tmp_path, capsys):
    # 3 seeds become 5 where the first 3 ran; other new runs, or fewer seeds, stay refused.
    import_plugins(["test_seam"])
    args = ["--suites", "Reach", "--methods", "ft", "--out", str(tmp_path), *TOY]
    write_record(expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", TOY_RUN,
                             ("test_seam",)), tmp_path), [])  # fmt: skip
    code, out, err = sweep_cli(capsys, *args, "--seeds", "0,1,2", "--dry-run")
    assert code == 0, err
    assert f"adding seeds 1, 2 to the sweep in {tmp_path.resolve()}" in err
    assert "3 runs, 0 finished" in out
    code, _, err = sweep_cli(capsys, *args, "--seeds", "1")
    assert "missing runs Reach-toy-ft-state-smoke-s0" in one_line_error(code, err)
    code, _, err = sweep_cli(capsys, *args, "--seeds", "0,1", "--methods", "ft,er")
    assert "new runs Reach-toy-er-state-smoke-s0" in one_line_error(code, err)
    code, _, err = sweep_cli(capsys, *args, "--seeds", "0,1", "--train.checkpoint_interval=50")
    assert "train.checkpoint_interval is 50, was 100" in one_line_error(code, err)


def test_a_sweep_written_before_a_setting_existed_is_the_same_sweep(tmp_path):
    """sweep.json of an older version lacks `train.demo_fraction`: at its legacy value the
    runs, and their from-scratch keys, are the same."""
    from ccfit.curriculum import OnlineTrack
    from ccfit.sweep.grid import check_same_sweep
    from ccfit.sweep.jobs import config_from_dict

    sweep = expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",)),
                   tmp_path)  # fmt: skip
    record = json.loads(json.dumps(sweep.record()))
    for run in record["runs"]:
        assert run["config"]["train"].pop("demo_fraction") == 0.0
    check_same_sweep(sweep, record)
    old = config_from_dict(record["runs"][0]["config"])
    assert OnlineTrack(old).reference_key() == sweep.runs[0].scratch_key
    record["runs"][0]["config"]["train"]["demo_fraction"] = 0.25
    with pytest.raises(InputError, match="train.demo_fraction is 0.0, was 0.25"):
        check_same_sweep(sweep, record)


def test_planning_a_sweep_reads_no_dataset(tmp_path):
    # The from-scratch key leaves out what the seed dataset holds, so planning never reads
    # it: a Hub dataset is fetched by the jobs that train, not by the login node that plans
    # (here no copy is cached and the endpoint refuses connections: reading it would be an
    # InputError).
    args = ("--seed_dataset", "nobody/absent", "--dataset_endpoint", "http://127.0.0.1:9",
            *RUN_ARGS[2:])  # fmt: skip
    grid = Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", args, ("test_seam",))
    (run,) = expand(grid, tmp_path).runs
    assert run.config["seed_dataset"] == "nobody/absent" and run.scratch_key


def test_check_same_sweep_ignores_where_runs_are_stored(tmp_path):
    grid = Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",))
    a, b = expand(grid, tmp_path / "a"), expand(grid, tmp_path / "b")
    check_same_sweep(b, a.record())  # the folder moved: the same sweep


def test_a_sweep_resumed_with_other_process_or_logging_settings_is_the_same_sweep(tmp_path):
    # What a run may change when it resumes (`config_base.NOT_IDENTITY`), its sweep may too:
    # resuming with --train.parallel=off was refused as 'a different sweep'.
    grid = Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",))
    before = expand(grid, tmp_path)
    resumed = dataclasses.replace(grid, args=(*RUN_ARGS, "--train.parallel=off",
                                              "--log.tensorboard=false"))  # fmt: skip
    check_same_sweep(expand(resumed, tmp_path), before.record())
    other = dataclasses.replace(grid, args=(*RUN_ARGS, "--train.eval_episodes=3"))
    with pytest.raises(InputError, match="holds a different sweep"):
        check_same_sweep(expand(other, tmp_path), before.record())


@pytest.mark.parametrize("bad,expected", [
    (["--suites", "Nope"], "unknown suite"),
    (["--suites", "Reach", "--methods", "ft,nope"], "nope"),
    (["--suites", "Reach", "--models", "nope"], "nope"),
    (["--suites", "Reach", "--seeds", "0,x"], "argument --seeds: expected integers"),
])  # fmt: skip
def test_bad_names_end_with_one_line(tmp_path, capsys, bad, expected):
    code, _, err = sweep_cli(capsys, *bad, "--out", str(tmp_path / "r"), "--plugins", "test_seam")
    assert expected in one_line_error(code, err)
    assert not (tmp_path / "r").exists()


def test_dry_run_writes_nothing(tmp_path, capsys):
    out_dir = tmp_path / "runs"
    code, out, err = sweep_cli(capsys, "--suites", "Reach,Grasp", "--methods", "ft,er", "--out",
                               str(out_dir), "--dry-run", *TOY)  # fmt: skip
    assert code == 0, err
    assert not out_dir.exists()
    assert ("would run: 2 from-scratch references, 2 shared first tasks, 4 runs, then the "
            "report") in out  # fmt: skip
    assert "  Grasp-toy-er-state-smoke-s0" in out
    code, out, err = sweep_cli(capsys, "--suites", "Reach", "--methods", "ft,er", "--out",
                               str(out_dir), "--dry-run", "--no-share-first-task",
                               *TOY)  # fmt: skip
    assert code == 0 and "would run: 1 from-scratch references, 2 runs, then" in out, err


def test_the_plan_shares_a_first_task_where_runs_would_start_from_it(tmp_path, monkeypatch):
    grid = Grid(("Reach",), ("toy",), ("ft", "ewc", "er"), (0, 1), "smoke", RUN_ARGS,
                ("test_seam",))  # fmt: skip
    sweep = expand(grid, tmp_path)
    keys = list(dict.fromkeys(r.scratch_key for r in sweep.runs))
    work = plan_work(sweep, {}, share_first_task=True)
    assert list(work.first) == keys  # one per seed, in the grid's order
    assert not plan_work(sweep, {}, share_first_task=False).first
    # a seed whose sharing runs began (a task checkpoint) or whose first task is done: none;
    # runs of a method that does not share it (ER, made to) need none
    monkeypatch.setattr(ExperienceReplay, "shares_first_task", False)
    began = [r for r in sweep.runs if r.scratch_key == keys[0] and r.config["method"]["type"]
             in ("ft", "ewc")]  # fmt: skip
    for run in began:
        (sweep.run_dir(run) / "tasks" / "0-reach-xy").mkdir(parents=True)
        (sweep.run_dir(run) / "tasks" / "0-reach-xy" / "checkpoint.pt").write_bytes(b"")
    (sweep.first_dir(keys[1])).mkdir(parents=True)
    assert list(plan_work(sweep, {}, share_first_task=True).first) == [keys[1]]
    (sweep.first_dir(keys[1]) / "first.json").write_text("{}")
    assert not plan_work(sweep, {}, share_first_task=True).first
    # one queued by an earlier submission is not planned again
    shutil.rmtree(sweep.first_dir(keys[1]))
    assert not plan_work(sweep, {f"first:{keys[1]}": "7"}, share_first_task=True).first


def test_slurm_launcher_without_sbatch_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    code, _, err = sweep_cli(capsys, "--suites", "Reach", "--out", str(tmp_path / "r"),
                             "--launcher", "slurm", *TOY)  # fmt: skip
    assert "no SLURM reachable: sbatch is not on PATH" in one_line_error(code, err)
    assert not (tmp_path / "r").exists()


def test_slurm_time_limit_below_30_minutes_is_refused(tmp_path, capsys):
    code, _, err = sweep_cli(capsys, "--suites", "Reach", "--out", str(tmp_path / "r"),
                             "--launcher", "slurm", "--time", "0:20:00", *TOY)  # fmt: skip
    assert "--time must be at least 30 minutes" in one_line_error(code, err)


def test_a_run_without_its_reference_does_not_start(tmp_path):
    sweep = expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",)),
                   tmp_path)  # fmt: skip
    run = sweep.runs[0]
    with pytest.raises(ScratchMissing, match="did not finish"):
        RunJob()(run.config, str(sweep.run_dir(run)), str(tmp_path / "scratch"), run.scratch_key,
                 ["test_seam"], sweep.code)  # fmt: skip
    assert not sweep.run_dir(run).exists()


@pytest.mark.integration
def test_keep_stages_reaches_every_run_of_a_sweep(tmp_path, capsys):
    root = tmp_path / "runs"
    code, _, err = sweep_cli(capsys, "--suites", "Reach", "--methods", "ft", "--seeds", "0",
                             "--out", str(root), "--max-parallel", "1", "--keep-stages",
                             *TOY)  # fmt: skip
    assert code == 0, err
    sweep, _ = load_sweep(root)
    [run] = sweep.runs
    tasks = len(json.loads((sweep.run_dir(run) / "metrics.json").read_text())["end_of_task"])
    kept = sorted(p.name for p in (sweep.run_dir(run) / "stages").iterdir())
    assert kept == [stage_path(sweep.run_dir(run), k).name for k in range(1, tasks + 1)]
    # the sweep's references keep nothing: nothing branches from them
    assert not list((root / "scratch").rglob("after-*.pt"))


def test_keep_stages_is_refused_on_the_offline_track(tmp_path, capsys):
    code, _, err = sweep_cli(capsys, "--track", "offline", "--suites", "Reach", "--out",
                             str(tmp_path / "r"), "--keep-stages", *TOY)  # fmt: skip
    assert "the offline track has none to branch from" in one_line_error(code, err)
    assert not (tmp_path / "r").exists()


def _mtimes(paths) -> list[int]:
    return [p.stat().st_mtime_ns for p in paths]


@pytest.mark.slow  # ~50 s; in CI the SLURM smoke sweep runs the same grid end to end
def test_local_sweep_trains_once_and_resubmits_only_unfinished_work(tmp_path, capsys):
    root = tmp_path / "runs"
    args = ["--suites", "Reach", "--methods", "ft,er", "--seeds", "0", "--out", str(root),
            "--max-parallel", "2", *TOY]  # fmt: skip
    code, out, err = sweep_cli(capsys, *args)
    assert code == 0, err
    sweep, record = load_sweep(root)
    [first] = record["submissions"]
    jobs = first["jobs"]
    scratch = [n for n in jobs if n.startswith("scratch:")]
    assert len(scratch) == 1 and all(j["state"] == "COMPLETED" for j in jobs.values())
    # the shared reference was trained once, before either run started
    runs = [f"run:{r.name}" for r in sweep.runs]
    assert all(jobs[scratch[0]]["end"] <= jobs[r]["start"] for r in runs)
    metrics = [sweep.run_dir(r) / "metrics.json" for r in sweep.runs]
    done = sweep.scratch_dir(sweep.runs[0].scratch_key) / "done.json"
    results = [json.loads(p.read_text()) for p in metrics]
    assert [m["method"] for m in results] == ["ft", "er"]
    assert all(m["scratch_dir"] == str(done.parent) for m in results)
    status = json.loads((root / "report" / "status.json").read_text())
    assert sorted(status["done"]) == sorted(r.name for r in sweep.runs) and not status["missing"]
    assert "table_toy.md" in status["report"] and (root / "report" / "table_toy.md").is_file()

    # the same command again: nothing to do, nothing touched
    stamps = _mtimes([*metrics, done, root / "report" / "status.json"])
    code, out, err = sweep_cli(capsys, *args)
    assert code == 0, err
    assert "nothing to submit" in out and "2 finished" in out
    assert len(load_sweep(root)[1]["submissions"]) == 1
    assert _mtimes([*metrics, done, root / "report" / "status.json"]) == stamps

    # a lost run: the report lists it; the command again trains only that run, identically
    lost = sweep.runs[1]
    (sweep.run_dir(lost) / "metrics.json").rename(tmp_path / "er-metrics.json")
    shutil.rmtree(sweep.run_dir(lost))
    status = write_status(root, {})
    assert status["missing"] == [{"name": lost.name, "started": False, "error": None}]
    lost_states = sweep_status(root)
    assert lost_states[f"run:{lost.name}"]["state"] == "failed"  # recorded done, gone
    assert lost_states["report"] == {"state": "done", "job": lost_states["report"]["job"],
                                     "detail": "lists 1 of 2 runs missing"}  # fmt: skip
    assert [r.name for r in plan_work(sweep, {}).runs] == [lost.name]
    code, out, err = sweep_cli(capsys, *args)
    assert code == 0, err
    second = load_sweep(root)[1]["submissions"][1]["jobs"]
    assert sorted(second) == ["report", f"run:{lost.name}"]
    assert _mtimes([metrics[0], done]) == stamps[:1] + stamps[2:3]
    again = json.loads(metrics[1].read_text())
    assert again == json.loads((tmp_path / "er-metrics.json").read_text())

    states = sweep_status(root)
    assert {s["state"] for s in states.values()} == {"done"}
    assert states["report"]["detail"] == ""
    code, out, _ = sweep_cli(capsys, "--status", str(root))
    assert code == 0 and out.endswith("0 pending, 0 running, 5 done, 0 failed, 0 not submitted\n")

    # grown by a seed in its folder: only the new seed's reference and runs train
    stamps = _mtimes([*metrics, done])
    grown = [*args[:5], "0,1", *args[6:]]
    code, out, err = sweep_cli(capsys, *grown)
    assert code == 0, err
    assert "adding seeds 1 to the sweep" in err
    sweep, record = load_sweep(root)
    assert record["grid"]["seeds"] == [0, 1] and len(sweep.runs) == 4
    third = record["submissions"][2]["jobs"]
    assert sorted(n for n in third if n.startswith("run:")) == sorted(
        f"run:{r.name}" for r in sweep.runs if r.config["seed"] == 1
    )
    assert _mtimes([*metrics, done]) == stamps


@pytest.mark.integration
def test_a_local_sweep_finishes_seed_after_seed(tmp_path, capsys):
    """One job at a time, the jobs start seed-major, each shared first task and reference just
    before their runs: stopped at any point, the sweep holds every method of the seeds it
    finished."""
    root = tmp_path / "runs"
    code, _, err = sweep_cli(
        capsys,
        "--suites",
        "Reach",
        "--methods",
        "ft,er",
        "--seeds",
        "0,1",
        "--out",
        str(root),
        "--max-parallel",
        "1",
        *TOY,
    )
    assert code == 0, err
    sweep, record = load_sweep(root)
    jobs = record["submissions"][0]["jobs"]
    started = sorted((j["start"], i, n) for i, (n, j) in enumerate(jobs.items()) if "start" in j)
    order = [
        n.split(":")[0]
        + ":"
        + ("s0" if "-s0" in n else "s1")
        + (":" + n.split("-")[2] if n.startswith("run:") else "")
        for _, _, n in started
    ]
    assert order[:8] == ["first:s0", "scratch:s0", "run:s0:ft", "run:s0:er", "first:s1",
                         "scratch:s1", "run:s1:ft", "run:s1:er"]  # fmt: skip
    # Each reference's job recorded what it cost, and the report counts the two once.
    from ccfit.train.cost import read_cost

    for key in {r.scratch_key for r in sweep.runs}:
        assert read_cost(sweep.scratch_dir(key))["segments"] == 1
    assert "| toy | Reach | 2 |" in (root / "report" / "cost.md").read_text()


def test_status_reads_an_abandoned_local_record_as_interrupted(tmp_path):
    sweep = expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",)),
                   tmp_path)  # fmt: skip
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    name = f"run:{sweep.runs[0].name}"
    write_record(
        sweep,
        [
            {
                "launcher": "local",
                "pid": gone.pid,
                "jobs": {
                    name: {"state": "RUNNING"},
                    f"scratch:{sweep.runs[0].scratch_key}": {"state": "FAILED", "error": "boom"},
                },
            }
        ],
    )
    status = sweep_status(tmp_path)
    assert status[name] == {"state": "failed", "job": f"local:{gone.pid}", "detail": "interrupted"}
    assert status[f"scratch:{sweep.runs[0].scratch_key}"]["detail"] == "boom"
    assert status["report"]["state"] == "not submitted"
    # a live launcher's record reads as it says
    write_record(
        sweep, [{"launcher": "local", "pid": os.getpid(), "jobs": {name: {"state": "RUNNING"}}}]
    )
    assert sweep_status(tmp_path)[name]["state"] == "running"


def test_status_says_where_an_unfinished_run_is(tmp_path):
    """A running or interrupted run's detail names its last evaluation (task, global step of
    the steps it trains),
    read from the tail of its metrics.jsonl, a cut line skipped; nothing before the first."""
    sweep = expand(Grid(("Reach",), ("toy",), ("ft",), (0,), "smoke", RUN_ARGS, ("test_seam",)),
                   tmp_path)  # fmt: skip
    run = sweep.runs[0]
    name = f"run:{run.name}"
    write_record(
        sweep, [{"launcher": "local", "pid": os.getpid(), "jobs": {name: {"state": "RUNNING"}}}]
    )
    assert sweep_status(tmp_path)[name]["detail"] == ""
    sweep.run_dir(run).mkdir(parents=True)
    records = [
        {"task": t, "global_step": 5 * i} for i, t in enumerate(["reach-xy"] * 120 + ["reach-xz"])
    ]
    text = "".join(json.dumps(r) + "\n" for r in records) + '{"task": "reach-xz", "glo'
    (sweep.run_dir(run) / "metrics.jsonl").write_text(text)  # longer than the tail read
    assert sweep_status(tmp_path)[name] == {
        "state": "running",
        "job": f"local:{os.getpid()}",
        "detail": "last evaluated reach-xz at global step 600 of 800",
    }  # 200 x 4 tasks
    cost = sweep.run_dir(run) / "cost.json"
    cost.write_text(json.dumps({"wall_s": 7000.0, "cpu_s": 5400.0, "segments": 2}))
    assert sweep_status(tmp_path)[name]["detail"] == (
        "last evaluated reach-xz at global step 600 of 800; "
        "1.5 CPU-hours so far, about 0.5 to go"  # 9 CPU-s per step, 200 steps left
    )
    cost.write_text('{"wall_s": 7000.0, "cpu_')  # damaged: bad input, named
    with pytest.raises(InputError, match="cost.json"):
        sweep_status(tmp_path)


def test_status_adds_up_the_cpu_hours_to_go(tmp_path, capsys):
    """The sweep's total: a started run at its own rate, one not started at its kind's median
    rate, a reference's rate never lent to a curriculum, a finished unit counted nowhere."""
    sweep = expand(Grid(("Reach",), ("toy",), ("ft", "er"), (0,), "smoke", RUN_ARGS,
                        ("test_seam",)), tmp_path)  # fmt: skip
    (reference,) = sweep.scratch_configs()
    ft, er = sweep.runs
    write_record(sweep, [])
    assert hours_to_go(tmp_path) == ""  # nothing has a rate yet

    def cost(directory, cpu_s):
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "cost.json").write_text(json.dumps({"wall_s": cpu_s, "cpu_s": cpu_s}))

    cost(sweep.scratch_dir(reference), 720.0)  # 200 steps, done: 3.6 CPU-s per step
    (sweep.scratch_dir(reference) / "done.json").write_text("{}")
    assert hours_to_go(tmp_path) == (
        "about 0.0 CPU-hours to go (2 not counted: no rate of their kind yet)"
    )
    cost(sweep.run_dir(ft), 5400.0)  # 9 CPU-s per step to step 600 of 800
    (sweep.run_dir(ft) / "metrics.jsonl").write_text(
        json.dumps({"task": "reach-xz", "global_step": 600}) + "\n"
    )
    # ft: 200 steps x 9 s; er: 800 steps x 9 s (ft's rate, its kind's only one)
    assert hours_to_go(tmp_path) == (
        "about 2.5 CPU-hours to go (1 without a rate of their own at their kind's median)"
    )
    (sweep.run_dir(ft) / "metrics.json").write_text("{}")  # ft done: er at ft's whole rate
    cost(sweep.run_dir(ft), 7200.0)  # 9 CPU-s per step over its 800
    assert hours_to_go(tmp_path) == (
        "about 2.0 CPU-hours to go (1 without a rate of their own at their kind's median)"
    )
    code, out, _ = sweep_cli(capsys, "--status", str(tmp_path))
    assert code == 0 and out.splitlines()[-1] == hours_to_go(tmp_path)


def test_a_failed_reference_fails_its_runs_unstarted(tmp_path, capsys):
    root = tmp_path / "runs"
    args = ["--suites", "Reach", "--methods", "ft,er", "--out", str(root), *TOY]
    sweep = expand(Grid(("Reach",), ("toy",), ("ft", "er"), (0,), "smoke", TOY_RUN,
                        ("test_seam",)), root)  # fmt: skip
    blocker = sweep.scratch_dir(sweep.runs[0].scratch_key)
    blocker.parent.mkdir(parents=True)
    blocker.write_text("not a directory")  # the reference cannot write its outputs
    code, out, err = sweep_cli(capsys, *args)
    assert code == EXIT_RUNS_MISSING == 1, err  # `ccfit sweep ... && next` stops here
    assert out.count("failed run:") == 2 and "its reference scratch:" in out
    status = json.loads((root / "report" / "status.json").read_text())
    assert status["done"] == [] and [m["started"] for m in status["missing"]] == [False, False]
    assert all("its reference scratch:" in m["error"] for m in status["missing"])
    log = root / "local" / f"scratch-{sweep.runs[0].scratch_key}.err"
    assert "NotADirectoryError" in log.read_text() or "FileExistsError" in log.read_text()
    [entry] = load_sweep(root)[1]["submissions"]
    error = entry["jobs"][f"scratch:{sweep.runs[0].scratch_key}"]["error"]
    assert error.startswith(("NotADirectoryError: ", "FileExistsError: ")), error
    states = sweep_status(root)
    # its shared first task trained: the runs failed for their reference alone
    assert [(n.split(":")[0], s["state"]) for n, s in states.items()] == [
        ("scratch", "failed"), ("first", "done"), ("run", "failed"), ("run", "failed"),
        ("report", "done")]  # fmt: skip
    assert states["report"]["detail"] == "lists 2 of 2 runs missing"
    assert not any(sweep.run_dir(r).exists() for r in sweep.runs)
    (root / "report" / "status.json").write_text('{"done": [], "miss')  # damaged: bad input
    code, _, err = sweep_cli(capsys, "--status", str(root))
    assert "report/status.json is not a sweep's report status" in one_line_error(code, err)


def test_a_config_of_no_track_is_one_line():
    """A sweep.json or config.json that is not a ccfit run's (no `train`, no `fit`) names the
    problem instead of a traceback."""
    from ccfit.tracks import track_of

    assert track_of({"train": {}}).name == "online" and track_of({"fit": {}}).name == "offline"
    for config in ({}, {"train": {}, "fit": {}}):
        with pytest.raises(InputError, match="not a ccfit run's config"):
            track_of(config)


@pytest.mark.skipif(not PROC.is_dir(), reason="reads processes from /proc")
def test_an_interrupted_local_sweep_ends_its_running_jobs_with_it(tmp_path):
    """SIGINT to the launcher alone (`kill -INT`; a terminal's Ctrl-C reaches the workers
    too): the launcher ends at once, its running job killed with it and recorded as
    interrupted, instead of the launcher waiting at exit for that job to end."""
    root = tmp_path / "runs"
    long = [a for a in TOY if not a.startswith("--train.steps=")] + ["--train.steps=10000000"]
    argv = ["sweep", "--suites", "Reach", "--methods", "ft", "--out", str(root), *long]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    launcher = subprocess.Popen([sys.executable, "-m", "ccfit.cli", *argv], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and launcher.poll() is None:
            if any(root.glob("*/*/config.json")):  # a job has begun training
                break
            time.sleep(0.1)
        assert launcher.poll() is None, launcher.stderr.read()[-2000:]
        assert any(root.glob("*/*/config.json")), "no job began in 300 s"
        running = workers(launcher.pid)
        assert running
        os.kill(launcher.pid, signal.SIGINT)
        launcher.wait(timeout=60)  # before: until the 10M-step job ended
    finally:
        launcher.kill()
        launcher.communicate()
    assert all(ended(pid) for pid in running)
    [entry] = load_sweep(root)[1]["submissions"]
    states = {n.split(":")[0]: j["state"] for n, j in entry["jobs"].items()}
    assert "INTERRUPTED" in states.values() and "COMPLETED" not in states.values(), states
