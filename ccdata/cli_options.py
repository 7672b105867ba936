"""Command-line options made from a settings dataclass: each field's name, type, default and
docstring become its option, so a setting's default and meaning are written once, on the field.

    add_field_options(parser, GenerateConfig, ("suite", "episodes", "seed"))
    config = GenerateConfig(**field_values(parser.parse_args(argv), ("suite", "episodes", "seed")))

A field `image_size` is the option `--image-size` (also `--image_size`: `OneLineParser`).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its docstring (the string under the field), over `cls` and its bases."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        (node,) = ast.parse(textwrap.dedent(inspect.getsource(klass))).body
        for field, doc in zip(node.body, node.body[1:], strict=False):
            if (
                isinstance(field, ast.AnnAssign)
                and isinstance(field.target, ast.Name)
                and isinstance(doc, ast.Expr)
                and isinstance(doc.value, ast.Constant)
                and isinstance(doc.value.value, str)
            ):
                docs[field.target.id] = " ".join(inspect.cleandoc(doc.value.value).split())
    return docs


def _value_type(hint: Any) -> type:
    """What an option of a field annotated `hint` converts its text to: the first of a union's
    types that is not None (`int | None` -> int); a path is taken as text."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    if hint is Path:
        return str
    if hint not in (int, float, str, bool):
        raise TypeError(f"no command-line option for a field of type {hint!r}")
    return hint


def add_field_options(parser, cls: type, names: Sequence[str],
                      unset: Mapping[str, str] | None = None) -> None:  # fmt: skip
    """Add an option to `parser` (or an argument group) for each field of dataclass `cls` in
    `names`: its type, its default, its docstring as help with the default appended; a field
    without a default is required. `unset`: fields whose option defaults to None (not given)
    because the command decides the value, with what it decides, for the help."""
    unset = unset or {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for name in names:
        field, kind = fields[name], _value_type(hints[name])
        text = docs.get(name, "").replace("%", "%%")  # argparse formats help with %
        option = "--" + name.replace("_", "-")
        if name in unset:
            default: Any = None
            text += f" (default: {unset[name]})"
        elif field.default is not dataclasses.MISSING:
            default = field.default
            if default is not None:
                text += f" (default: {default})"
        else:
            parser.add_argument(option, type=kind, required=True, help=text)
            continue
        if kind is bool:
            parser.add_argument(option, action=argparse.BooleanOptionalAction, default=default,
                                help=text)  # fmt: skip
        else:
            parser.add_argument(option, type=kind, default=default, help=text)


def field_values(args: argparse.Namespace, names: Sequence[str]) -> dict[str, Any]:
    """The parsed values of the options `add_field_options` added for `names`."""
    return {name: getattr(args, name) for name in names}


def parameter_default(fn: Callable, name: str) -> Any:
    """The default of `fn`'s parameter `name`: an option's default where a function, not a
    settings class, holds the setting (`ccdata calibrate --episodes`)."""
    return inspect.signature(fn).parameters[name].default
