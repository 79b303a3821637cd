"""Backend-neutral array helpers: one implementation serves numpy and torch.

Pure functions in this package are written once against the array API standard
(``array_api_compat``), so the same code runs on numpy arrays in the env and on
torch tensors (differentiable, any device) in the policies. This module holds the
few operations the standard lacks.
"""

from __future__ import annotations

from typing import Any

import array_api_compat
import numpy as np

Array = Any  # numpy.ndarray or torch.Tensor


def namespace(*arrays: Array):
    """Array-API namespace shared by ``arrays`` (numpy or torch); python scalars ignored."""
    arrays = tuple(a for a in arrays if not isinstance(a, (int, float, bool)) and a is not None)
    return array_api_compat.array_namespace(*arrays)


def is_torch(x: Array) -> bool:
    """True when ``x`` is a torch tensor."""
    return array_api_compat.is_torch_array(x)


def cummax(x: Array, axis: int = -1) -> Array:
    """Running maximum along ``axis`` (numpy: ``maximum.accumulate``; torch: ``cummax``)."""
    if is_torch(x):
        return x.cummax(dim=axis).values
    return np.maximum.accumulate(x, axis=axis)


def cummin(x: Array, axis: int = -1) -> Array:
    """Running minimum along ``axis``."""
    if is_torch(x):
        return x.cummin(dim=axis).values
    return np.minimum.accumulate(x, axis=axis)


def asarray_like(value: Any, like: Array) -> Array:
    """``value`` as an array of ``like``'s backend, dtype and device."""
    xp = namespace(like)
    return xp.asarray(value, dtype=like.dtype, device=array_api_compat.device(like))
