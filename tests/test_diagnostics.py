"""The published diagnostics (`results/diagnostics/*.py`) still run against today's API.

Each script reads finished runs and the Grasp dataset through the toolkit's internals (restore,
the evaluator, the update step, the RSSM), so a renamed function or a changed signature would
only show when someone reran a published result. Here each runs on smoke-size runs made here
and a tiny Grasp dataset, with shorter episodes and fewer retraining updates; its output must
have the published output's fields, with values in their ranges.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from ccdata.errors import EXIT_USAGE, InputError, run_script
from ccdata.record import GenerateConfig, generate
from ccfit.cli import main as ccfit

DIAGNOSTICS = Path(__file__).resolve().parents[1] / "results" / "diagnostics"
EPISODE_STEPS = 20
TRAIN = ["--train.steps=100", "--train.seed_steps=50", "--train.eval_interval=100",
         "--train.checkpoint_interval=100", f"--train.episode_steps={EPISODE_STEPS}"]  # fmt: skip


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"diagnostics_{name}", DIAGNOSTICS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _RunsOnDemand(dict):
    """Run directories made on first use: `make test` runs one script here (on the DreamerV3
    run), the integration tier the others, so neither tier pays for runs it does not read."""

    def __init__(self, root: Path, commands: dict[str, tuple[str, list[str]]],
                 common: list[str]) -> None:  # fmt: skip
        super().__init__()
        self.root, self.commands, self.common = root, commands, common

    def __missing__(self, key: str) -> Path:
        name, argv = self.commands[key]
        run = self.root / name
        assert ccfit([*argv, "--out", str(run), *self.common]) == 0
        self[key] = run
        return run


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A tiny Grasp dataset, and on demand a smoke Grasp curriculum per method the ER script
    compares, single-task pick-cube runs of TD-MPC2 and DreamerV3, and a box-pnp-close one (a
    scene with a lid and stage flags)."""
    root = tmp_path_factory.mktemp("diagnostics")
    dataset, _ = generate(GenerateConfig("Grasp", episodes=2, explore_episodes=2, image_size=32,
                                         max_steps=EPISODE_STEPS, root=root / "Grasp"),
                          progress=False)  # fmt: skip
    scratch = ["--scratch-root", str(root / "scratch")]
    commands = {  # key: (run directory, what makes it)
        "ewc": ("Grasp-tdmpc2-ewc", ["run", "--suite", "Grasp", "--method.type=ewc", *scratch]),
        "er": ("Grasp-tdmpc2-er", ["run", "--suite", "Grasp", "--method.type=er", *scratch]),
        "tdmpc2": ("pick-cube-tdmpc2", ["train", "--task", "pick-cube", "--model.type=tdmpc2"]),
        "dreamerv3": ("pick-cube-dreamerv3", ["train", "--task", "pick-cube",
                                              "--model.type=dreamerv3"]),
        "box": ("box-pnp-close-tdmpc2", ["train", "--task", "box-pnp-close",
                                         "--model.type=tdmpc2"]),
    }  # fmt: skip
    common = ["--preset", "smoke", "--seed_dataset", "null", "--quiet", *TRAIN]
    return SimpleNamespace(dataset=dataset, runs=_RunsOnDemand(root, commands, common))


def _run(script, argv: list[str], capsys) -> str:
    capsys.readouterr()
    script.main(argv)
    return capsys.readouterr().out


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


READING = {"reward_abs_err", "Q_mean", "Q_pi_mean", "return_mean", "dynamics_rel_err",
           "pi_vs_episode_action"}  # fmt: skip
"""What `ccfit.analysis.reading` gives per policy."""


@pytest.mark.integration
def test_grasp_er_pick(made, monkeypatch, capsys):
    script = _script("grasp_er_pick")
    monkeypatch.setattr(script, "DATASET", str(made.dataset))
    runs = [made.runs["ewc"], made.runs["er"]]
    lines = _run(script, [str(r) for r in runs], capsys).splitlines()
    assert [json.loads(line)["run"] for line in lines] == [r.name for r in runs]
    for line in lines:
        out = json.loads(line)
        for task in ("pick-cube", "place-cube"):  # the tasks before the last
            for policy in ("oracle", "random"):
                reading = out[f"{task}/reading/{policy}"]
                assert set(reading) == READING
                assert all(_finite(v) for v in reading.values())
                assert reading["reward_abs_err"] >= 0 and reading["dynamics_rel_err"] >= 0
            acting = out[f"{task}/acting"]
            assert set(acting) == {"mppi", "policy_mean"}
            assert all(len(v) == 3 and all(_finite(s) for s in v) for v in acting.values())


