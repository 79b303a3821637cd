"""Generator checkpoint files: atomic writing, training state, and :func:`load_generator`.

A file is one ``torch.save`` dict, read back with ``torch.load(weights_only=True)``:

==================  ==========================================================
key                 content
==================  ==========================================================
format, config,     ``RiskFlowGenerator.checkpoint()`` of the **EMA** weights, so
state_dict          ``RiskFlowGenerator.from_checkpoint(file)`` rebuilds the model
normalizer          ``ActionNormalizer.to_dict()``: the action statistics of training
version             ``{"riskflow_env": __version__, "git_commit", "git_dirty"}``
train_config        the training options (``train.TrainOptions``) as plain values
step, metrics       optimiser steps done; latest training and validation metrics
training            only in resumable files: raw weights, optimiser, RNG states,
                    elapsed training time [s]
==================  ==========================================================

Files are written to a temporary name in the target folder and renamed (atomic), so
an interrupted save never leaves a truncated checkpoint. The shipped checkpoint
(``policies/checkpoints/riskflow_default.pt``) has no ``training`` entry.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from collections.abc import Mapping
from contextlib import ExitStack
from importlib import resources
from pathlib import Path
from typing import Any

import torch

from policies.riskflow.config import ModelConfig
from policies.riskflow.data import ActionNormalizer
from policies.riskflow.generator import CheckpointError, RiskFlowGenerator

DEFAULT_NAME = "riskflow_default.pt"
METADATA_KEYS = ("version", "train_config", "step", "metrics")


def code_version() -> dict[str, Any]:
    """``riskflow_env.__version__`` and, inside a git checkout, the commit and a dirty flag."""
    import riskflow_env

    version: dict[str, Any] = {
        "riskflow_env": riskflow_env.__version__,
        "git_commit": None,
        "git_dirty": None,
    }
    root = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        )
        if commit.returncode == 0:
            version["git_commit"] = commit.stdout.strip()
            status = subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no"],
                cwd=root,
                capture_output=True,
                text=True,
                timeout=10,
            )
            version["git_dirty"] = bool(status.stdout.strip()) if status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return version


def build_checkpoint(
    ema_model: RiskFlowGenerator,
    normalizer: ActionNormalizer,
    *,
    step: int,
    train_config: Mapping[str, Any],
    metrics: Mapping[str, Any],
    training: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The checkpoint dict (see the module docstring); ``training=None`` for a slim file."""
    checkpoint = ema_model.checkpoint()
    checkpoint.update(
        normalizer=normalizer.to_dict(),
        version=code_version(),
        train_config=dict(train_config),
        step=int(step),
        metrics=dict(metrics),
    )
    if training is not None:
        checkpoint["training"] = dict(training)
    return checkpoint


def save_checkpoint(checkpoint: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """``torch.save`` to a temporary file beside ``path``, then rename it (atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as file:
            torch.save(dict(checkpoint), file)
            file.flush()
            os.fsync(file.fileno())
        os.chmod(temporary, 0o644)  # mkstemp makes it private
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read a checkpoint file (``weights_only``: no code is unpickled).

    Raises:
        FileNotFoundError: no file at ``path``.
        CheckpointError: the file is not a generator checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no generator checkpoint at {path}")
    try:
        checkpoint = torch.load(path, map_location=device, weights_only=True)
    except Exception as err:  # torch raises several types for corrupt or foreign files
        raise CheckpointError(f"cannot read generator checkpoint {path}: {err}") from err
    if not isinstance(checkpoint, dict):
        raise CheckpointError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict")
    return checkpoint


def normalizer_of(checkpoint: Mapping[str, Any]) -> ActionNormalizer:
    """The checkpoint's action statistics; :class:`CheckpointError` if missing or malformed."""
    try:
        return ActionNormalizer.from_dict(checkpoint["normalizer"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint has no valid action normalizer: {err!r}") from None


def load_generator(
    path: str | os.PathLike | None = None,
    device: torch.device | str = "cpu",
    config: ModelConfig | None = None,
) -> tuple[RiskFlowGenerator, ActionNormalizer, dict[str, Any]]:
    """Load a generator for sampling: ``(model, normalizer, metadata)``.

    Args:
        path: a checkpoint file; None loads the shipped
            ``policies/checkpoints/riskflow_default.pt``.
        device: where the model goes.
        config: optional expected architecture (a mismatch raises, naming the fields).

    Returns:
        The EMA model in ``eval()`` mode without gradients, its action normalizer, and
        ``{"version", "train_config", "step", "metrics"}`` of the file (None if absent).

    Raises:
        FileNotFoundError: no such file (for the default: the checkpoint was not shipped).
        CheckpointError: the file does not fit the model (names the mismatch).
    """
    with ExitStack() as stack:
        if path is None:
            resource = resources.files("policies").joinpath("checkpoints", DEFAULT_NAME)
            if not resource.is_file():
                raise FileNotFoundError(
                    f"the shipped generator checkpoint policies/checkpoints/{DEFAULT_NAME} is "
                    "missing; train one with `riskflow-train` (README: Generator training) "
                    "and pass its path"
                )
            path = stack.enter_context(resources.as_file(resource))
        checkpoint = load_checkpoint(path)
    model = RiskFlowGenerator.from_checkpoint(checkpoint, config)
    model = model.to(device).eval().requires_grad_(False)
    metadata = {key: checkpoint.get(key) for key in METADATA_KEYS}
    return model, normalizer_of(checkpoint), metadata


__all__ = [
    "DEFAULT_NAME",
    "build_checkpoint",
    "code_version",
    "load_checkpoint",
    "load_generator",
    "normalizer_of",
    "save_checkpoint",
]
