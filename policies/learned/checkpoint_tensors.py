"""Checks on the tensors of a loaded checkpoint, from their metadata first.

``torch.load(weights_only=True)`` runs no code, but a tensor's sizes and strides are the
file's word: a 2.6 MB file can hold a tensor expanded with stride 0 to 2**28 elements
over a one-element storage, which anything that makes it contiguous (the SHA-256 digest
of :func:`~policies.learned.checkpoint.weights_digest`, ``load_state_dict``) turns into a
1 GiB allocation. :func:`check_tensor_layouts` refuses such tensors from their sizes,
strides and storage alone, before anything reads their values; :func:`check_finite`
refuses NaN or inf weights, naming the tensor.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from policies.learned.generator import CheckpointError

MAX_TENSOR_BYTES = 1024 * 2**20  # [bytes] all tensors of one checkpoint, as their shapes declare
_NAME_CHARS = 120  # [chars] longest tensor name quoted in an error


def check_tensor_layouts(checkpoint: Any, source: str) -> None:
    """Walk ``checkpoint`` (dicts, lists, tuples; each container once) and refuse, with a
    :class:`CheckpointError` naming ``source`` and the tensor, any tensor that is not a
    plain strided one (sparse, quantized, nested), that declares more elements than its
    storage holds (expanded, e.g. with stride 0), or that takes all tensors together past
    :data:`MAX_TENSOR_BYTES`. Reads no tensor value."""
    total = 0
    seen: set[int] = set()
    stack: list[tuple[str, Any]] = [("", checkpoint)]
    while stack:
        name, value = stack.pop()
        if isinstance(value, torch.Tensor):
            total += _declared_bytes(value, name, source)
            if total > MAX_TENSOR_BYTES:
                raise CheckpointError(
                    f"{source}: tensors totalling over {MAX_TENSOR_BYTES} bytes (at "
                    f"{_quote(name)}) exceed the limit MAX_TENSOR_BYTES"
                )
        elif isinstance(value, (Mapping, list, tuple)) and id(value) not in seen:
            seen.add(id(value))
            items = value.items() if isinstance(value, Mapping) else enumerate(value)
            stack.extend((f"{name}[{key!r}]" if name else str(key), item) for key, item in items)


def _declared_bytes(tensor: torch.Tensor, name: str, source: str) -> int:
    """The bytes ``tensor`` declares; CheckpointError unless its storage holds them all."""
    if tensor.layout != torch.strided or tensor.is_quantized or tensor.is_nested:
        raise CheckpointError(
            f"{source}: tensor {_quote(name)} has layout {tensor.layout} (quantized: "
            f"{tensor.is_quantized}); expected a plain dense tensor"
        )
    declared = tensor.numel() * tensor.element_size()
    stored = tensor.untyped_storage().nbytes()
    if declared > stored:
        raise CheckpointError(
            f"{source}: tensor {_quote(name)} of shape {tuple(tensor.shape)} and strides "
            f"{tensor.stride()} declares {declared} bytes over a storage of {stored} "
            "(an expanded tensor); expected a dense one"
        )
    return declared


def check_finite(state_dict: Mapping[str, torch.Tensor], source: str) -> None:
    """CheckpointError naming ``source`` and the first tensor of ``state_dict`` that holds
    NaN or inf (weights that would make every plan non-finite)."""
    for name in sorted(state_dict):
        tensor = state_dict[name]
        if isinstance(tensor, torch.Tensor) and (tensor.is_floating_point() or tensor.is_complex()):
            bad = int((~torch.isfinite(tensor)).sum())
            if bad:
                raise CheckpointError(
                    f"{source}: weight tensor state_dict[{_quote(repr(name))}] holds {bad} NaN "
                    "or inf value(s)"
                )


def _quote(name: str) -> str:
    """``name`` (a path such as ``state_dict['encoder.weight']``), cut to a readable length."""
    return name if len(name) <= _NAME_CHARS else name[:_NAME_CHARS] + "..."


__all__ = ["MAX_TENSOR_BYTES", "check_finite", "check_tensor_layouts"]
