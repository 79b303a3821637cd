"""Every option of every command line (examples, benchmarks, console scripts) has help text
that shows its default."""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from policies.dataclass_cli import dataclass_parser
from policies.evaluation.cli import parser as eval_parser
from policies.evaluation.cli import report_parser
from policies.stress.cli import compare_parser as stress_compare_parser
from policies.stress.cli import parser as stress_parser
from policies.stress.cli import replay_parser as stress_replay_parser
from policies.train import parser as train_parser
from riskflow_env.scenarios.cli import build_parser as data_parser
from tests.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
HELPERS = ("benchmarks/methods.py", "benchmarks/timing.py")  # imported by the scripts
SCRIPTS = sorted(
    str(path.relative_to(ROOT)) for folder in ("examples", "benchmarks")
    for path in (ROOT / folder).glob("*.py") if str(path.relative_to(ROOT)) not in HELPERS
)  # fmt: skip
NEEDS_RL = ("examples/train_ego_ppo.py", "examples/train_adversaries_marl.py")
NEEDS_TORCHRL = ("examples/train_ego_torchrl.py",)


def _script_parser(relative: str) -> argparse.ArgumentParser:
    if relative in NEEDS_RL:
        pytest.importorskip("stable_baselines3", reason="the rl extra is not installed")
    if relative in NEEDS_TORCHRL:
        pytest.importorskip("torchrl", reason="the torchrl extra is not installed")
    module = load_script(relative)
    return dataclass_parser(module.Options, Path(relative).name)


def _actions(parser: argparse.ArgumentParser):
    """(parser, action) of every option and positional, subcommands included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _actions(sub)
        elif not isinstance(action, argparse._HelpAction):
            yield parser, action


def _check(parser: argparse.ArgumentParser) -> None:
    for owner, action in _actions(parser):
        name = "/".join(action.option_strings) or action.dest
        assert action.help and action.help.strip(), f"{owner.prog} {name}: no help text"
        if action.option_strings:
            shown = owner._get_formatter()._get_help_string(action)
            said = "%(default)" in shown or "(default:" in shown  # in words, once
            if action.required:  # no default: says so instead
                said = "(required" in shown and "default" not in shown
            assert said, f"{owner.prog} {name}: the default (or that it is required) is not shown"


@pytest.mark.parametrize("relative", SCRIPTS)
def test_script_options_have_help_and_defaults(relative):
    _check(_script_parser(relative))


@pytest.mark.parametrize(
    "build",
    [
        data_parser,
        train_parser,
        eval_parser,
        report_parser,
        stress_parser,
        stress_compare_parser,
        stress_replay_parser,
    ],
    ids=[
        "riskflow-data",
        "riskflow-train",
        "riskflow-eval",
        "riskflow-eval report",
        "riskflow-stress",
        "riskflow-stress compare",
        "riskflow-stress replay",
    ],
)
def test_console_script_options_have_help_and_defaults(build):
    _check(build())


@dataclass(frozen=True)
class _Several:
    seeds: tuple[int, ...] = (0, 1, 2)
    """noise seeds"""
    formats: tuple[str, ...] = ()
    """formats"""


def test_a_tuple_default_shows_as_typed():
    shown = " ".join(dataclass_parser(_Several, "prog").format_help().split())
    assert "noise seeds (default: 0 1 2)" in shown and "formats (default: none)" in shown


def test_a_description_keeps_its_command_examples_and_wraps_its_prose(monkeypatch):
    """A script's docstring as ``--help``'s description: paragraphs and indented command
    lines as written, prose wrapped to the terminal."""

    @dataclass(frozen=True)
    class Options:
        seed: int = 0
        """a seed"""

    monkeypatch.setenv("COLUMNS", "60")
    prose = "word " * 30
    command = "python run.py --seed 1 --out a/very/long/folder/name/of/a/run"
    doc = f"Title line.\n\n    {command}\n\n{prose}\n"
    text = dataclass_parser(Options, "run.py", doc).format_help()
    assert f"\n    {command}\n" in text
    body = text.split("Title line.")[1].split("options:")[0]
    prose_lines = [line for line in body.splitlines() if line.startswith("word")]
    assert len(prose_lines) > 1 and all(len(line) <= 60 for line in prose_lines)


def test_an_option_a_recipe_may_give_says_so_once(capsys):
    """``riskflow-train --help`` is printed while a recipe may still give ``--data``: the
    option says it is required unless a recipe gives it, and shows no default."""
    from policies.train import parse_options

    with pytest.raises(SystemExit):
        parse_options(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    data = text.split("--data DATA [DATA ...]")[-1].split("--data-weights")[0]
    assert "(required, unless --recipe gives it)" in data and "default" not in data


def test_positionals_are_not_marked_required():
    """A positional must be given anyway: its help says what it is, not "(required)"."""
    shown = " ".join(stress_replay_parser().format_help().split())
    assert "a replay file (failures/*.npz of a run)" in shown
    assert "of a run) (required)" not in shown



DEFAULT_IN_WORDS = re.compile(r"(?:^|[;,:]\s)\s*default\b")  # "; default: X", not "its default"


def test_a_default_said_in_words_is_shown_once():
    """An option whose help says its default in words (``...; default: the shipped
    evaluation scenes``) shows it once, in argparse's form: not also ``(default: None)``."""
    parsers = [build() for build in (eval_parser, stress_parser, stress_replay_parser)]
    parsers += [train_parser(), data_parser()]
    for relative in SCRIPTS:
        if relative not in NEEDS_RL + NEEDS_TORCHRL:
            parsers.append(_script_parser(relative))
    for parser in parsers:
        for owner, action in _actions(parser):
            if not action.option_strings:
                continue
            shown = owner._get_formatter()._get_help_string(action)
            words = shown.replace("(default: %(default)s)", "")
            assert not (DEFAULT_IN_WORDS.search(words) and words != shown), (
                f"{owner.prog} {action.option_strings[0]}: the default is said twice: {shown!r}"
            )
        rendered = " ".join(parser.format_help().split())
        assert not re.search(r"default:[^()]*\(default:", rendered), parser.prog
    shown = " ".join(eval_parser().format_help().split())
    assert "(default: the shipped evaluation scenes)" in shown
