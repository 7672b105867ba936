"""A curriculum branched from another run after its first tasks (`ccfit.branch`): the source
keeps its stage states, a branch with the source's own config reproduces the source's later
tasks record for record, a branch with other method options changes only the tasks after the
branch point, and what would not be the source run up to there is refused (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import ccfit.curriculum as C
from ccfit.branch import BRANCH, Branch, stage_path
from ccfit.cli import main
from ccfit.config import CurriculumConfig
from ccfit.config_parse import resolve
from ccfit.curriculum import Curriculum
from ccfit.train import CONFIG, METRICS

try:
    from short_episodes import EPISODE_STEPS
except ImportError:  # tests/ imported as a package
    from tests.short_episodes import EPISODE_STEPS

SUITE = "Grasp"
TRAIN = {"steps": 100, "seed_steps": 50, "eval_interval": 100, "checkpoint_interval": 50,
         "episode_steps": EPISODE_STEPS}  # fmt: skip


def _config(**method) -> CurriculumConfig:
    return resolve(CurriculumConfig, {
        "suite": SUITE, "preset": "smoke", "seed_dataset": None, "train": dict(TRAIN),
        "method": {"type": "er", "batch_size": 16, **method},
    })  # fmt: skip


def _records(run_dir: Path) -> list[dict]:
    return [json.loads(x) for x in (run_dir / METRICS).read_text().splitlines() if x.strip()]


def _by_stage(records: list[dict], below: int) -> list[dict]:
    return [r for r in records if r["stage"] < below]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("branch")
    result = Curriculum(_config(), root / "source", root / "scratch", progress=False,
                        keep_stages=True).run()  # fmt: skip
    return SimpleNamespace(root=root, dir=root / "source", result=result)


def test_a_run_with_keep_stages_keeps_its_state_after_every_task(source):
    final = torch.load(source.dir / C.STATE, map_location="cpu", weights_only=False)
    for k in (1, 2, 3):
        state = torch.load(stage_path(source.dir, k), map_location="cpu", weights_only=False)
        assert state["completed"] == k and len(state["heads"]) == k
    assert stage_path(source.dir, 3).read_bytes() == (source.dir / C.STATE).read_bytes()
    assert final["completed"] == 3


@pytest.mark.integration
def test_a_run_that_kept_stages_keeps_them_when_resumed_without_the_flag(source, tmp_path,
                                                                          monkeypatch):  # fmt: skip
    """Interrupted just after its first stage, then resumed without `keep_stages` (a sweep
    or a command given without the flag), the run still keeps every stage, and they are the
    uninterrupted run's."""
    real = C.keep_stage

    def keep_then_stop(run_dir, state, completed):
        real(run_dir, state, completed)
        raise KeyboardInterrupt  # stopped right after the stage of task 1

    out = tmp_path / "run"
    monkeypatch.setattr(C, "keep_stage", keep_then_stop)
    with pytest.raises(KeyboardInterrupt):
        Curriculum(_config(), out, source.root / "scratch", progress=False,
                   keep_stages=True).run()  # fmt: skip
    monkeypatch.setattr(C, "keep_stage", real)
    assert sorted(p.name for p in (out / "stages").iterdir()) == ["after-1.pt"]
    Curriculum(_config(), out, source.root / "scratch", progress=False).run()
    for k in (1, 2, 3):
        ours = torch.load(stage_path(out, k), map_location="cpu", weights_only=False)
        theirs = torch.load(stage_path(source.dir, k), map_location="cpu", weights_only=False)
        assert ours["completed"] == theirs["completed"] == k
        assert all(torch.equal(ours["model"][n], theirs["model"][n]) for n in theirs["model"])


@pytest.fixture(scope="module")
def branches(source):
    """Two branches of the source: its own config after task 1, no replay after task 2."""
    made = {}
    for name, method, after in (("same", {}, 1), ("no-replay", {"replay_ratio": 0.0}, 2)):
        out = source.root / name
        result = Curriculum(_config(**method), out, source.root / "scratch", progress=False,
                            branch=Branch(source.dir, after)).run()  # fmt: skip
        made[name] = SimpleNamespace(dir=out, result=result)
    return made


@pytest.mark.integration
def test_a_branch_with_the_sources_config_reproduces_the_source(source, branches):
    out, result = branches["same"].dir, branches["same"].result
    assert result == source.result
    assert _records(out) == _records(source.dir)
    branch = json.loads((out / BRANCH).read_text())
    assert branch["after"] == 1 and Path(branch["source"]) == source.dir.resolve()
    assert json.loads((out / CONFIG).read_text())["resolved_branch"] == branch
    # Resumed (finished) without the branch flags: the directory knows what it is.
    again = Curriculum(_config(), out, source.root / "scratch", progress=False).run()
    assert again == result


