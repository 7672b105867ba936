"""How a config command's argv becomes its config: one reading of argv (`read_argv`), the
preset's defaults in memory, draccus's decoder; and the one-line errors of bad input."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from ccfit.config_argv import read_argv
from ccfit.config_base import ConfigError

PUBLISHED = Path(__file__).parents[1] / (
    "results/online/reach-tdmpc2/Reach-tdmpc2-ft-state-cpu-s0/config.json"
)


@pytest.mark.parametrize(
    "argv, expected",
    [(["--train.steps=10"], {"train.steps": "10"}),
     (["--train.steps", "10"], {"train.steps": "10"}),
     (["--image-size", "32", "--image_size=48"], {"image_size": "48"}),  # the last one wins
     (["--method.lam", "-5"], {"method.lam": "-5"}),  # a negative number is a value
     (["--out"], {"out": None}),  # missing: the reader says whether --out exists first
     (["--out", "--quiet"], {"out": None, "quiet": True}),
     (["--keep-stages", "--scratch-root", "DIR"], {"keep_stages": True, "scratch_root": "DIR"})],
)  # fmt: skip
def test_read_argv_takes_both_spellings_and_both_forms(argv, expected):
    switches = {"quiet": None, "keep_stages": None, "scratch_root": "DIR"}
    assert read_argv(argv, switches) == expected


def test_a_stray_word_is_one_line():
    with pytest.raises(ValueError, match="unexpected argument 'stray'"):
        read_argv(["--suite", "Reach", "stray"])


def test_parsing_writes_no_file(monkeypatch):
    """The preset's defaults reach draccus in memory (they once went through a temporary
    JSON file per parse)."""
    from ccfit.config import CurriculumConfig, TaskRunConfig
    from ccfit.config_parse import parse_cli
    from ccfit.offline.config import OfflineConfig

    def refuse(*args, **kwargs):
        raise AssertionError("a temporary file was made while parsing")

    for name in ("NamedTemporaryFile", "TemporaryFile", "SpooledTemporaryFile", "mkstemp",
                 "mkdtemp", "TemporaryDirectory"):  # fmt: skip
        monkeypatch.setattr(tempfile, name, refuse)
    assert parse_cli(TaskRunConfig, ["--task", "reach-xy", "--preset", "smoke"]).task == "reach-xy"
    run = parse_cli(CurriculumConfig, ["--suite", "Reach", "--method.type=ewc"])
    assert run.method.type == "ewc"
    assert parse_cli(OfflineConfig, ["--suite", "Reach", "--preset=cpu"]).preset == "cpu"
    again = parse_cli(CurriculumConfig, ["--config_path", str(PUBLISHED)])
    assert again.suite == "Reach"


def test_fit_names_the_option_it_reads_for_seed_dataset(capsys):
    from ccfit.cli import main

    assert main(["fit", "--suite", "Reach", "--seed_dataset", "ccdata/Reach"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("ccfit: error: --seed_dataset is not an option of ccfit fit: the "
                          "offline track reads --dataset")  # fmt: skip


@pytest.mark.parametrize(
    "argv, message",
    [(["--suite", "Reach", "--train.nope=1"], "--train.nope is not an option: see --help"),
     (["--suite", "Reach", "--model.type=pwm", "--model.nope=1"],
      "--model.nope is not an option: see --help"),
     (["--suite", "Reach", "--nope", "1"], "--nope is not an option: see --help"),
     (["--suite"], "--suite takes a value: --suite VALUE"),
     (["--suite", "Reach", "--train", "3"], "--train is a group of options; set its fields")],
)  # fmt: skip
def test_bad_options_are_one_line(argv, message):
    from ccfit.config import CurriculumConfig
    from ccfit.config_parse import parse_cli

    with pytest.raises(ValueError) as raised:  # ConfigError and InputError alike
        parse_cli(CurriculumConfig, argv)
    assert str(raised.value).startswith(message)
    assert "\n" not in str(raised.value)


def test_an_unknown_model_is_named_before_its_options():
    from ccfit.config import CurriculumConfig
    from ccfit.config_parse import parse_cli

    with pytest.raises(ConfigError, match="unknown model"):
        parse_cli(CurriculumConfig, ["--suite", "Reach", "--model.type=nope", "--model.x=1"])


def test_an_option_of_another_command_is_named_as_not_an_option(capsys):
    from ccfit.cli import main

    assert main(["train", "--task", "reach-xy", "--keep-stages", "--out", "runs/x"]) == 2
    assert capsys.readouterr().err == (
        "ccfit: error: --keep_stages is not an option of ccfit train: see --help\n"
    )