@pytest.mark.integration
def test_task_reading(made, capsys):
    script = _script("task_reading")
    out = json.loads(_run(script, [str(made.runs["tdmpc2"]), "--dataset", str(made.dataset)],
                          capsys))  # fmt: skip
    assert out["run"] == "pick-cube-tdmpc2" and out["task_step"] == 100
    for policy in ("oracle", "noisy-oracle", "random"):
        assert out[policy]["episodes"] == 2 and set(out[policy]) == READING | {"episodes"}
        assert all(_finite(v) for v in out[policy].values())
    assert set(out["acting"]) == {"mppi", "policy_mean"}
    assert all(len(v) == 3 and all(_finite(s) for s in v) for v in out["acting"].values())
    with pytest.raises(InputError, match="this reads TD-MPC2-style models"):
        script.main([str(made.runs["dreamerv3"]), "--dataset", str(made.dataset)])


@pytest.mark.integration
def test_packnet_prune(made, monkeypatch, capsys):
    script = _script("packnet_prune")
    monkeypatch.setattr(script, "RETRAINING", (0, 2, 5))
    lines = _run(script, [str(made.runs["tdmpc2"])], capsys).splitlines()
    points = [json.loads(line) for line in lines]
    assert [p["after"] for p in points] == [
        "trained (before the prune)",
        "prune + 0 retraining updates",
        "prune + 2 retraining updates",
        "prune + 5 retraining updates",
    ]
    for p in points:
        assert len(p["normalized"]) == 3 and all(_finite(s) for s in p["normalized"])
        assert all(0.0 <= s <= 1.0 for s in p["success"])


@pytest.mark.integration
def test_dreamerv3_pick(made, monkeypatch, capsys):
    script = _script("dreamerv3_pick")
    monkeypatch.setattr(script, "DATASET", str(made.dataset))
    out = json.loads(_run(script, [str(made.runs["dreamerv3"])], capsys))
    assert out["run"] == "pick-cube-dreamerv3" and out["task_step"] == 100
    for policy, episodes in (("oracle", 2), ("random", 2)):
        assert out[policy]["episodes"] == episodes
        numbers = {k: v for k, v in out[policy].items() if k != "corr_episode_reward_sums"}
        assert all(_finite(v) for v in numbers.values())
        assert out[policy]["reward_abs_err_per_step"] >= 0


@pytest.mark.integration
def test_dreamerv3_state_precision(made, capsys):
    script = _script("dreamerv3_state_precision")
    run = made.runs["dreamerv3"]
    out = json.loads(_run(script, [str(run), "--dataset", str(made.dataset)], capsys))
    assert out["task_step"] == 100 and out["state_recon_scale"] == 1.0
    assert {"oracle", "random"} <= out.keys()
    for policy in ("oracle", "random"):
        got = out[policy]
        assert got["rows"] > 0 and 0.0 <= got["p_end_open_loop"] <= 1.0
        for kind in ("posterior", "prior_1", "open_loop_15", "still", "mean"):
            assert set(got[kind]) == {"hand", "cube", "goal"}
            assert all(_finite(v) and v >= 0 for v in got[kind].values())
        assert got["still"]["goal"] == 0.0  # the goal never moves within an episode
    assert out["random"]["still"]["cube"] < 1e-3  # the random arm hardly touches the cube
    with pytest.raises(InputError, match="tdmpc2 run from state; this script reads a DreamerV3"):
        script.main([str(made.runs["tdmpc2"]), "--dataset", str(made.dataset)])


def test_dreamerv3_imagination(made, capsys):
    script = _script("dreamerv3_imagination")
    run = made.runs["dreamerv3"]
    out = json.loads(_run(script, [str(run), "--dataset", str(made.dataset)], capsys))
    assert out["run"] == str(run) and out["task_step"] == 100
    for policy in ("random", "oracle"):
        got = out[policy]
        assert got["starts"] > 0 and got["rollouts"] == script.ROLLOUTS * got["starts"]
        assert all(0 <= got[k] <= 1 for k in ("term_mode", "term_prob", "imag_cont_mode_mean"))
        assert _finite(got["imag_reward_mean"])
        assert got["imag_reward_max"] >= got["imag_reward_mean"]


@pytest.mark.integration
def test_stage_reached(made, capsys):
    script = _script("stage_reached")
    out = json.loads(_run(script, [str(made.runs["tdmpc2"]), "3"], capsys))
    assert out["task"] == "pick-cube" and out["task_step"] == 100
    assert len(out["success"]) == len(out["best_raw"]) == len(out["steps"]) == 3
    assert all(0.0 <= r <= 10.0 for r in out["best_raw"])
    pairs = zip(out["steps_at_5_or_more"], out["steps"], strict=True)
    assert all(0 <= k <= n <= EPISODE_STEPS for k, n in pairs)
    assert "lid_to_closed_first_and_least_m" not in out  # pick-cube's scene has no lid
    assert not [key for key in out if key.startswith("steps_") and key != "steps_at_5_or_more"]


