"""Training recipes: the ``riskflow-train`` options of each shipped checkpoint, as files.

``riskflow-train --recipe NAME_OR_PATH`` starts from a recipe's values; the options given
beside it override them. ``NAME_OR_PATH`` is a shipped recipe's name (this folder's
``NAME.json``) or a path to a ``.json`` file, written the same way::

    {
      "description": "what the recipe trains and how to run it",
      "options": {"data": ["data/train"], "steps": 9500, "lr": 0.001}
    }

``options`` holds ``riskflow-train`` options by field name (``TrainOptions``: ``lr``,
``recovery_parked``, ...), with JSON values: numbers, strings for paths, lists for the
options that take several values, null for none. Relative paths are read from the folder
``riskflow-train`` runs in, as on the command line.

==================  =============================================================
recipe              trains
==================  =============================================================
riskflow-default    ``policies/checkpoints/riskflow_default.pt`` (MeanFlow)
diffusion-default   ``policies/checkpoints/diffusion_default.pt`` (the CTG / CTG++ /
                    CCDiff-style baselines' denoiser)
==================  =============================================================

``tests/policies/test_recipes.py`` checks that each shipped recipe gives the options
stored in its checkpoint, so that the two cannot drift apart.
"""

from __future__ import annotations

import json
import os
from importlib import resources
from pathlib import Path
from typing import Any

SUFFIX = ".json"
KEYS = ("description", "options")


def shipped_recipes() -> tuple[str, ...]:
    """The names of the recipes shipped in this folder, sorted."""
    folder = resources.files(__name__)
    return tuple(
        sorted(item.name[: -len(SUFFIX)] for item in folder.iterdir() if item.name.endswith(SUFFIX))
    )


def recipe_text(name_or_path: str | os.PathLike) -> tuple[str, str]:
    """``(where, text)`` of a recipe: a shipped one by name, or a ``.json`` file.

    Raises:
        FileNotFoundError: no such file, or no shipped recipe of that name (the shipped
            names are listed).
    """
    text = os.fspath(name_or_path)
    if text.endswith(SUFFIX) or os.sep in text or (os.altsep and os.altsep in text):
        path = Path(text)
        if not path.is_file():
            raise FileNotFoundError(f"no recipe file at {path}")
        return str(path), path.read_text(encoding="utf-8")
    resource = resources.files(__name__).joinpath(text + SUFFIX)
    if not resource.is_file():
        raise FileNotFoundError(
            f"no shipped recipe named {text!r} (shipped: {', '.join(shipped_recipes())}); "
            f"a recipe file needs the {SUFFIX} suffix"
        )
    return f"policies/recipes/{text}{SUFFIX}", resource.read_text(encoding="utf-8")


def read_recipe(name_or_path: str | os.PathLike) -> dict[str, Any]:
    """The ``options`` of a recipe (module docstring), as read from its JSON.

    Raises:
        FileNotFoundError: see :func:`recipe_text`.
        ValueError: naming the file: not JSON, not an object, a key other than
            ``description`` and ``options``, or ``options`` missing or not an object.
    """
    where, text = recipe_text(name_or_path)
    try:
        recipe = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{where} is not valid JSON: {err}") from None
    if not isinstance(recipe, dict):
        raise ValueError(f"{where} must hold a JSON object, got {type(recipe).__name__}")
    unknown = sorted(set(recipe) - set(KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; a recipe has {list(KEYS)}")
    options = recipe.get("options")
    if not isinstance(options, dict):
        raise ValueError(f"{where}: 'options' must be an object of riskflow-train options")
    return options


__all__ = ["read_recipe", "recipe_text", "shipped_recipes"]
