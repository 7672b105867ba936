"""`ccfit publish` copies no path of the machine that made the runs (`ccfit.portable`): runs made
under an absolute folder, seeded from a dataset under the LeRobot home, through a frozen
encoder file elsewhere, are published with those paths relative or by name, and the copy reads
back as the original does (the same report, the same settings to `ccfit compare`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from ccfit.cli import main
from ccfit.compare import compare_runs
from ccfit.metrics import compute_metrics
from ccfit.portable import portable_json, portable_str
from ccfit.report import group_runs, write_report
from ccfit.report.runs import find_runs

TASKS, STEPS = 3, 100


def lerobot_home() -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME)


def write_curriculum(root: Path, name: str, method: str, seed: int, encoder: Path) -> Path:
    """A finished curriculum in a sweep's layout (its reference in `root/scratch`), whose
    files name the paths of the machine that made it, written as a run writes them."""
    run, scratch = root / name, root / "scratch" / f"Reach-s{seed}-ref"
    run.mkdir(parents=True)
    records = []
    for t in range(TASKS):
        for i in range((TASKS - t) * 2 + 1):
            step = t * STEPS + 50 * i
            score = min(80.0, 40.0 * i) * (1.0 - 0.1 * seed) - (10.0 * t if i > 2 else 0.0)
            records.append({"global_step": step, "normalized_return": score,
                            "stage": max(t, (step - 1) // STEPS), "task_index": t})  # fmt: skip
    reference = [{"global_step": 50 * i, "normalized_return": 30.0 * i,
                  "task_index": TASKS - 1} for i in range(3)]  # fmt: skip
    config = {"encoder": f"frozen:{encoder}", "method": {"type": method}, "model": "tdmpc2",
              "obs": "pixels", "out": str(run), "preset": "smoke",
              "resolved_encoder_sha256": "ab" * 32,
              "resolved_seed_dataset": str(lerobot_home() / "ccdata" / "Reach"),
              "seed": seed, "seed_dataset": "auto", "suite": "Reach",
              "train": {"seed": seed, "steps": STEPS}}  # fmt: skip
    if not scratch.exists():
        scratch.mkdir(parents=True)
        (scratch / "done.json").write_text(json.dumps(reference))
        write_json(scratch / "config.json", {**config, "out": str(scratch)})
    metrics = compute_metrics(records, reference, TASKS, STEPS)
    write_json(run / "config.json", config)
    write_json(run / "metrics.json", {**metrics, "scratch_dir": str(scratch)})
    (run / "metrics.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n"
                                               for r in records))  # fmt: skip
    return run


def write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")


def write_task_run(root: Path, name: str) -> Path:
    """A finished `ccfit train` run made with an absolute `--out`."""
    run = root / name
    run.mkdir(parents=True)
    write_json(run / "config.json", {
        "model": {"type": "tdmpc2"}, "obs": "state", "out": str(run), "preset": "cpu",
        "resolved_seed_dataset": str(lerobot_home() / "ccdata" / "Reach"), "seed": 0,
        "seed_dataset": "auto", "task": "reach-xy",
        "train": {"buffer_capacity": 1000, "demo_fraction": 0.0, "eval_interval": 1000,
                  "steps": 2000}})  # fmt: skip
    (run / "metrics.jsonl").write_text("".join(
        json.dumps({"normalized_return": s, "task_step": 1000 * i}) + "\n"
        for i, s in enumerate([0.0, 60.0, 90.0])))  # fmt: skip
    write_json(run / "cost.json", {"cpu_s": 7200.0, "segments": 1, "wall_s": 10.0})
    return run


@pytest.fixture
def machine(tmp_path: Path) -> Path:
    """A machine's run folders under an absolute path: a sweep of two methods by two seeds
    through an encoder kept outside it, with its sweep.json, and a single-task run."""
    where = tmp_path / "machine"
    encoder = where / "encoders" / "enc-s0.safetensors"
    sweep = where / "sweep"
    runs = [write_curriculum(sweep, f"{method}-s{seed}", method, seed, encoder)
            for method in ("ft", "er") for seed in (0, 1)]  # fmt: skip
    code = {"commit": "abc1234" + "0" * 33, "git": "abc1234", "source": str(where / "code")}
    write_json(sweep / "sweep.json", {
        "code": code, "grid": {"args": ["--encoder", f"frozen:{encoder}"]},
        "runs": [{"config": json.loads((r / "config.json").read_text()), "dir": r.name,
                  "name": r.name} for r in runs],
        "submissions": [{"code": code, "jobs": {}}], "version": 1})  # fmt: skip
    write_task_run(where / "learn", "tdmpc2-reach-xy-s0")
    return where


def test_published_files_hold_no_path_of_the_machine_that_made_them(machine, tmp_path,
                                                                    monkeypatch):  # fmt: skip
    monkeypatch.chdir(tmp_path)  # published as the project does: `--out results/...`
    results = Path("results")
    assert main(["publish", str(machine / "sweep"), "--out", str(results / "sweep"),
                 "--root", str(results)]) == 0  # fmt: skip
    assert main(["publish", str(machine / "learn"), "--out", str(results / "single-task")]) == 0
    # the same seeds published again beside them are the same runs (configs compared as
    # published): refused, not averaged as another group
    again = results / "again"
    assert main(["publish", str(machine / "sweep"), "--out", str(again), "--root", "results"]) == 2
    assert not again.exists()
    files = [p for p in results.rglob("*") if p.is_file() and p.suffix != ".png"]
    assert {p.name for p in files} >= {"config.json", "metrics.json", "metrics.jsonl",
                                       "done.json", "sweep.json", "learnability.md"}  # fmt: skip
    machine_paths = (str(tmp_path), str(lerobot_home()))
    leaked = [str(p) for p in files if any(m in p.read_text() for m in machine_paths)]
    assert not leaked, f"published files naming a path of the machine: {leaked}"

    run = results / "sweep" / "ft-s0"
    config = json.loads((run / "config.json").read_text())
    assert config["out"] == "ft-s0"  # where it was made, relative to the folder published
    assert config["resolved_seed_dataset"] == "ccdata/Reach"  # under the LeRobot home
    assert config["encoder"] == "frozen:enc-s0.safetensors"  # outside it: by name
    assert json.loads((run / "metrics.json").read_text())["scratch_dir"] == "scratch/Reach-s0-ref"
    assert json.loads((results / "sweep" / "scratch" / "Reach-s0-ref" / "config.json")
                      .read_text())["out"] == "scratch/Reach-s0-ref"  # fmt: skip
    sweep = json.loads((results / "sweep" / "sweep.json").read_text())
    assert sweep["code"]["source"] == "code" and sweep["runs"][0]["config"]["out"] == "ft-s0"
    assert sweep["grid"]["args"] == ["--encoder", "frozen:enc-s0.safetensors"]
    task = json.loads((results / "single-task" / "tdmpc2-reach-xy-s0" / "config.json").read_text())
    assert task["out"] == "tdmpc2-reach-xy-s0" and task["resolved_seed_dataset"] == "ccdata/Reach"
    # only the paths changed: the rest of each file is the original's, byte for byte
    original = (machine / "sweep" / "ft-s0" / "metrics.json").read_text()
    assert (run / "metrics.json").read_text() == original.replace(
        str(machine / "sweep") + "/", "")  # fmt: skip
    assert (run / "metrics.jsonl").read_bytes() == (
        machine / "sweep" / "ft-s0" / "metrics.jsonl").read_bytes()  # fmt: skip

    # read back as the original: the same groups, the same tables, the same settings
    shutil.rmtree(machine / "sweep" / "scratch")  # the copy reads its own references
    shutil.copytree(results / "sweep" / "scratch", machine / "sweep" / "scratch")
    assert [(k, sorted(r.path.name for r in g)) for k, g in
            group_runs(find_runs([machine / "sweep"])).items()] == [
        (k, sorted(r.path.name for r in g)) for k, g in
        group_runs(find_runs([results / "sweep"])).items()]  # fmt: skip
    write_report([machine / "sweep"], tmp_path / "original")
    write_report([results / "sweep"], tmp_path / "published")
    names = sorted(p.name for p in (tmp_path / "original").iterdir()
                   if p.suffix in (".md", ".csv"))  # fmt: skip
    assert any(n.startswith("table_") for n in names)
    for name in names:
        assert (tmp_path / "published" / name).read_bytes() == (
            tmp_path / "original" / name).read_bytes(), name  # fmt: skip
    comparison = compare_runs(machine / "sweep" / "ft-s0", run)
    assert comparison.settings == {} and comparison.reproduces


def test_a_published_config_read_back_still_asks_for_the_dataset_it_was_seeded_from(tmp_path):
    """`--config_path` of a published run whose `--seed_dataset auto` had found the suite's
    dataset (recorded as `ccdata/Reach`, under the LeRobot home): where there is none, one line
    says so and names where it was, as for the run's own config.json."""
    from ccdata.errors import InputError
    from ccfit.config import TaskRunConfig
    from ccfit.config_parse import parse_cli
    from ccfit.train.run import check_seed_dataset_as_run

    published = write_task_run(tmp_path, "tdmpc2-reach-xy-s0") / "config.json"
    saved = json.loads(portable_json(published.read_text(), [tmp_path]))
    assert saved["resolved_seed_dataset"] == "ccdata/Reach"
    assert not (lerobot_home() / "ccdata" / "Reach").exists()
    cfg = parse_cli(TaskRunConfig, ["--task", "reach-xy", "--preset", "smoke"])
    with pytest.raises(InputError, match=r"which is not here \(it was at ccdata/Reach\)"):
        check_seed_dataset_as_run(cfg, "Reach", saved, published)


def test_a_path_is_rewritten_only_where_it_is_absolute():
    root = "/data/sweep"
    assert portable_str("/data/sweep/a/b", [root]) == "a/b"
    assert portable_str("/data/sweep", [root]) == "."
    assert portable_str("frozen:/elsewhere/enc.safetensors", [root]) == "frozen:enc.safetensors"
    assert portable_str("/u/.cache/huggingface/lerobot/ccdata/Grasp") == "ccdata/Grasp"
    assert portable_str("ImportError: /tmp/x/y.so: bad") == "ImportError: y.so: bad"
    for kept in ("https://huggingface.co/ccdata/Reach", "runs/a/b", "../runs/x", "~/x/y",
                 "1/2", "N/A", "/alone", "a / b"):  # fmt: skip
        assert portable_str(kept, [root]) == kept
    text = '{\n  "a": "/data/sweep/x",\n  "n": 1.0000000000000002, "é": "/q/r/\\u00e9"\n}\n'
    assert portable_json(text, [root]) == (
        '{\n  "a": "x",\n  "n": 1.0000000000000002, "é": "\\u00e9"\n}\n'
    )
