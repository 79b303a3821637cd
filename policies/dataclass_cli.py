"""Command lines generated from a frozen options dataclass (CleanRL style, no extra dependency).

Each field becomes ``--field-name``; its type (``int``, ``float``, ``str``, ``Path``,
``X | None``) parses the value, ``tuple[X, ...]`` fields take several values (given
once or repeated: ``--data A B`` and ``--data A --data B`` are the same), ``bool``
fields become ``--x / --no-x``, fields without a default are required, a field's
``metadata={"flag": "--other"}`` renames its flag, and the help text is the field's
attribute docstring (the string literal written under it), followed by the default::

    @dataclass(frozen=True)
    class Options:
        steps: int = 100
        \"\"\"optimiser steps\"\"\"

    options = parse_dataclass(Options, ["--steps", "5"], prog="tool")

A ``ValueError`` from the dataclass's ``__post_init__`` becomes a usage error (exit 2);
:func:`check_at_least` and :func:`check_choices` write the common ones, naming the flag
(or ``Owner.field``, for a configuration dataclass that is no command's options).

With ``recipes`` (:class:`Recipes`), the command also takes ``--recipe NAME_OR_PATH``: a
file of field values (JSON types: numbers, strings for paths, lists for tuples, null for
None) that replace the defaults, so that the flags given beside it override the recipe
(``riskflow-train --recipe riskflow-default --steps 100``). Its values are checked
against the field types like the flags' (:func:`field_values`).
"""

from __future__ import annotations

import argparse
import ast
import copy
import dataclasses
import inspect
import math
import re
import shlex
import sys
import textwrap
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from riskflow_env.cli_errors import (
    CommandLineParser,
    DefaultsHelpFormatter,
    add_debug_flag,
    run_script,
)
from riskflow_env.config import check_field_types as field_types
from riskflow_env.config import is_integer, is_number

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


@dataclass(frozen=True)
class Recipes:
    """Where ``--recipe NAME_OR_PATH`` reads its values."""

    read: Callable[[str], Mapping[str, Any]]
    """NAME_OR_PATH -> {field: value} as read from the file (OSError or ValueError naming
    what is wrong)"""
    names: tuple[str, ...] = ()
    """the shipped recipes' names, listed in the help"""


