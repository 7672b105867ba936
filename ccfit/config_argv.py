"""The command line of a config command (`ccfit train`, `run`, `fit`) read once into options:
the one pass over argv, before any option is given a meaning.

    read_argv(["--suite", "Reach", "--train.steps=10", "--keep-stages"], {"keep_stages": None})
    # {"suite": "Reach", "train.steps": "10", "keep_stages": True}

Which options exist is for the reader of the options to say (`ccfit.config_parse`: the config
tree's fields; `ccfit.cli`: the command's own options).

An option is `--name value` or `--name=value`; words in a name are joined with `_` or `-`
alike (`--image-size` is `--image_size`), the rule of both console scripts. The last of a
repeated option wins.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ccdata.errors import InputError

HELP = ("--help", "-h")


def asks_for_help(argv: Sequence[str]) -> bool:
    return any(a in HELP for a in argv)


def option_name(spelt: str) -> str:
    """The name of an option as the config tree spells it: `--image-size` -> `image_size`."""
    return spelt.removeprefix("--").replace("-", "_")


def read_argv(
    argv: Sequence[str], switches: Mapping[str, str | None] | None = None
) -> dict[str, Any]:
    """Option name -> its text; True for a switch; None where the value is missing (the last
    word, or another option next): whoever knows the option says that it needs one, after
    saying whether it exists. `switches` names the options outside the config tree, with what
    each takes as help shows it (`DIR`), None for one that takes no value (`--quiet`); every
    other option takes a value."""
    switches = switches or {}
    out: dict[str, Any] = {}
    i = 0
    while i < len(argv):
        arg = argv[i]
        i += 1
        spelt, sep, value = arg.partition("=")
        if not spelt.startswith("--") or spelt == "--":
            raise InputError(f"unexpected argument {arg!r}: options are --name VALUE or "
                             "--name=VALUE; see --help")  # fmt: skip
        name = option_name(spelt)
        if name in switches and switches[name] is None:
            if sep:
                raise InputError(f"{spelt} takes no value, got {arg!r}")
            out[name] = True
        elif sep:
            out[name] = value
        elif i < len(argv) and not argv[i].startswith("--"):
            out[name] = argv[i]
            i += 1
        else:
            out[name] = None
    return out


def missing_value(name: str, takes: str = "VALUE") -> InputError:
    """The error of an option given without its value (`read_argv` gave it None)."""
    spelt = "--" + name
    return InputError(f"{spelt} takes a value: {spelt} {takes}")
