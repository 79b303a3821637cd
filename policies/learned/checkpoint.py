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

``save_checkpoint`` adds ``kind`` (``"meanflow"`` or ``"diffusion"``, from
``train_config["generator"]``) and ``weights_sha256`` (:func:`weights_digest`: SHA-256
of every ``state_dict`` tensor's name, dtype, shape and bytes). :func:`load_checkpoint`
verifies the digest (a damaged file raises :class:`CheckpointError`; a file written
before digests existed loads with a warning), and :func:`load_generator` refuses a
file of another kind and floating-point weights that are not float32.

Files are written to a temporary name in the target folder and renamed (atomic), so
an interrupted save never leaves a truncated checkpoint. The shipped checkpoint
(``policies/checkpoints/riskflow_default.pt``) has no ``training`` entry.
"""

from __future__ import annotations

import copy
import hashlib
import os
import re
import subprocess
import threading
import warnings
from collections.abc import Mapping
from contextlib import ExitStack
from importlib import resources
from pathlib import Path
from typing import Any

import torch

from policies.learned.checkpoint_tensors import check_finite, check_tensor_layouts
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import CheckpointError, RiskFlowGenerator
from riskflow_env.atomic_files import atomic_file
from riskflow_env.folder_lock import make_output_file

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


def weights_digest(state_dict: Mapping[str, Any]) -> str:
    """SHA-256 hex digest of a state dict: every tensor's name, dtype, shape and bytes."""
    digest = hashlib.sha256()
    for name in sorted(state_dict):
        tensor = state_dict[name]
        if not isinstance(tensor, torch.Tensor):
            raise CheckpointError(f"state_dict entry {name!r} is a {type(tensor).__name__}")
        tensor = tensor.detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def checkpoint_kind(checkpoint: Mapping[str, Any]) -> str:
    """``"meanflow"`` or ``"diffusion"``: the stored ``kind``, else ``train_config``'s."""
    kind = checkpoint.get("kind")
    if kind is None:
        train_config = checkpoint.get("train_config")
        kind = train_config.get("generator") if isinstance(train_config, Mapping) else None
    return kind or "meanflow"


def save_checkpoint(checkpoint: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """``torch.save`` to ``path``, atomically (:mod:`riskflow_env.atomic_files`).

    A checkpoint with a ``state_dict`` gets ``kind`` and ``weights_sha256`` added."""
    checkpoint = dict(checkpoint)
    if isinstance(checkpoint.get("state_dict"), Mapping):
        checkpoint["kind"] = checkpoint_kind(checkpoint)
        checkpoint["weights_sha256"] = weights_digest(checkpoint["state_dict"])
    path = make_output_file(path)
    with atomic_file(path) as file:
        torch.save(dict(checkpoint), file)
    return path


def load_checkpoint(path: str | os.PathLike, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read a checkpoint file (``weights_only``: no code is unpickled).

    Every tensor is checked from its metadata before any value is read
    (:func:`~policies.learned.checkpoint_tensors.check_tensor_layouts`: no expanded or
    sparse tensors, at most ``MAX_TENSOR_BYTES`` in all), then the digest is verified and
    the weights must be finite.

    Raises:
        FileNotFoundError: no file at ``path``.
        CheckpointError: the file is not a generator checkpoint, or one of the above
            checks fails (the message names the file and the tensor).
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a generator checkpoint file")
    if not path.is_file():
        raise FileNotFoundError(f"no generator checkpoint at {path}")
    with path.open("rb") as file:
        head = file.read(4)
    if head and not head.startswith((b"PK\x03\x04", b"\x80")):  # a zip, or a legacy pickle
        raise CheckpointError(
            f"cannot read generator checkpoint {path}: not a file written by torch.save"
        )
    try:
        with warnings.catch_warnings():  # a foreign pickle's protocol: the error says enough
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            checkpoint = torch.load(path, map_location=device, weights_only=True)
    except Exception as err:  # torch raises several types for corrupt or foreign files
        raise CheckpointError(
            f"cannot read generator checkpoint {path}: {load_failure(err)}"
        ) from None
    if not isinstance(checkpoint, dict):
        raise CheckpointError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict")
    check_tensor_layouts(checkpoint, str(path))
    verify_weights(checkpoint, str(path))
    if isinstance(checkpoint.get("state_dict"), Mapping):
        check_finite(checkpoint["state_dict"], str(path))
    return checkpoint


def load_failure(error: Exception) -> str:
    """What ``torch.load(weights_only=True)``'s ``error`` says of a file, in one short line.

    The safe loader refuses any file that is not a ``torch.save`` of tensors and plain
    values (a text file, a foreign pickle, a saved module or numpy array); its message then
    advises loading the file unsafely or allowlisting what it holds, which a generator
    checkpoint never calls for, so only what it refused is kept."""
    text = " ".join(str(error).split())
    if isinstance(error, EOFError) and not text:  # an empty or cut-off file
        return "the file is empty or truncated (EOFError)"
    if isinstance(error, KeyError) or "inline_container" in text:  # a zip, not torch.save's
        return "not a file written by torch.save"
    if "Weights only load failed" not in text and "WeightsUnpickler error" not in text:
        return text[:300]
    refused = re.search(r"Unsupported global: GLOBAL (\S+)", text)
    if refused:
        what = f"it holds {refused.group(1)}"
    else:
        what = text.split("WeightsUnpickler error:")[-1].split(" Check the documentation")[0]
        what = what.split(" Please ")[0].strip()[:120]
    return f"the safe loader refuses it ({what}); a checkpoint holds tensors and plain values"


def verify_weights(checkpoint: Mapping[str, Any], source: str = "checkpoint") -> None:
    """Check ``weights_sha256`` against the state dict (CheckpointError when they differ);
    a checkpoint without one (written before digests existed) only warns."""
    state = checkpoint.get("state_dict")
    if not isinstance(state, Mapping):
        return
    expected = checkpoint.get("weights_sha256")
    if expected is None:
        warnings.warn(
            f"{source}: checkpoint has no weights_sha256 (written by an older version); "
            "its weights cannot be verified",
            UserWarning,
            stacklevel=3,
        )
        return
    try:
        found = weights_digest(state)
    except CheckpointError as err:
        raise CheckpointError(f"{source}: {err}") from None
    if found != expected:
        raise CheckpointError(
            f"{source}: the weights do not match the stored weights_sha256 (damaged or "
            f"altered file): expected {expected}, got {found}"
        )


def normalizer_of(checkpoint: Mapping[str, Any]) -> ActionNormalizer:
    """The checkpoint's action statistics; :class:`CheckpointError` if missing or malformed."""
    data = checkpoint.get("normalizer")
    if not isinstance(data, Mapping) or any(
        not isinstance(data.get(key), (list, tuple)) or len(data[key]) > 2
        for key in ("mean", "std")
    ):
        raise CheckpointError(
            "checkpoint 'normalizer' must hold 'mean' and 'std' lists of 2 numbers"
        )
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
    checkpoint = read_checkpoint(
        path, DEFAULT_NAME, "generator", "`riskflow-train` (docs/how-to/train-generator.md)"
    )
    kind = checkpoint_kind(checkpoint)
    if kind != "meanflow":
        raise CheckpointError(
            f"{path or DEFAULT_NAME} is a {kind!r} checkpoint, not a MeanFlow generator; load "
            "it with policies.baselines.diffusion.model.load_diffusion (or load_base_generator)"
        )
    try:
        return frozen_generator(checkpoint, config, device)
    except CheckpointError as err:
        raise CheckpointError(f"{path or DEFAULT_NAME}: {err}") from None


def read_checkpoint(
    path: str | os.PathLike | None, default_name: str, what: str, how_to_train: str
) -> dict[str, Any]:
    """:func:`load_checkpoint` of ``path``, or of the shipped
    ``policies/checkpoints/<default_name>`` when ``path`` is None (a FileNotFoundError
    names the ``what`` checkpoint and ``how_to_train`` one when it is not shipped); a file
    is read once per process while it is unchanged (:func:`_read_once`)."""
    with ExitStack() as stack:
        if path is None:
            resource = resources.files("policies").joinpath("checkpoints", default_name)
            if not resource.is_file():
                raise FileNotFoundError(
                    f"the shipped {what} checkpoint policies/checkpoints/{default_name} is "
                    f"missing; train one with {how_to_train} and pass its path"
                )
            path = stack.enter_context(resources.as_file(resource))
        return _read_once(Path(path))


_READ: dict[tuple, dict[str, Any]] = {}  # (path, mtime, ctime, size, inode) -> checkpoint
_READ_LOCK = threading.Lock()
READ_CACHE_SIZE = 4  # checkpoint files kept read in a process


def _read_once(path: Path) -> dict[str, Any]:
    """:func:`load_checkpoint` of ``path``, read and verified once per process while the
    file is unchanged (an evaluation builds a policy per rollout). The caller gets its own
    copy of everything but the state dict's tensors, which it must not change in place
    (the models copy them in ``load_state_dict``)."""
    try:
        stat = path.stat()
    except OSError:
        return load_checkpoint(path)  # its error names the file
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_ctime_ns, stat.st_size, stat.st_ino)
    with _READ_LOCK:
        checkpoint = _READ.get(key)
        if checkpoint is None:
            checkpoint = load_checkpoint(path)
            if len(_READ) >= READ_CACHE_SIZE:
                _READ.pop(next(iter(_READ)))
            _READ[key] = checkpoint
    return {
        name: dict(value) if name == "state_dict" else copy.deepcopy(value)
        for name, value in checkpoint.items()
    }


def checkpoint_digest(path: str | os.PathLike) -> str:
    """The ``weights_sha256`` of the checkpoint file at ``path`` (computed for a file
    written before digests were stored); read once per process while unchanged."""
    checkpoint = _read_once(Path(path))
    stored = checkpoint.get("weights_sha256")
    if isinstance(stored, str):
        return stored
    state = checkpoint.get("state_dict")
    if not isinstance(state, Mapping):
        raise CheckpointError(f"{path} holds no state_dict")
    return weights_digest(state)


def frozen_generator(
    checkpoint: Mapping[str, Any], config: ModelConfig | None, device: torch.device | str
) -> tuple[RiskFlowGenerator, ActionNormalizer, dict[str, Any]]:
    """The checkpoint's network on ``device`` in ``eval()`` mode without gradients, its
    action normalizer and its ``METADATA_KEYS`` entries (None if absent)."""
    model = RiskFlowGenerator.from_checkpoint(checkpoint, config)
    model = model.to(device).eval().requires_grad_(False)
    metadata = {key: checkpoint.get(key) for key in METADATA_KEYS}
    return model, normalizer_of(checkpoint), metadata


__all__ = [
    "DEFAULT_NAME",
    "build_checkpoint",
    "checkpoint_kind",
    "code_version",
    "frozen_generator",
    "load_checkpoint",
    "load_generator",
    "normalizer_of",
    "read_checkpoint",
    "save_checkpoint",
    "verify_weights",
    "weights_digest",
]