def dataclass_parser(
    cls: type,
    prog: str,
    description: str = "",
    recipes: Recipes | None = None,
    debug: bool = False,
) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with one option per field of the dataclass ``cls`` (and
    ``--recipe`` with ``recipes``; ``--debug`` with ``debug``: see
    :mod:`riskflow_env.cli_errors`)."""
    parser = CommandLineParser(prog=prog, description=description, formatter_class=_DefaultsAsTyped)
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
            kwargs.update(nargs="+", type=typing.get_args(hint)[0], action=_Several)
        else:  # X or X | None
            kwargs["type"] = next(
                a for a in typing.get_args(hint) or (hint,) if a is not type(None)
            )
        flag = field.metadata.get("flag", flag_of(field.name))
        parser.add_argument(flag, **kwargs)
    if recipes is not None:
        shipped = f" (shipped: {', '.join(recipes.names)})" if recipes.names else ""
        parser.add_argument(
            "--recipe",
            metavar="NAME_OR_PATH",
            help=f"start from a recipe's values: a shipped recipe's name{shipped} or a .json "
            "file; the options given on the command line override them",
        )
    if debug:
        add_debug_flag(parser)
    return parser


class _DefaultsAsTyped(DefaultsHelpFormatter):
    """Each option's default in its help, a tuple's values as one types them: ``(default:
    0 1 2)``, not ``(default: (0, 1, 2))``. The description keeps its paragraphs and its
    indented blocks (a script's docstring: its command examples); prose is wrapped to the
    terminal."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        blocks = re.split(r"\n\s*\n", text.strip("\n"))
        return "\n\n".join(
            "\n".join(indent + line for line in block.splitlines())
            if any(line[:1].isspace() for line in block.splitlines())
            else super(_DefaultsAsTyped, self)._fill_text(block, width, indent)
            for block in blocks
        )

    def _get_help_string(self, action: argparse.Action) -> str:
        if not action.required and "(default:" in (action.help or ""):  # said in words
            return action.help
        return super()._get_help_string(action)

    def _expand_help(self, action: argparse.Action) -> str:
        if isinstance(action.default, tuple):
            help_text = self._get_help_string(action)  # of the default as it is: () is unset
            action = copy.copy(action)
            action.help = help_text
            action.default = " ".join(str(value) for value in action.default) or "none"
        return super()._expand_help(action)


class _Several(argparse.Action):
    """A ``tuple`` field's values: the first use on a command line replaces the default
    (or the recipe's value), a repeated use adds to it."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # noqa: ANN001
        repeated = getattr(self, "parsing", None) is namespace  # this parse has used it
        before = list(getattr(namespace, self.dest)) if repeated else []
        setattr(namespace, self.dest, before + list(values))
        self.parsing = namespace


def flag_of(name: str) -> str:
    """The flag of the field ``name`` (``--field-name``)."""
    return "--" + name.replace("_", "-")


def _named(name: str, owner: str | None) -> str:
    """How a check names the field ``name``: its flag, or ``owner.name`` with an owner."""
    return flag_of(name) if owner is None else f"{owner}.{name}"


def check_at_least(
    options: Any,
    lows: Mapping[str, int],
    optional: Sequence[str] = (),
    owner: str | None = None,
    highs: Mapping[str, int] | None = None,
) -> None:
    """ValueError naming the flag of the first field of ``options`` in ``lows`` that is not
    an int at least its bound (and at most its bound in ``highs``, where it has one); the
    fields named in ``optional`` may also be None ("not given"). With ``owner`` (a class
    name), the field is named ``owner.field`` instead. A numpy integer is accepted and
    stored as a Python int (bools are not ints)."""
    highs = highs or {}
    for name, low in lows.items():
        value = getattr(options, name)
        if value is None and name in optional:
            continue
        high = highs.get(name)
        if not is_integer(value) or value < low or (high is not None and value > high):
            span = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise ValueError(f"{_named(name, owner)} must be an int {span}, got {value!r}")
        object.__setattr__(options, name, int(value))


def check_sizes(options: Any, names: Sequence[str], low: int = 1, high: int | None = None) -> None:
    """ValueError naming the flag of the first tuple field of ``options`` in ``names`` that
    is empty or holds a value that is not an int in [``low``, ``high``] (e.g. the scene
    counts a benchmark runs, ``--scenes 1 8 32``)."""
    for name in names:
        values = list(getattr(options, name))
        if not values or not all(is_integer(v) and low <= v <= (high or v) for v in values):
            span = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise ValueError(f"{flag_of(name)}: one or more ints {span}, got {values}")


def check_between(
    options: Any, bounds: Mapping[str, tuple[float, float]], owner: str | None = None
) -> None:
    """ValueError naming the flag (or ``owner.field``) of the first field of ``options`` in
    ``bounds`` that is not a finite number with ``low < value <= high`` (an infinite bound
    is no bound)."""
    for name, (low, high) in bounds.items():
        value = getattr(options, name)
        if not (is_number(value) and math.isfinite(value) and low < value <= high):
            span = (
                f" in ({low:g}, {high:g}]"
                if math.isfinite(low) and math.isfinite(high)
                else f" > {low:g}"
                if math.isfinite(low)
                else f" <= {high:g}"
                if math.isfinite(high)
                else ""
            )
            raise ValueError(f"{_named(name, owner)} must be a finite number{span}, got {value!r}")


def passed_options(text: str, option: str, reserved: Iterable[str], why: str) -> list[str]:
    """The command-line words of ``text``, an option (``option``, e.g. ``--extra``) whose
    value a script passes on to another command; ValueError naming ``option`` for text that
    does not split (an open quote) or that sets one of the ``reserved`` flags, which the
    script sets itself (``why`` says so)."""
    try:
        words = shlex.split(text)
    except ValueError as error:
        raise ValueError(f"{option}: {error}") from None
    taken = sorted({word.split("=")[0] for word in words} & set(reserved))
    if taken:
        raise ValueError(f"{option} may not set {taken}: {why}")
    return words


def check_field_types(options: Any, owner: str | None = None) -> None:
    """:func:`riskflow_env.config.check_field_types`, the errors naming the flag (or
    ``owner.field``, as :func:`check_at_least`)."""
    field_types(options, lambda name: _named(name, owner))


def check_choices(
    options: Any, choices: Mapping[str, Sequence[str]], owner: str | None = None
) -> None:
    """ValueError naming the flag (or ``owner.field``, as :func:`check_at_least`) of the
    first field of ``options`` in ``choices`` whose value is not one of its choices."""
    for name, allowed in choices.items():
        value = getattr(options, name)
        if value not in allowed:
            raise ValueError(
                f"{_named(name, owner)} must be one of {tuple(allowed)}, got {value!r}"
            )


def field_values(cls: type, values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` (read from JSON) as the typed field values of the dataclass ``cls``.

    Raises:
        ValueError: naming the field: an unknown field, or a value of another type than
            the field's (an int for an int, a number for a float, a string for a str or
            Path, a list for a tuple, null only for ``X | None``).
    """
    if not isinstance(values, Mapping):
        raise ValueError(f"expected an object of options, got {type(values).__name__}")
    hints = typing.get_type_hints(cls)
    names = [field.name for field in dataclasses.fields(cls)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ValueError(f"unknown option(s) {unknown}; the options are {names}")
    return {name: _typed(hints[name], value, name) for name, value in values.items()}


def from_fields(cls: type[T], source: Any, *, suffix: str = "", **given: Any) -> T:
    """The dataclass ``cls`` with each field read from ``source``'s attribute of the same
    name plus ``suffix`` (e.g. options -> a config), but the fields in ``given``.

    Raises:
        AttributeError: ``source`` lacks an attribute a field asks for.
    """
    names = [field.name for field in dataclasses.fields(cls) if field.name not in given]
    return cls(**{name: getattr(source, name + suffix) for name in names}, **given)


_KINDS = {
    bool: "true or false",
    int: "an int",
    float: "a number",
    str: "a string",
    Path: "a path (a string)",
}


def _typed(hint: Any, value: Any, where: str) -> Any:
    """``value`` as type ``hint`` (:func:`field_values`)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        if not isinstance(value, list):
            raise ValueError(f"{where} must be a list, got {value!r}")
        return tuple(_typed(args[0], item, f"{where}[{i}]") for i, item in enumerate(value))
    if type(None) in args:  # X | None
        if value is None:
            return None
        hint = next(arg for arg in args if arg is not type(None))
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    fits = {
        bool: isinstance(value, bool),
        int: number and isinstance(value, int),
        float: number,
        str: isinstance(value, str),
        Path: isinstance(value, str),
    }
    if hint not in fits:
        raise TypeError(f"{where}: fields of type {hint} cannot be read from a recipe")
    if not fits[hint]:
        raise ValueError(f"{where} must be {_KINDS[hint]}, got {value!r}")
    return hint(value)


def parse_dataclass(
    cls: type[T],
    argv: Sequence[str] | None = None,
    prog: str | None = None,
    description: str = "",
    recipes: Recipes | None = None,
    debug: bool = False,
) -> T:
    """Parse ``argv`` (``sys.argv[1:]`` if None) into an instance of the dataclass ``cls``
    (with ``recipes``, a ``--recipe``'s values replace the defaults; with ``debug``,
    ``--debug`` is accepted and left to the command's error guard)."""
    parser = dataclass_parser(cls, prog or cls.__name__, description, recipes, debug)
    argv = sys.argv[1:] if argv is None else list(argv)
    if recipes is not None:
        _apply_recipe(parser, cls, argv, recipes)
    values = vars(parser.parse_args(argv))
    values.pop("debug", None)  # read by the command's error guard (riskflow_env.cli_errors)
    if recipes is not None:
        del values["recipe"]
    try:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    except ValueError as err:
        parser.error(str(err))


def _apply_recipe(
    parser: argparse.ArgumentParser, cls: type, argv: list[str], recipes: Recipes
) -> None:
    """Set ``parser``'s defaults to the values of the ``--recipe`` in ``argv``, if any (a
    usage error naming the recipe when it cannot be read or does not fit ``cls``)."""
    required = [action for action in parser._actions if action.required]
    for action in required:  # the recipe may give them (--help still says they are needed)
        action.required, action.recipe_may_give = False, True
    name = parser.parse_known_args(argv)[0].recipe
    for action in required:
        action.required = True
    if name is None:
        return
    try:
        raw = recipes.read(name)
    except (OSError, ValueError) as err:  # the message names the file
        parser.error(f"--recipe: {err}")
    try:
        values = field_values(cls, raw)
    except ValueError as err:
        parser.error(f"--recipe {name}: {err}")
    for action in parser._actions:
        if action.dest in values:
            action.required = False
    parser.set_defaults(**values)


def run_main(main: Callable[[T], Any], cls: type[T], prog: str, description: str = "") -> None:
    """The ``__main__`` of a script whose ``main`` takes its options: the command line parsed
    into ``cls`` (``--debug`` declared) and ``main(options)`` run, a user error printed as
    one line (:func:`riskflow_env.cli_errors.run_script`)."""
    run_script(prog, lambda: main(parse_dataclass(cls, None, prog, description, debug=True)))