@pytest.mark.integration
def test_stage_reached_follows_the_lid_and_stage_flags_where_the_scene_has_them(made, capsys):
    out = json.loads(_run(_script("stage_reached"), [str(made.runs["box"]), "2"], capsys))
    assert out["task"] == "box-pnp-close"
    lid = out["lid_to_closed_first_and_least_m"]
    assert len(lid) == 2
    # the lid starts open, away from its closed pose; the least distance is along the episode
    assert all(0.0 <= least <= first and first > 0.0 for first, least in lid)
    # the scene's stage flags, each counted over the episode's steps
    for flag in ("steps_cube_in_box", "steps_lid_closed"):
        assert len(out[flag]) == 2
        assert all(0 <= k <= n for k, n in zip(out[flag], out["steps"], strict=True))


@pytest.mark.integration
def test_handover_lets_the_oracle_play_until_the_raw_reward_reaches_the_threshold(made, capsys):
    """The policy takes over where the oracle alone first reaches T on that layout (the same
    layout seed, the same 20-step episodes); T = 0 is the run alone; a T the oracle never
    reaches gives nulls. DreamerV3 (a recurrent acting state) takes over too."""
    from ccdata.env import make_env
    from ccdata.policies import make_policy
    from ccfit.train.evaluate import eval_seeds

    seed = eval_seeds(0, 0, 1)[0]
    env = make_env("pick-cube", episode_steps=EPISODE_STEPS)
    oracle = make_policy("oracle", "pick-cube")
    obs, _ = env.reset(seed=seed)
    raw = []
    for _ in range(EPISODE_STEPS):
        obs, *_, info = env.step(oracle.act(obs))
        raw.append(float(info["raw_reward"]))
    at = raw[5]  # reached by step 6 at the latest
    first = next(i + 1 for i, r in enumerate(raw) if r >= at)
    script = _script("handover")
    lines = _run(script, [str(made.runs["tdmpc2"]), "--layouts", "2", "--at", f"0,{at},1000"],
                 capsys).splitlines()  # fmt: skip
    alone, handed, never = (json.loads(x) for x in lines)
    assert [x["handover_at_raw"] for x in (alone, handed, never)] == [0.0, at, 1000.0]
    assert alone["handover_step"] == [0, 0] and handed["handover_step"][0] == first
    for x in (alone, handed):
        assert all(isinstance(s, bool) for s in x["success"])
        assert all(0.0 <= r <= 10.0 for r in x["best_raw"] + x["last_raw"])
    assert set(never) - {"run", "task", "task_step", "handover_at_raw", "acting"} == {
        "handover_step",
        "success",
        "best_raw",
        "last_raw",
    }
    assert all(v == [None, None] for k, v in never.items() if k in ("success", "best_raw"))
    out = json.loads(_run(script, [str(made.runs["dreamerv3"]), "--layouts", "1", "--at",
                                   str(at)], capsys))  # fmt: skip
    assert out["handover_step"] == [first]
    with pytest.raises(InputError, match="--at takes comma-separated numbers"):
        script.main([str(made.runs["tdmpc2"]), "--at", "a,b"])


@pytest.mark.integration
def test_handover_can_act_by_the_policy_alone(made, capsys, monkeypatch):
    """`--acting policy`: the run's policy's mean acts, the planner is never called."""
    import ccfit.models.tdmpc2.model as tdmpc2_model

    def no_planning(*args, **kwargs):
        raise AssertionError("planned")

    monkeypatch.setattr(tdmpc2_model, "mppi_plan", no_planning)
    script = _script("handover")
    argv = [str(made.runs["tdmpc2"]), "--layouts", "1", "--at", "0"]
    out = json.loads(_run(script, [*argv, "--acting", "policy"], capsys))
    assert out["acting"] == "policy" and out["handover_step"] == [0]
    with pytest.raises(AssertionError, match="planned"):
        _run(script, argv, capsys)
    with pytest.raises(InputError, match="has no policy to act alone"):
        script.main([str(made.runs["dreamerv3"]), "--acting", "policy"])


