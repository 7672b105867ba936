"""The one exception type for bad user input (unknown names, missing or corrupt data, bad
settings): command-line tools print its message on one line and exit 2. Anything else that
escapes is a bug and keeps its traceback."""


class InputError(ValueError):
    """Bad input from the user; the message says what and how to fix it."""
