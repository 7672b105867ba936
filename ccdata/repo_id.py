"""Hub repo ids (`ORG/NAME`): one check for every command that takes one, so that a dataset
`ccdata generate` writes under LeRobot's cache can also be pushed under the same id."""

from __future__ import annotations

import re

from ccdata.errors import InputError

_NAME_PART = re.compile(r"[A-Za-z0-9_](?:[A-Za-z0-9._-]*[A-Za-z0-9_])?")
_MAX_PART = 96


def validate_repo_id(repo_id: str) -> str:
    """Check that `repo_id` is a Hub dataset id `ORG/NAME` and return it.

    Each part: 1 to 96 characters among letters, digits, `-`, `_`, `.`; starts and ends with a
    letter, digit or `_`; no `--` or `..`; the name does not end in `.git`.
    """
    if not isinstance(repo_id, str):
        raise InputError(f"repo id must be a string like 'ORG/NAME', got {type(repo_id).__name__}")
    parts = repo_id.split("/")
    if len(parts) != 2:
        raise InputError(f"repo id {repo_id!r} must have the form 'ORG/NAME' (exactly one '/')")
    for label, part in zip(("ORG", "NAME"), parts, strict=True):
        if not 1 <= len(part) <= _MAX_PART:
            raise InputError(f"repo id {repo_id!r}: {label} must have 1 to {_MAX_PART} characters")
        if not _NAME_PART.fullmatch(part):
            raise InputError(
                f"repo id {repo_id!r}: {label} may only use letters, digits, '-', '_', '.' and "
                "must start and end with a letter, digit or '_'"
            )
        if "--" in part or ".." in part:
            raise InputError(f"repo id {repo_id!r}: '--' and '..' are not allowed")
    if parts[1].endswith(".git"):
        raise InputError(f"repo id {repo_id!r}: NAME must not end with '.git'")
    return repo_id
