"""The one exception type for bad user input (unknown names, missing or corrupt data, bad
settings): command-line tools print its message on one line and exit 2. Anything else that
escapes is a bug and keeps its traceback. Also the pieces every command line shares for that:
the exit status, a parser whose usage errors are one line, a script entry point, and the
exit of a command whose reader left (`ccfit sweep --status RUNS | head`)."""

from __future__ import annotations

import argparse
import os
import select
import sys
import textwrap
from collections.abc import Callable, Sequence

EXIT_USAGE = 2
EXIT_PIPE_CLOSED = 128 + 13
"""What a shell reports for a process that SIGPIPE ended: what `head` leaves its writer."""


class CliError(Exception):
    """A problem with the user's input or environment: one line, non-zero exit."""


class InputError(ValueError):
    """Bad input from the user; the message says what and how to fix it."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage error is one line on stderr and exit 2, not the usage block: the
    console scripts' and the repository's scripts' (diagnostics) parser.

    An option is taken spelt with `_` as with `-` between its words (`--repo_id` is
    `--repo-id`), as the config commands of ccfit take theirs: one rule for both CLIs."""

    def error(self, message: str) -> None:
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)

    def parse_known_args(self, args=None, namespace=None):
        args = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args([self._dashed(a) for a in args], namespace)

    def _dashed(self, arg: str) -> str:
        """`arg` with the spelling this parser registered, where it names one of its options
        with `_` for `-`."""
        name, sep, value = arg.partition("=")
        if not name.startswith("--") or "_" not in name:
            return arg
        dashed = name.replace("_", "-")
        return dashed + sep + value if dashed in self._option_string_actions else arg


def add_command(sub, name: str, summary: str, example: str) -> argparse.ArgumentParser:
    """A subcommand of a console script whose --help opens with its summary and a runnable
    example (`sub`: what `add_subparsers` returned)."""
    description = f"{textwrap.fill(summary, 88)}\n\nExample:\n    {example}"
    return sub.add_parser(name, help=summary, description=description,
                          formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip


def run_script(main: Callable[[Sequence[str] | None], object], prog: str,
               argv: Sequence[str] | None = None) -> int:  # fmt: skip
    """A script's entry point: `main(argv)` (None: sys.argv); an InputError it raises (a
    missing or corrupt run directory, an unknown name) ends it with one line on stderr and
    exit 2."""
    try:
        main(argv)
    except InputError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    return 0


def stdout_reader_gone() -> bool:
    """stdout is a pipe or socket whose reader has left (poll reports an error on it): a
    BrokenPipeError then came from writing output nobody wants, not from a pipe of the
    program's own (a worker's), which is a bug."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by a test, or closed
        return False
    if not hasattr(select, "poll"):  # Windows: no poll; keep the traceback
        return False
    poll = select.poll()
    poll.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poll.poll(0))


def stdout_closed() -> int:
    """The exit of a command whose stdout's reader left: no traceback (the output was not
    wanted, nothing failed). Python's flush of stdout at exit would raise again, so stdout
    now points at /dev/null."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return EXIT_PIPE_CLOSED
