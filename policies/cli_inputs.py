"""Checks of the inputs the command-line tools share (``riskflow-eval``, ``riskflow-stress``,
the examples): the scene source ``--data``, the torch ``--device``, a re-planning
interval and a list of seeds, each with an error that names the argument."""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Sequence
from numbers import Integral

import numpy as np
import torch

from riskflow_env.config import DynamicsConfig
from riskflow_env.scenarios import ScenarioBank, shipped_bank
from riskflow_env.scenarios.folders import open_scenes
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset

SHIPPED = "shipped:eval"  # the data source name of the shipped evaluation scenes
DT = DynamicsConfig().dt  # [s] the env's time step
SEED_LIMIT = 2**32  # seeds are below this: numpy's and Stable-Baselines3's bound


def open_data(data: str | None) -> ScenarioBank | ScenarioNetDataset:
    """The scenes of ``--data``: the shipped evaluation bank (None), a folder of ``.npz``
    scenes (loaded) or a ScenarioNet dataset folder (read scene by scene when a rollout
    needs it: :func:`riskflow_env.scenarios.folders.open_scenes`); ValueError naming
    ``--data`` when it is none of them."""
    if data in (None, SHIPPED):
        return shipped_bank("eval")
    try:
        return open_scenes(data)
    except (OSError, ValueError) as err:  # missing, a file, no scenes, a malformed index
        raise ValueError(f"--data: {err}") from err


def check_device(device: str | torch.device, option: str = "--device") -> None:
    """ValueError naming ``option`` unless ``device`` is a torch device this machine has."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(
            f"{option}: {device!r} is not a torch device (expected e.g. 'cpu', 'cuda', 'cuda:0')"
        ) from None
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"{option} {device}: CUDA is not available on this machine")
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(f"{option} {device}: this machine has {count} CUDA device(s)")
    elif parsed.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{option} {device}: MPS is not available on this machine")
    elif parsed.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"{option}: {device!r} is not supported (expected cpu, cuda or mps)")


def check_interval(
    interval: float, dt: float, horizon_s: float | None, option: str = "--interval"
) -> float:
    """A re-planning interval: a positive multiple of ``dt`` [s] within the plan horizon
    ``horizon_s`` [s] (None: no bound); returns it rounded to the step, or a ValueError
    naming ``option``."""
    steps = interval / dt
    if not (math.isfinite(steps) and steps > 0 and math.isclose(steps, round(steps), rel_tol=1e-6)):
        raise ValueError(f"{option}: {interval} s is not a positive multiple of dt = {dt} s")
    if horizon_s is not None and round(steps) > round(horizon_s / dt):
        raise ValueError(f"{option}: {interval} s exceeds the plan horizon {horizon_s:g} s")
    return round(steps) * dt


def check_seeds(seeds: Sequence[int], option: str = "--seeds") -> tuple[int, ...]:
    """``seeds`` as a tuple of ints (numpy integers taken): one or more distinct ints in
    ``[0, 2**32)``, or a ValueError naming ``option`` (a repeated seed would run and count
    the same episodes twice)."""
    values = tuple(seeds)
    if not values or any(
        isinstance(s, (bool, np.bool_)) or not isinstance(s, Integral) or not 0 <= s < SEED_LIMIT
        for s in values
    ):
        raise ValueError(f"{option} must be one or more ints in [0, 2**32), got {list(values)}")
    values = tuple(int(s) for s in values)
    if len(set(values)) != len(values):
        raise ValueError(f"{option} must be distinct, got {list(values)}")
    return values


def parse_seeds(text: str, option: str = "--seeds") -> tuple[int, ...]:
    """The seeds of a comma- or space-separated list (``"0,1,2"``), checked as
    :func:`check_seeds`; a ValueError naming ``option`` otherwise."""
    words = text.replace(",", " ").split()
    if not words or not all(word.isascii() and word.isdigit() for word in words):
        raise ValueError(f"{option} must be comma-separated ints >= 0 (e.g. 0,1,2), got {text!r}")
    return check_seeds([int(word) for word in words], option)


def did_you_mean(name: object, known: Iterable[str]) -> str:
    """`` (did you mean X?)`` for the closest of ``known`` to ``name``, or ``""``."""
    close = difflib.get_close_matches(str(name), list(known), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


__all__ = [
    "DT",
    "SEED_LIMIT",
    "SHIPPED",
    "check_device",
    "check_interval",
    "check_seeds",
    "did_you_mean",
    "open_data",
    "parse_seeds",
]
