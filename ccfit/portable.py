"""Paths as a published file holds them: none of the machine that made it.

A run records where things lay on its machine: its own directory (`out`), its from-scratch
reference's (`scratch_dir`), its dataset (`resolved_seed_dataset`, `resolved_dataset`), its
frozen encoder (`encoder`, `frozen:PATH`), the code snapshot that ran it (`code.source`).
`ccfit publish` writes each absolute path in the JSON it copies as:
- under the folder published (`roots`): relative to it, the layout the copy keeps
  (`Reach-tdmpc2-ft-state-cpu-s0`, `scratch/<key>`);
- under the LeRobot home (`$HF_LEROBOT_HOME`, `~/.cache/huggingface/lerobot`): relative to it,
  which is the dataset's repo id (`ccdata/Reach`), from which ccfit finds it there again
  (`ccfit.data.resolve_source`); what it held is recorded beside (`content_sha256`);
- anything else: its name (`frozen:encoder-cpu-s0.safetensors`, `code-958d1c5`); an encoder
  file is identified by its SHA-256 (`resolved_encoder_sha256`), a code snapshot by its commit.

Readers keep working: a reference is found beside a run by its name (`scratch_dir_of`), a run
read back with `--config_path` takes `--out` (its `out` is where it was made), and `ccfit
compare` compares settings in this form (`same_as_published`).
"""

from __future__ import annotations

import functools
import json
import os
import posixpath
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

ABSOLUTE_PATH = re.compile(r"(?<![\w.~/\\-])/[\w.@+=~-]+/[\w.@+=~/-]*")
"""An absolute path of two components or more in a string, alone or inside one (`frozen:/a/b`,
`--x=/a/b`, a message): a `/` that starts it (not one of a URL's `//`, a fraction's or a
relative path's) and what follows it of a path."""
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_LEROBOT_CACHE = ".cache/huggingface/lerobot"
"""LeRobot's default home under a user's home (`$HF_HOME/lerobot`)."""


@functools.cache
def _lerobot_homes() -> tuple[str, ...]:
    """This machine's LeRobot home (as given and resolved); read only when a path needs it."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return tuple(dict.fromkeys((os.path.normpath(HF_LEROBOT_HOME),
                                os.path.realpath(HF_LEROBOT_HOME))))  # fmt: skip


def _under(path: str, root: str) -> str | None:
    """`path` relative to `root` ('.' for the root itself); None when not under it."""
    if path == root:
        return "."
    if root != "/" and path.startswith(root.rstrip("/") + "/"):
        return path[len(root.rstrip("/")) + 1 :]
    return None


def portable_path(path: str, roots: Iterable[str | Path] = ()) -> str:
    """Absolute `path` as published: relative to the first of `roots` holding it, else to the
    LeRobot home holding it, else its name (module docstring)."""
    path = posixpath.normpath(path)
    for root in roots:
        relative = _under(path, posixpath.normpath(str(root)))
        if relative is not None:
            return relative
    cache = f"/{_LEROBOT_CACHE}/"
    if cache in path:
        return path.split(cache, 1)[1]
    for home in _lerobot_homes():
        relative = _under(path, home)
        if relative is not None and relative != ".":
            return relative
    return posixpath.basename(path)


def portable_str(text: str, roots: Iterable[str | Path] = ()) -> str:
    """`text` with each absolute path in it as published (`portable_path`)."""
    roots = _roots(roots)
    return ABSOLUTE_PATH.sub(lambda m: portable_path(m[0], roots), text)


def portable(value: Any, roots: Iterable[str | Path] = ()) -> Any:
    """A JSON value with every string in it (keys too) as `portable_str` writes it."""
    roots = _roots(roots)
    if isinstance(value, str):
        return portable_str(value, roots)
    if isinstance(value, dict):
        return {portable_str(k, roots): portable(v, roots) for k, v in value.items()}
    if isinstance(value, list):
        return [portable(v, roots) for v in value]
    return value


def portable_json(text: str, roots: Iterable[str | Path] = ()) -> str:
    """JSON (or JSON lines) text with every string that holds an absolute path rewritten by
    `portable_str` and nothing else touched: numbers, layout and key order stay byte for byte."""
    roots = _roots(roots)

    def rewrite(m: re.Match) -> str:
        if "/" not in m[0]:
            return m[0]
        value = json.loads(m[0])
        new = portable_str(value, roots)
        return m[0] if new == value else json.dumps(new, ensure_ascii=m[0].isascii())

    return _JSON_STRING.sub(rewrite, text)


def same_as_published(a: Any, b: Any) -> bool:
    """Two settings alike once published (`portable`): a dataset by where it lies under the
    LeRobot home, a file outside the run by its name."""
    return json.dumps(portable(a), sort_keys=True) == json.dumps(portable(b), sort_keys=True)


def _roots(roots: Iterable[str | Path]) -> list[str]:
    """`roots` as normalised absolute paths, the deepest first (a folder inside another one is
    the one a path under both is relative to)."""
    out = {posixpath.normpath(str(r)) for r in roots}
    return sorted(out, key=lambda r: (-r.count("/"), r))
