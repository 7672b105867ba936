"""The one exception type for bad user input (unknown names, missing or corrupt data, bad
settings): command-line tools print its message on one line and exit 2. Anything else that
escapes is a bug and keeps its traceback. Also the pieces every command line shares for that:
the exit status, a parser whose usage errors are one line, and a script entry point."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

EXIT_USAGE = 2


class InputError(ValueError):
    """Bad input from the user; the message says what and how to fix it."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage error is one line on stderr and exit 2, not the usage block: the
    console scripts' and the repository's scripts' (diagnostics) parser."""

    def error(self, message: str) -> None:
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


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