@pytest.mark.integration
def test_er_branch(made, tmp_path, capsys):
    """An ER run that kept its stages, its branch without replay after task 2, and FT's."""
    source, branch = tmp_path / "er", tmp_path / "er-off"
    common = ["run", "--suite", "Grasp", "--method.type=er", "--scratch-root",
              str(made.runs["ewc"].parent / "scratch"), "--preset", "smoke", "--seed_dataset",
              "null", "--quiet", *TRAIN]  # fmt: skip
    assert ccfit([*common, "--keep-stages", "--out", str(source)]) == 0
    assert ccfit([*common, "--method.replay_ratio=0", "--out", str(branch),
                  "--branch-from", str(source), "--branch-after", "2"]) == 0  # fmt: skip
    runs = [source, branch, made.runs["ewc"]]
    lines = [json.loads(x) for x in _run(_script("er_branch"), [str(r) for r in runs],
                                         capsys).splitlines()]  # fmt: skip
    assert [x["run"] for x in lines[:3]] == [r.name for r in runs]
    assert len(lines) == 4 and lines[3]["reference"]  # the three share one reference
    assert lines[1]["branch"]["after"] == 2 and lines[0]["branch"] is None
    for x in lines:
        assert x["task"] == "pnp-cube" if "task" in x else x["reference"]
        assert x["evaluations"] >= 1 and _finite(x["mean_last_21"]) and _finite(x["end_of_task"])
    assert set(lines[0]["earlier_while_it_trains"]) == {"pick-cube", "place-cube"}


def test_end_score_reads_each_published_curriculum_both_ways(capsys):
    """As published (its metrics.json's BWT) and with C_i from the evaluation before b_i; the
    committed output is what it gives over today's results (runs published since add lines)."""
    results = DIAGNOSTICS.parent
    out = _run(_script("end_score"), [str(results / "online")], capsys)
    lines = [json.loads(x) for x in out.splitlines()]
    runs, groups = lines[:-1], lines[-1]["groups"]
    assert len(runs) >= 50 and sum(g["runs"] for g in groups) == len(runs)
    for line in runs:
        path = results / "online" / line["folder"] / line["run"]
        metrics = json.loads((path / "metrics.json").read_text())
        assert line["bwt"] == pytest.approx(metrics["bwt"])
        assert line["end_scores"] == pytest.approx(metrics["end_of_task"][:-1])
        records = [json.loads(x) for x in (path / "metrics.jsonl").read_text().splitlines()]
        shifted = line["end_scores_before_close"]
        for i, (end, score) in enumerate(zip(metrics["task_ends"][:-1], shifted, strict=True)):
            before = [r for r in records if r["task_index"] == i and r["global_step"] < end]
            assert score == max(before, key=lambda r: r["global_step"])["normalized_return"]
    published = (DIAGNOSTICS / "end_score.jsonl").read_text().splitlines()
    assert set(published[:-1]) <= set(out.splitlines()[:-1])


@pytest.mark.parametrize("name", ["grasp_er_pick", "packnet_prune", "dreamerv3_pick",
                                  "stage_reached", "er_branch", "task_reading",
                                  "handover", "end_score"])  # fmt: skip
def test_a_diagnostic_refuses_a_missing_run_in_one_line(name, tmp_path, capsys):
    script = _script(name)
    capsys.readouterr()
    assert run_script(script.main, f"{name}.py", [str(tmp_path / "absent")]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith(f"{name}.py: error: ") and str(tmp_path / "absent") in err
    assert err.count("\n") == 1


@pytest.mark.integration
def test_optimizer_state_pairs_the_arms_by_seed(made, tmp_path, capsys):
    """Two arms of one grid, with and without `keep_backbone_optimizer`: the first task agrees
    exactly (it starts fresh either way), every seed gets its paired differences."""
    keep = tmp_path / "keep" / "Grasp-tdmpc2-ewc"
    argv = ["run", "--suite", "Grasp", "--method.type=ewc", "--train.keep_backbone_optimizer=true",
            "--scratch-root", str(made.runs["ewc"].parent / "scratch"), "--out", str(keep),
            "--preset", "smoke", "--seed_dataset", "null", "--quiet", *TRAIN]  # fmt: skip
    assert ccfit(argv) == 0
    script = _script("optimizer_state")
    (line,) = _run(script, [str(keep.parent), str(made.runs["ewc"].parent)], capsys).splitlines()
    out = json.loads(line)
    assert (out["model"], out["suite"], out["method"]) == ("tdmpc2", "Grasp", "ewc")
    assert out["first_task_identical"] == {"0": True}
    diff = out["keep_minus_fresh"]["0"]
    assert set(diff) == {"bwt", "forgetting", "fwt", "mean_end_of_task", "mean_final"}
    assert _finite(diff["mean_final"]) and _finite(diff["fwt"])
    for arm in ("keep", "fresh"):
        assert set(out[arm]) == {"bwt", "forgetting", "fwt", "per_seed"}
    capsys.readouterr()
    absent = str(tmp_path / "absent")
    assert run_script(script.main, "optimizer_state.py", [absent, str(keep.parent)]) == EXIT_USAGE
    assert absent in capsys.readouterr().err
