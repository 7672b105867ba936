"""Every subcommand of both console scripts opens its --help with a runnable example, and the
example parses: the contract a new subcommand gets for free."""

from __future__ import annotations

import argparse
import shlex

import pytest

import ccdata.cli
import ccfit.cli


def _subcommands(cli) -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


COMMANDS = [("ccdata", name) for name in _subcommands(ccdata.cli)] + [
    ("ccfit", name) for name in _subcommands(ccfit.cli) if name not in ccfit.cli.CONFIG_COMMANDS
]


def test_the_subcommands_are_all_listed():
    # an empty list would pass every case below unseen
    assert len([c for c in COMMANDS if c[0] == "ccdata"]) == 8
    assert {"report", "publish", "compare", "pretrain-encoder"} <= {n for _, n in COMMANDS}


@pytest.mark.parametrize("script, name", COMMANDS)
def test_help_opens_with_a_runnable_example(script, name):
    cli = ccdata.cli if script == "ccdata" else ccfit.cli
    parser = _subcommands(cli)[name]
    text = parser.format_help()
    summary, _, rest = parser.description.partition("\n\nExample:\n    ")
    assert summary and text.index(summary.splitlines()[0]) < text.index("Example:")
    example = rest.splitlines()[0]
    argv = shlex.split(example)
    assert argv[:2] == [script, name]
    args = cli.build_parser().parse_args(argv[1:])
    assert args.command == name and callable(args.func)


@pytest.mark.parametrize("name", ccfit.cli.CONFIG_COMMANDS)
def test_config_commands_open_with_an_example_that_parses(name):
    from ccfit.config import CurriculumConfig, TaskRunConfig
    from ccfit.config_parse import parse_cli
    from ccfit.offline.config import OfflineConfig

    example = ccfit.cli.CONFIG_COMMANDS[name].__doc__.split("  (")[0]
    argv = shlex.split(example)
    assert argv[:2] == ["ccfit", name]
    if name == "sweep":
        from ccfit.sweep.cli import build_parser

        assert build_parser().parse_args(argv[2:]).suites == ("Reach",)
        assert "\n    ccfit sweep --suites Reach,Grasp" in build_parser().format_help()
        return
    cls = {"train": TaskRunConfig, "run": CurriculumConfig, "fit": OfflineConfig}[name]
    assert isinstance(parse_cli(cls, argv[2:]), cls)
