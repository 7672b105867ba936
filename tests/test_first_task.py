"""Runs of one seed share their first task (`ccfit.first_task`).

The contract, over every registered method that says it shares the first task: a run started
from the shared first task equals the run that trained its own, record for record and weight
for weight. A method that does not share it trains its own; the shared task is trained once;
`ccfit sweep` (sharing by default) wires it through."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import ccfit.curriculum as C
from ccdata.errors import InputError
from ccfit.cli import main
from ccfit.config import CurriculumConfig
from ccfit.config_parse import resolve
from ccfit.continual import METHODS, method_names
from ccfit.continual.ft import FineTune
from ccfit.curriculum import Curriculum, OnlineTrack
from ccfit.first_task import FIRST_DONE, FIRST_RECORD, first_task_done, start_from_first_task
from ccfit.run_files import CHECKPOINT
from ccfit.runner import CurriculumRunner
from ccfit.train import METRICS

try:
    from short_episodes import EPISODE_STEPS
except ImportError:  # tests/ imported as a package
    from tests.short_episodes import EPISODE_STEPS

BENCH = Path(__file__).resolve().parents[1] / "bench" / "first_task.py"
SUITE = "Reach"
# 110 steps of 25-step episodes: the first task ends inside an episode, which the shared part
# cuts before its checkpoint.
TRAIN = {"steps": 110, "seed_steps": 50, "eval_interval": 55, "checkpoint_interval": 50,
         "episode_steps": EPISODE_STEPS}  # fmt: skip
SHARING = [m for m in method_names() if METHODS[m].shares_first_task]


def _config(method: str, model: str = "tdmpc2", parallel: str = "off") -> CurriculumConfig:
    return resolve(CurriculumConfig, {
        "suite": SUITE, "preset": "smoke", "seed_dataset": None,
        "train": {**TRAIN, "parallel": parallel}, "method": {"type": method},
        "model": {"type": model},
    })  # fmt: skip


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / METRICS).read_text().splitlines() if x.strip()]


def _shared(first: Path) -> list[Path]:
    """The shared first tasks in `first` (beside their lock files)."""
    return [p for p in first.iterdir() if not p.name.startswith(".")]


def _run(cfg: CurriculumConfig, out: Path, scratch: Path, first: Path | None = None) -> dict:
    track = OnlineTrack(cfg, first_root=first)
    return CurriculumRunner(track, out, scratch, progress=False).run()


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    torch.set_num_threads(1)
    return tmp_path_factory.mktemp("first")


def test_the_methods_that_close_their_first_task_only_share_it():
    assert {"ft", "er", "ewc", "packnet"} <= set(SHARING)
    assert "experts" not in SHARING  # its first task trains group 0's experts alone


# TD-MPC2 under every sharing method in `make test`; evaluation in a worker (requests in
# flight where the shared part stops) and the other models in the integration tier.
CASES = [pytest.param("tdmpc2", m, "off", id=f"tdmpc2-{m}") for m in SHARING] + [
    pytest.param(model, m, parallel, id=f"{model}-{m}-{parallel}", marks=pytest.mark.integration)
    for model, m, parallel in [("tdmpc2", "packnet", "on"), ("tdmpc2", "er", "on"),
                               *(("dreamerv3", m, "off") for m in SHARING), ("pwm", "ft", "off")]
]  # fmt: skip


@pytest.mark.parametrize(("model", "method", "parallel"), CASES)
def test_a_run_from_the_shared_first_task_equals_one_that_trained_its_own(root, model, method,
                                                                         parallel):  # fmt: skip
    cfg = _config(method, model, parallel)
    name = f"{model}-{method}-{parallel}"
    own = _run(cfg, root / f"own-{name}", root / "scratch")
    shared = _run(cfg, root / f"shared-{name}", root / "scratch", first=root / "first")
    assert (root / f"shared-{name}" / FIRST_RECORD).is_file()
    assert not (root / f"own-{name}" / FIRST_RECORD).exists()
    assert _records(root / f"shared-{name}") == _records(root / f"own-{name}")
    assert {k: shared[k] for k in ("bwt", "fwt")} == {k: own[k] for k in ("bwt", "fwt")}
    states = [torch.load(root / f"{kind}-{name}" / C.STATE, map_location="cpu",
                         weights_only=False) for kind in ("own", "shared")]  # fmt: skip
    for key, tensor in states[0]["model"].items():
        assert torch.equal(tensor, states[1]["model"][key]), key


def test_the_shared_first_task_is_trained_once(root):
    first = root / "first"
    runs = [root / f"shared-tdmpc2-{m}-off" for m in SHARING]
    if not all((r / FIRST_RECORD).is_file() for r in runs):  # run alone (-k): make two
        runs = [root / f"once-{m}" for m in ("ft", "ewc")]
        for run in runs:
            _run(_config(run.name.split("-")[1]), run, root / "scratch", first=first)
    (shared,) = [p for p in _shared(first) if "tdmpc2" in p.name]
    done = json.loads((shared / FIRST_DONE).read_text())
    for run in runs:
        record = json.loads((run / FIRST_RECORD).read_text())
        assert record["shared"] == shared.name
        assert record["state_sha256"] == done["state_sha256"]
    # Trained in one segment: a second training would have added its own to cost.json.
    assert json.loads((shared / "cost.json").read_text())["segments"] == 1


def test_a_start_from_it_killed_before_its_checkpoint_starts_again(root):
    first = root / "first"
    if not (first.is_dir() and _shared(first)):  # run alone (-k): make one
        _run(_config("ft"), root / "once-ft", root / "scratch", first=first)
    (shared,) = [p for p in _shared(first) if "tdmpc2" in p.name]
    out = root / "killed"
    folder = out / "tasks" / "0-reach-xy"
    out.mkdir()
    start_from_first_task(shared, out, folder)
    (folder / CHECKPOINT).unlink()  # killed after the records, before the checkpoint
    start_from_first_task(shared, out, folder)
    source = torch.load(shared / "tasks" / "0-reach-xy" / CHECKPOINT, weights_only=False)
    state = torch.load(folder / CHECKPOINT, weights_only=False)
    assert "method" in source and "method" not in state  # the run's own method closes it
    assert state["task_step"] == source["task_step"] == TRAIN["steps"]
    assert all(torch.equal(v, state["model"][k]) for k, v in source["model"].items())
    assert sorted(p.name for p in (folder / "replay").iterdir()) == sorted(
        f["file"] for f in state["replay_files"])  # fmt: skip
    assert _records(out) == [r for r in _records(shared) if r["stage"] == 0]


def test_a_method_that_does_not_share_it_trains_its_own(root, monkeypatch):
    monkeypatch.setattr(FineTune, "shares_first_task", False)
    out = root / "alone-ft"
    _run(_config("ft"), out, root / "scratch", first=root / "first-unused")
    assert not (out / FIRST_RECORD).exists() and not (root / "first-unused").exists()


@pytest.mark.integration
def test_a_sweep_shares_the_first_task_of_each_seed(tmp_path):
    torch.set_num_threads(1)
    out = tmp_path / "sweep"
    argv = ["sweep", "--suites", SUITE, "--methods", "ft,packnet", "--seeds", "0",
            "--preset", "smoke", "--seed_dataset", "null", "--max-parallel", "1",
            "--out", str(out)]  # fmt: skip
    argv += [f"--train.{k}={v}" for k, v in TRAIN.items()]
    assert main(argv) == 0  # sharing is the default online
    runs = sorted(p for p in out.iterdir() if (p / "metrics.json").is_file())
    assert len(runs) == 2 and all((p / FIRST_RECORD).is_file() for p in runs)
    # neither run trained it: a job of its own did
    assert [json.loads((p / FIRST_RECORD).read_text())["trained_by"] for p in runs] == ["job"] * 2
    (shared,) = _shared(out / "first")
    assert (shared / FIRST_DONE).is_file()
    # trained by a job of its own before either run started
    (entry,) = json.loads((out / "sweep.json").read_text())["submissions"]
    order = sorted(entry["jobs"], key=lambda n: entry["jobs"][n]["start"])
    assert entry["jobs"][f"first:{shared.name}"]["state"] == "COMPLETED"
    assert order.index(f"first:{shared.name}") < min(
        order.index(n) for n in entry["jobs"] if n.startswith("run:"))  # fmt: skip
    alone = Curriculum(_config("packnet"), tmp_path / "alone", tmp_path / "scratch",
                       progress=False).run()  # fmt: skip
    published = json.loads(next(p for p in runs if "packnet" in p.name).joinpath(
        "metrics.json").read_text())  # fmt: skip
    assert (published["bwt"], published["fwt"]) == (alone["bwt"], alone["fwt"])
    bench = subprocess.run([sys.executable, str(BENCH), str(out)], capture_output=True,
                           text=True, check=True)  # fmt: skip
    saved = json.loads(bench.stdout)
    (first,) = saved["shared_first_tasks"]
    assert first["runs"] == 2 and first["saved_cpu_s"] == first["cpu_s"] > 0
    assert saved["without_sharing_over_with"] > 1.0


def test_an_offline_sweep_cannot_share_it(tmp_path, capsys):
    argv = ["sweep", "--track", "offline", "--suites", SUITE, "--methods", "ft", "--seeds",
            "0", "--share-first-task", "--out", str(tmp_path / "off")]  # fmt: skip
    assert main(argv) == 2
    assert "--share-first-task" in capsys.readouterr().err


def test_a_damaged_shared_record_is_one_message_naming_the_remedy(tmp_path):
    shared = tmp_path / "first" / "key"
    shared.mkdir(parents=True)
    (shared / FIRST_DONE).write_text("{not json")
    with pytest.raises(InputError, match=r"first\.json: missing or corrupt .*delete .*key"):
        first_task_done(shared)


def test_its_helpers_need_a_finished_shared_task(tmp_path):
    with pytest.raises(RuntimeError, match="not finished"):
        start_from_first_task(tmp_path / "none", tmp_path / "run", tmp_path / "run" / "t")
