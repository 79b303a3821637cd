"""Training recipes (``riskflow-train --recipe``): the shipped ones give the options their
checkpoints were trained with; flags override them; a bad recipe is a usage error naming it."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from policies.learned.checkpoint import load_checkpoint
from policies.recipes import read_recipe, shipped_recipes
from policies.train import TrainOptions, parse_options

CHECKPOINTS = Path(__file__).resolve().parents[2] / "policies" / "checkpoints"
SHIPPED = {"riskflow-default": "riskflow_default.pt", "diffusion-default": "diffusion_default.pt"}
# Options of earlier versions that the shipped runs stored, at the value that left them off.
REMOVED = {"recovery_kerbside": 0}


def _plain(value):
    if isinstance(value, tuple):
        return [_plain(item) for item in value]
    return str(value) if isinstance(value, Path) else value


def _folder(path: str | None) -> str | None:
    """A bank folder by its last two parts (the runs wrote absolute paths of their machine)."""
    return None if path is None else "/".join(Path(path).parts[-2:])


def test_every_shipped_checkpoint_has_its_recipe():
    assert set(shipped_recipes()) == set(SHIPPED)


@pytest.mark.parametrize(("recipe", "checkpoint"), SHIPPED.items())
def test_a_shipped_recipe_gives_the_options_stored_in_its_checkpoint(recipe, checkpoint):
    """Every option of ``riskflow-train --recipe NAME`` equals the one stored in the
    shipped file, but for ``out`` (a folder of the machine that trained it) and the time
    budget: a run that its budget stopped is repeated by ``stop_step`` at the stored step."""
    stored = load_checkpoint(CHECKPOINTS / checkpoint)
    run = dict(stored["train_config"])
    for name, off in REMOVED.items():
        assert run.pop(name, off) == off, f"{checkpoint} was trained with {name}"
    defaults = {field.name: _plain(field.default) for field in dataclasses.fields(TrainOptions)}
    assert set(run) <= set(defaults), f"{checkpoint} stores options this version lacks"
    expected = defaults | run  # options added after the run: at their defaults, as it ran
    if expected["time_budget_min"]:
        assert stored["step"] < expected["steps"], "the budget ended the run"
        expected |= {"time_budget_min": 0.0, "stop_step": stored["step"]}
    options = {
        name: _plain(value) for name, value in vars(parse_options(["--recipe", recipe])).items()
    }
    for values in (expected, options):
        del values["out"]
        values["data"] = [_folder(folder) for folder in values["data"]]
        values["val_data"] = _folder(values["val_data"])
    assert options == expected
    assert stored["kind"] == options["generator"]


def test_options_given_beside_a_recipe_override_it():
    options = parse_options(
        ["--recipe", "riskflow-default", "--steps", "9600", "--lr", "0.5", "--data", "mine"]
    )
    assert (options.steps, options.lr, options.data) == (9600, 0.5, (Path("mine"),))
    assert options.recovery_parked == 2 and options.one_step_fraction == 0.25  # the recipe's
    later = parse_options(["--steps", "9600", "--recipe", "riskflow-default", "--data", "mine"])
    assert later.steps == 9600  # wherever --recipe stands


def test_a_repeated_tuple_option_adds_to_itself_and_replaces_the_recipe():
    repeated = parse_options(["--recipe", "riskflow-default", "--data", "a", "--data", "b"])
    once = parse_options(["--recipe", "riskflow-default", "--data", "a", "b"])
    assert repeated.data == once.data == (Path("a"), Path("b"))


def test_a_recipe_file_by_path_gives_the_required_options(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"options": {"data": ["a", "b"], "val_data": "v", "init": None}}))
    options = parse_options(["--recipe", str(path)])
    assert options.data == (Path("a"), Path("b")) and options.val_data == Path("v")
    assert options.init is None and options.steps == TrainOptions.steps  # the rest: defaults
    assert read_recipe(path) == {"data": ["a", "b"], "val_data": "v", "init": None}


@pytest.mark.parametrize(
    ("recipe", "message"),
    [
        ({"options": {"data": ["a"], "lrr": 1}}, r"--recipe \S+: unknown option\(s\) \['lrr'\]"),
        ({"options": {"data": ["a"], "steps": "10"}}, r"--recipe \S+: steps must be an int"),
        ({"options": {"data": ["a"], "steps": 1.5}}, "steps must be an int, got 1.5"),
        ({"options": {"data": ["a"], "lr": True}}, "lr must be a number, got True"),
        ({"options": {"data": "a"}}, "data must be a list, got 'a'"),
        ({"options": {"data": [1]}}, r"data\[0\] must be a path"),
        ({"options": {"data": ["a"], "resume": 1}}, "resume must be true or false"),
        ({"options": {"data": ["a"], "val_data": 3}}, "val_data must be a path"),
        ({"option": {"data": ["a"]}}, r"mine\.json: unknown key\(s\) \['option'\]"),
        ({"description": "no options"}, r"mine\.json: 'options' must be an object"),
        ([1, 2], r"mine\.json must hold a JSON object"),
        ({"options": {"data": ["a"], "steps": 0}}, r"--steps must be an int in \[1, "),
    ],
)
def test_a_bad_recipe_is_a_usage_error_naming_it(recipe, message, tmp_path, capsys):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(recipe))
    with pytest.raises(SystemExit) as exit_info:
        parse_options(["--recipe", str(path)])
    assert exit_info.value.code == 2
    assert re.search(message, capsys.readouterr().err)


@pytest.mark.parametrize(
    ("recipe", "message"),
    [
        ("riskflow-defualt", "no shipped recipe named 'riskflow-defualt' (shipped: "),
        ("missing.json", "no recipe file at missing.json"),
        ("broken.json", "broken.json is not valid JSON"),
    ],
)
def test_a_missing_or_unreadable_recipe_is_a_usage_error_naming_it(
    recipe, message, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "broken.json").write_text('{"options": ')
    with pytest.raises(SystemExit) as exit_info:
        parse_options(["--recipe", recipe, "--data", "a"])
    assert exit_info.value.code == 2
    assert f"--recipe: {message}" in capsys.readouterr().err


def test_without_a_recipe_data_is_still_required(capsys):
    with pytest.raises(SystemExit):
        parse_options([])
    assert "the following arguments are required: --data" in capsys.readouterr().err
