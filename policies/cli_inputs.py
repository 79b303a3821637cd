"""Checks of the inputs the command-line tools share (``riskflow-eval``, ``riskflow-stress``,
the examples): the scene source ``--data`` and the torch ``--device``, each with an error
that names the argument."""

from __future__ import annotations

import torch

from riskflow_env.scenarios import ScenarioBank, shipped_bank
from riskflow_env.scenarios.folders import open_scenes
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset

SHIPPED = "shipped:eval"  # the data source name of the shipped evaluation scenes


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


def check_device(device: str) -> None:
    """ValueError naming ``--device`` unless ``device`` is a torch device this machine has."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(
            f"--device: {device!r} is not a torch device (expected e.g. 'cpu', 'cuda', 'cuda:0')"
        ) from None
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"--device {device}: CUDA is not available on this machine")
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(f"--device {device}: this machine has {count} CUDA device(s)")
    elif parsed.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"--device {device}: MPS is not available on this machine")
    elif parsed.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"--device: {device!r} is not supported (expected cpu, cuda or mps)")


__all__ = ["SHIPPED", "check_device", "open_data"]
