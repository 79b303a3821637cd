"""Command lines generated from a frozen options dataclass (CleanRL style, no extra dependency).

Each field becomes ``--field-name``; its type (``int``, ``float``, ``str``, ``Path``,
``X | None``) parses the value, ``tuple[X, ...]`` fields take several values, ``bool``
fields become ``--x / --no-x``, fields without a default are required, a field's
``metadata={"flag": "--other"}`` renames its flag, and the help text is the field's
attribute docstring (the string literal written under it), followed by the default::

    @dataclass(frozen=True)
    class Options:
        steps: int = 100
        \"\"\"optimiser steps\"\"\"

    options = parse_dataclass(Options, ["--steps", "5"], prog="tool")

A ``ValueError`` from the dataclass's ``__post_init__`` becomes a usage error (exit 2).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import typing
from collections.abc import Sequence
from typing import Any, TypeVar

T = TypeVar("T")


def field_docs(cls: type) -> dict[str, str]:
    """``{field: docstring}`` of the attribute docstrings of a dataclass's fields (those
    of its dataclass bases included)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        docs |= {
            node.target.id: doc.value.value
            for node, doc in zip(body, body[1:], strict=False)
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
            if isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)
        }
    return docs


def dataclass_parser(cls: type, prog: str, description: str = "") -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with one option per field of the dataclass ``cls``."""
    parser = argparse.ArgumentParser(
        prog=prog, description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    hints, docs = typing.get_type_hints(cls), field_docs(cls)
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        kwargs: dict[str, Any] = {"help": docs.get(field.name, " "), "dest": field.name}
        if field.default is dataclasses.MISSING:
            kwargs["required"] = True
        else:
            kwargs["default"] = field.default
        if hint is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(hint) is tuple:
            kwargs.update(nargs="+", type=typing.get_args(hint)[0])
        else:  # X or X | None
            kwargs["type"] = next(
                a for a in typing.get_args(hint) or (hint,) if a is not type(None)
            )
        flag = field.metadata.get("flag", "--" + field.name.replace("_", "-"))
        parser.add_argument(flag, **kwargs)
    return parser


def parse_dataclass(
    cls: type[T], argv: Sequence[str] | None = None, prog: str | None = None, description: str = ""
) -> T:
    """Parse ``argv`` (``sys.argv[1:]`` if None) into an instance of the dataclass ``cls``."""
    parser = dataclass_parser(cls, prog or cls.__name__, description)
    values = vars(parser.parse_args(argv))
    try:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    except ValueError as err:
        parser.error(str(err))
