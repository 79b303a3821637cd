"""mkdocs hook: the command-line reference is generated from the parsers at build time.

A page line of the form ``<!-- cli: package.module:function -->`` is replaced by the help of
the ``argparse.ArgumentParser`` that ``function()`` returns, and then by the help of each of
its subcommands, each in a text block under its own heading. The help is formatted 100
columns wide whatever the terminal. Every console script of pyproject.toml's
``[project.scripts]`` must have its module named by a marker in some page, and every marker
must import: otherwise the build fails (``mkdocs build --strict``: a warning is an error).
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
from pathlib import Path

from mkdocs.exceptions import PluginError

MARKER = re.compile(r"^<!-- cli: (?P<module>[\w.]+):(?P<function>\w+) -->$", re.MULTILINE)
WIDTH = "100"  # [columns] of the generated help
HEADING = "####"  # a (sub)command's heading, under the page's ### of the console script

_seen_modules: set[str] = set()


def _help(parser: argparse.ArgumentParser) -> str:
    """``parser``'s help, then its subcommands' (each under a heading), as markdown."""
    blocks = [f"```text\n{parser.format_help().rstrip()}\n```"]
    for action in parser._actions:  # argparse keeps subcommands in a private action type
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                blocks.append(f"{HEADING} `{sub.prog}`\n\n{_help(sub)}")
    return "\n\n".join(blocks)


def _replace(match: re.Match[str]) -> str:
    module, function = match["module"], match["function"]
    try:
        build = getattr(importlib.import_module(module), function)
    except (ImportError, AttributeError) as err:
        raise PluginError(f"cli_reference: cannot import {module}:{function}: {err}") from err
    parser = build()
    if not isinstance(parser, argparse.ArgumentParser):
        raise PluginError(f"cli_reference: {module}:{function}() is not an ArgumentParser")
    _seen_modules.add(module)
    return _help(parser)


def console_scripts(pyproject: Path) -> dict[str, str]:
    """``{name: "module:function"}`` of pyproject.toml's ``[project.scripts]`` table (read
    line by line: ``tomllib`` is Python 3.11+)."""
    section = pyproject.read_text().split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    return dict(re.findall(r'^([\w-]+)\s*=\s*"([\w.:]+)"', section, re.MULTILINE))


def on_pre_build(config) -> None:
    _seen_modules.clear()


def on_page_markdown(markdown: str, page, config, files) -> str:
    if "<!-- cli: " not in markdown:
        return markdown
    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        return MARKER.sub(_replace, markdown)
    finally:
        if previous is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = previous


def on_post_build(config) -> None:
    scripts = console_scripts(Path(config.config_file_path).parent / "pyproject.toml")
    missing = {
        name: target
        for name, target in scripts.items()
        if target.split(":")[0] not in _seen_modules
    }
    if missing:
        raise PluginError(
            "cli_reference: no '<!-- cli: module:function -->' marker for the console "
            f"scripts {missing} (docs/reference/cli.md)"
        )
