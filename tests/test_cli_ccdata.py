"""ccdata's command line: listing, rendering, references, and one-line errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

import ccdata
from ccdata.cli import build_parser, main
from ccdata.cli_generate import generate_config
from ccdata.errors import CliError


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ccdata.cli", *args], capture_output=True, text=True
    )


def test_list_prints_every_suite_with_its_matrix(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("Reach", "Grasp", "BinPnP", "PnPBlock", "DrawerPnP", "PnPBoxClose"):
        assert f"{name}  (axis:" in out
    assert "bin-yellow-purple  [. x x x]  composition" in out
    assert "  from state, pnp-red-block and pnp-blue-block are one task" in out
    assert out.count("are one task") == 2  # BinPnP and PnPBlock


@pytest.mark.parametrize(
    "args, message",
    [
        (["list", "--suite", "Nope"], "unknown suite 'Nope'"),
        (["render", "--task", "nope", "--out", "x.png"], "unknown task 'nope'"),
        (["generate", "--suite", "Nope"], "unknown suite 'Nope'"),
        # a path, not a Hub id: it would have written the dataset outside LeRobot's cache
        (["generate", "--suite", "Reach", "--repo-id", "../escape"], "repo id '../escape'"),
        (["generate", "--suite", "Reach", "--episodes", "abc"], "invalid int value: 'abc'"),
        (["generate", "--suite", "Reach", "--root", __file__], f"root {__file__} is a file"),
        (
            ["render", "--task", "reach-xy", "--out", "x.png", "--image-size", "100000"],
            "image_size must be in [8, 16384], got 100000",
        ),  # fmt: skip
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message):
    result = run_cli(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("buffered", [True, False], ids=["buffered", "unbuffered"])
@pytest.mark.parametrize("script", ["ccdata.cli", "ccfit.cli"])
def test_a_reader_gone_ends_the_command_quietly(script, buffered, tmp_path):
    """`ccdata list | head -1`, `ccfit sweep --status RUNS | head -1`: stdout's reader
    leaves before the output is written; the command ends as SIGPIPE would end it, without a
    traceback, whether Python's stdout is flushed at exit (buffered) or at each line
    (PYTHONUNBUFFERED)."""
    args = ["list"]
    if script == "ccfit.cli":
        from ccfit.sweep.grid import Grid, expand, write_record

        write_record(expand(Grid(("Reach",), ("tdmpc2",), ("ft",), (0,)), tmp_path), [])
        args = ["sweep", "--status", str(tmp_path)]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    read, write = os.pipe()
    os.close(read)  # gone before the first byte
    proc = subprocess.run([sys.executable, "-m", script, *args], stdout=write,
                          stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    os.close(write)
    assert (proc.returncode, proc.stderr) == (141, ""), proc.stderr


def test_a_broken_pipe_of_its_own_keeps_its_traceback(monkeypatch):
    """A worker's pipe broken is a bug, not a reader gone: stdout is still read here."""

    def worker_gone(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr("ccdata.cli._cmd_list", worker_gone)
    read, write = os.pipe()
    with os.fdopen(write, "w") as out, os.fdopen(read):  # the reader stays till the end
        monkeypatch.setattr(sys, "stdout", out)
        with pytest.raises(BrokenPipeError):
            main(["list"])


def test_generate_runs_a_worker_per_available_core_by_default():
    parse = build_parser().parse_args
    reach = ["generate", "--suite", "Reach"]
    assert generate_config(parse(reach)).workers == len(os.sched_getaffinity(0))
    assert generate_config(parse([*reach, "--workers", "3"])).workers == 3
    # The cores of the process's affinity mask (taskset, cpusets, SLURM), not the machine's.
    one_core = min(os.sched_getaffinity(0))
    code = (
        f"import os; os.sched_setaffinity(0, {{{one_core}}}); "
        "from ccdata.cli import build_parser; from ccdata.cli_generate import generate_config; "
        f"print(generate_config(build_parser().parse_args({reach!r})).workers)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.strip() == "1", done.stderr
    # Only a --workers the user gave is refused with slurm; the default is not.
    generate_config(parse([*reach, "--launcher", "slurm"]))
    with pytest.raises(CliError, match="--workers is for --launcher local"):
        generate_config(parse([*reach, "--launcher", "slurm", "--workers", "1"]))
    assert "identical with any number of workers" in " ".join(
        run_cli("generate", "--help").stdout.split()
    )


@pytest.mark.parametrize("command", [["verify"], ["card"], ["push", "--repo-id", "org/x"]])
def test_a_dataset_command_without_a_dataset_is_one_line(command, tmp_path, monkeypatch, capsys):
    # An absent directory, and one that holds no dataset.
    for root in (tmp_path / "absent", tmp_path):
        assert main([*command, "--root", str(root)]) == 2
        assert capsys.readouterr().err == (
            f"ccdata {command[0]}: error: no dataset at {root} (no meta/info.json)\n"
        )
    if command[0] == "card":  # --suite renders the suite's default card: no dataset needed
        return
    monkeypatch.setattr("lerobot.utils.constants.HF_LEROBOT_HOME", tmp_path)
    assert main([*command, "--suite", "Reach"]) == 2
    assert capsys.readouterr().err == (
        f"ccdata {command[0]}: error: no dataset at {tmp_path / 'ccdata/Reach'} (no "
        "meta/info.json): run `ccdata generate --suite Reach` first\n"
    )


def test_render_writes_three_views_and_an_episode(tmp_path, capsys):
    png, mp4 = tmp_path / "views.png", tmp_path / "episode.mp4"
    code = main(
        [
            "render",
            "--task",
            "reach-xy",
            "--out",
            str(png),
            "--video",
            str(mp4),
            "--image-size",
            "48",
        ]
    )
    assert code == 0
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)[..., ::-1]  # BGR -> RGB
    assert image.shape == (48, 144, 3)
    env = ccdata.make_env("reach-xy", seed=0, image_size=48)
    env.reset()
    np.testing.assert_array_equal(image, env.render())  # lossless, channels in RGB order
    env.close()
    with av.open(str(mp4)) as container:
        frames = sum(1 for _ in container.decode(video=0))
    assert 2 <= frames <= 251
    assert "success=True" in capsys.readouterr().out


def test_references_are_reproducible(tmp_path):
    from ccdata.references import write_references

    a = json.loads(write_references(["reach-xy"], episodes=3, path=tmp_path / "a.json").read_text())
    b = json.loads(write_references(["reach-xy"], episodes=3, path=tmp_path / "b.json").read_text())
    assert a["tasks"] == b["tasks"]
    ref = a["tasks"]["reach-xy"]
    assert ref["success_rate"] == 1.0
    assert -5.0 < ref["mean_discounted_return"] < 0.0


def test_references_write_into_the_package_only_when_asked(capsys):
    """The maintainer command names where it writes: without --out or --in-place it stops in
    one line, before any rollout, and the installed references.json stays as it was."""
    import ccdata.references

    package_file = Path(ccdata.references.__file__).with_name(ccdata.references.REFERENCE_FILE)
    before = package_file.read_bytes()
    for argv in (["references", "--task", "reach-xy"], ["references", "--out", "x.json",
                                                          "--in-place"]):  # fmt: skip
        with pytest.raises(SystemExit) as stop:
            main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and "--in-place" in err and "--out" in err
    assert package_file.read_bytes() == before


def test_references_out_that_cannot_take_them_is_one_line_before_any_rollout(tmp_path, capsys):
    (tmp_path / "not-json.json").write_text("[1, 2")
    (tmp_path / "list.json").write_text("[1, 2]")
    cases = {
        tmp_path: f"cannot write references to {tmp_path}: a folder",
        tmp_path / "absent" / "r.json": f"no folder {tmp_path / 'absent'}",
        tmp_path / "not-json.json": "not-json.json holds no references to add to (Expecting",
        tmp_path / "list.json": "list.json holds no references to add to (no 'tasks' object)",
    }
    for out, message in cases.items():
        assert main(["references", "--task", "reach-xy", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("ccdata references: error: ") and message in err
        assert err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["list.json", "not-json.json"]


@pytest.mark.parametrize(
    "suite", ["Reach", "Grasp", "BinPnP", "PnPBlock", "DrawerPnP", "PnPBoxClose"]
)
def test_checked_in_cards_are_current(suite):
    from pathlib import Path

    from ccdata.cards import render_card

    card = Path(__file__).parent.parent / "cards" / f"{suite}.md"
    assert card.read_text() == render_card(suite), f"regenerate: ccdata card --suite {suite}"


def test_card_has_lerobot_header_and_suite_yaml():
    import yaml

    from ccdata.cards import render_card

    text = render_card("BinPnP")
    header = yaml.safe_load(text.split("---")[1])
    assert header["task_categories"] == ["robotics"] and "LeRobot" in header["tags"]
    assert header["configs"][0]["data_files"] == "data/*/*.parquet"
    assert header["ccdata"]["tasks"][-1] == "bin-yellow-purple"
    assert header["ccdata"]["composition_matrix"][3] == [0, 1, 1, 1]
    for section in (
        "## Composition matrix",
        "## Oracle reference returns",
        "## Loading",
        "## Citation",
        "## Policies and counts",
        "## Rendering",
    ):
        assert section in text


def test_a_corrupt_dataset_record_is_one_line_and_a_bug_keeps_its_traceback(
    tmp_path, monkeypatch, capsys
):
    """Bad input (here a ccdata.json cut short) is one line and exit 2; a ValueError from the
    code itself is a bug, not bad input, and must escape with its traceback (it was printed as
    one line and exit 2 before InputError was told apart)."""
    from ccdata.dataset_format import CCDATA_META, read_ccdata_metadata

    (tmp_path / CCDATA_META).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / CCDATA_META).write_text('{"suite": "Rea')
    with pytest.raises(ccdata.errors.InputError, match=f"{CCDATA_META} is corrupt"):
        read_ccdata_metadata(tmp_path)

    def broken(args):
        raise ValueError("an internal inconsistency")

    monkeypatch.setattr("ccdata.cli._cmd_list", broken)
    with pytest.raises(ValueError, match="an internal inconsistency"):
        main(["list"])


def test_every_option_is_taken_with_either_spelling():
    """One rule for both CLIs: `--a_b` is `--a-b` (ccfit's config commands take both too)."""
    import argparse

    from ccfit.sweep.cli import build_parser as sweep_parser

    parse = build_parser().parse_args
    dashed = ["generate", "--suite", "Reach", "--image-size", "32", "--repo-id", "me/Reach",
              "--explore-episodes", "3", "--max-steps", "20"]  # fmt: skip
    under = ["--" + a[2:].replace("-", "_") if a.startswith("--") else a for a in dashed]
    assert under != dashed and parse(under) == parse(dashed)
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    checked = 0
    for parser in [*sub.choices.values(), sweep_parser()]:
        for action in parser._actions:
            for option in action.option_strings:
                if option.startswith("--") and "-" in option[2:]:
                    assert parser._dashed("--" + option[2:].replace("-", "_") + "=1") == (
                        option + "=1"
                    )
                    checked += 1
    assert checked >= 15


def _generate_parser():
    import argparse

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return sub.choices["generate"]


def test_generate_options_are_the_settings_fields_with_their_defaults_and_help():
    """`ccdata generate`'s options are made from `GenerateConfig`'s fields: a default or a
    help text changed on the field is the option's, never restated."""
    import dataclasses

    from ccdata.cli_generate import GENERATE_FIELDS, GENERATE_UNSET
    from ccdata.cli_options import field_docs
    from ccdata.record import GenerateConfig

    fields = {f.name: f for f in dataclasses.fields(GenerateConfig)}
    docs = field_docs(GenerateConfig)
    actions = {a.dest: a for a in _generate_parser()._actions}
    defaults = vars(build_parser().parse_args(["generate", "--suite", "Reach"]))
    for name in GENERATE_FIELDS:
        action = actions[name]
        assert action.option_strings[0] == "--" + name.replace("_", "-")
        assert action.help.startswith(docs[name].replace("%", "%%"))
        if name in GENERATE_UNSET:
            assert defaults[name] is None
        elif fields[name].default is dataclasses.MISSING:
            assert action.required
        else:
            assert defaults[name] == fields[name].default, name
            assert fields[name].default is None or f"(default: {fields[name].default})" in (
                action.help
            )
    config = generate_config(build_parser().parse_args(["generate", "--suite", "Reach",
                                                        "--workers", "1"]))  # fmt: skip
    assert config == GenerateConfig(suite="Reach", workers=1)


def test_generate_help_lists_every_option_with_its_default():
    text = " ".join(_generate_parser().format_help().split())
    assert "--explore-episodes EXPLORE_EPISODES Episodes per task for each exploration" in text
    assert "(default: 25)" in text and "(default: 64)" in text


def test_field_docs_reads_each_fields_docstring_over_the_bases():
    from ccdata.cli_options import field_docs
    from ccdata.record import GenerateConfig

    docs = field_docs(GenerateConfig)
    assert docs["episodes"] == "Oracle episodes per task."  # DatasetSettings'
    assert docs["workers"].startswith("Processes rolling out episodes")  # GenerateConfig's own


def test_calibrate_and_references_defaults_are_their_functions():
    import inspect

    from ccdata.calibration import calibrate
    from ccdata.references import write_references

    def default(fn, name):
        return inspect.signature(fn).parameters[name].default

    args = build_parser().parse_args(["calibrate"])
    for name in ("episodes", "target", "iterations", "tolerance"):
        assert getattr(args, name) == default(calibrate, name)
    args = build_parser().parse_args(["references", "--out", "refs.json"])
    assert args.episodes == default(write_references, "episodes")