@pytest.mark.integration
def test_a_branch_with_other_method_options_changes_only_the_later_tasks(source, branches):
    out = branches["no-replay"].dir
    ours, theirs = _records(out), _records(source.dir)
    assert _by_stage(ours, 2) == _by_stage(theirs, 2) and _by_stage(ours, 2)
    later = [(r["task"], r["normalized_return"]) for r in ours if r["stage"] == 2]
    assert later and later != [(r["task"], r["normalized_return"])
                               for r in theirs if r["stage"] == 2]  # fmt: skip
    config = json.loads((out / CONFIG).read_text())
    assert config["method"]["replay_ratio"] == 0.0 and config["resolved_branch"]["after"] == 2


def _cli(source_dir: Path, out: Path, *extra: str) -> list[str]:
    argv = ["run", "--suite", SUITE, "--preset", "smoke", "--seed_dataset", "null",
            "--method.type=er", "--method.batch_size=16", "--out", str(out), "--quiet"]  # fmt: skip
    argv += [f"--train.{k}={v}" for k, v in TRAIN.items()]
    return argv + ["--branch-from", str(source_dir), *extra]


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--branch-after", "2", "--seed", "1"], "differs from the source's in seed"),
        (["--branch-after", "2", "--method.type=ewc"], "keeps the source's method (er)"),
        (["--branch-after", "3"], "--branch-after must be in 1..2"),
        (["--branch-after", "two"], "takes a number of tasks"),
        ([], "go together"),
    ],
)
def test_a_branch_that_would_not_be_the_source_run_is_refused(source, tmp_path, capsys, extra,
                                                              needle):  # fmt: skip
    argv = _cli(source.dir, tmp_path / "branch", *extra)
    if "--method.type=ewc" in extra:
        argv = [a for a in argv if a not in ("--method.type=er", "--method.batch_size=16")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "branch" / C.STATE).exists()


def test_a_branch_needs_a_source_that_kept_its_stages_and_a_new_out(source, tmp_path, capsys):
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / CONFIG).write_text((source.dir / CONFIG).read_text())
    assert main(_cli(plain, tmp_path / "a", "--branch-after", "1")) == 2
    assert "--keep-stages" in capsys.readouterr().err
    assert main(_cli(tmp_path / "nowhere", tmp_path / "b", "--branch-after", "1")) == 2
    assert "no run there" in capsys.readouterr().err
    assert main(_cli(source.dir, source.dir, "--branch-after", "1")) == 2
    assert "already holds a run" in capsys.readouterr().err
    (plain / CONFIG).write_text('{"suite": ')
    assert main(_cli(plain, tmp_path / "c", "--branch-after", "1")) == 2
    assert "missing or corrupt" in capsys.readouterr().err


@pytest.mark.integration
def test_the_report_keeps_a_branch_apart_from_its_source(source, branches):
    from ccfit.report import load_groups

    groups = load_groups([source.root])
    variants = sorted(v for (_, _, method, v) in groups if method == "er")
    assert len(variants) == 3, variants  # the source, and the two branches
    assert any("resolved_branch.after=2" in v and "replay_ratio=0.0" in v for v in variants)


@pytest.mark.integration
def test_a_branch_start_killed_before_its_record_starts_again(source, branches, tmp_path):
    """What a start writes before branch.json (the state, the records) is written again."""
    out = tmp_path / "killed"
    out.mkdir()
    (out / C.STATE).write_bytes(b"half a copy")
    (out / METRICS).write_text('{"half": ')
    C.start_branch(Branch(source.dir, 1), json.loads((source.dir / CONFIG).read_text()), out,
                   3, C.STATE)  # fmt: skip
    assert (out / C.STATE).read_bytes() == stage_path(source.dir, 1).read_bytes()
    assert _records(out) == _by_stage(_records(source.dir), 1)
    assert json.loads((out / BRANCH).read_text())["after"] == 1


@pytest.mark.integration
def test_er_without_replay_after_a_branch_trains_as_ft_does(source, tmp_path):
    """What `results/diagnostics/er_branch.py` relies on: ER with `replay_ratio` 0 from
    task K on is FT from there. ER's first task replays nothing, so a branch after it is FT."""
    ft = Curriculum(resolve(CurriculumConfig, {
        "suite": SUITE, "preset": "smoke", "seed_dataset": None, "train": dict(TRAIN),
        "method": {"type": "ft"},
    }), tmp_path / "ft", source.root / "scratch", progress=False).run()  # fmt: skip
    branch = Curriculum(_config(replay_ratio=0.0), tmp_path / "er-off", source.root / "scratch",
                        progress=False, branch=Branch(source.dir, 1)).run()  # fmt: skip
    assert _records(tmp_path / "er-off") == _records(tmp_path / "ft")
    assert {k: v for k, v in branch.items() if k != "method"} == {
        k: v for k, v in ft.items() if k != "method"
    }
