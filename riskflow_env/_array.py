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


# NumPy >= 2.1 implements the array API standard in its main namespace (cumulative_sum
# included), so numpy inputs get ``numpy`` itself: same ufuncs, same results, without the
# compat wrappers' per-call overhead (its ``clip`` alone cost a quarter of an env step).
_NUMPY_IS_STANDARD = np.lib.NumpyVersion(np.__version__) >= "2.1.0"
_BY_TYPE: dict[type, Any] = {}  # array type -> namespace, filled on first sight


def _namespace_of_type(x: Array):
    if _NUMPY_IS_STANDARD and isinstance(x, np.ndarray):
        return np
    return array_api_compat.array_namespace(x)


def namespace(*arrays: Array):
    """Array-API namespace shared by ``arrays`` (numpy or torch); python scalars ignored.

    The namespace of each array type is looked up once and cached; mixing backends
    raises ``TypeError`` as ``array_api_compat.array_namespace`` does.
    """
    found = None
    for x in arrays:
        if x is None or isinstance(x, (int, float, bool)):
            continue
        kind = type(x)
        xp = _BY_TYPE.get(kind)
        if xp is None:
            xp = _BY_TYPE[kind] = _namespace_of_type(x)
        if found is None:
            found = xp
        elif xp is not found:
            kept = [a for a in arrays if a is not None and not isinstance(a, (int, float, bool))]
            return array_api_compat.array_namespace(*kept)  # raises: mixed backends
    if found is None:
        raise TypeError("namespace requires at least one non-scalar array input")
    return found


def is_torch(x: Array) -> bool:
    """True when ``x`` is a torch tensor."""
    return type(x) is not np.ndarray and array_api_compat.is_torch_array(x)


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
