"""Backend-neutral array helpers: one implementation serves numpy and torch.

Pure functions in this package are written once against the array API standard
(``array_api_compat``), so the same code runs on numpy arrays in the env and on
torch tensors (differentiable, any device) in the policies. This module holds the
few operations the standard lacks.
"""

from __future__ import annotations

import functools
import math
import types
from typing import Any

import array_api_compat
import numpy as np

Array = Any  # numpy.ndarray or torch.Tensor


# NumPy >= 2.1 implements the array API standard in its main namespace (cumulative_sum
# included), so numpy inputs get numpy itself (see ``_numpy``): same ufuncs, same results,
# without the compat wrappers' per-call overhead (its ``clip`` alone cost a quarter of an
# env step).
_NUMPY_IS_STANDARD = np.lib.NumpyVersion(np.__version__) >= "2.1.0"
_BY_TYPE: dict[type, Any] = {}  # array type -> namespace, filled on first sight


def _namespace_of_type(x: Array):
    if _NUMPY_IS_STANDARD and isinstance(x, np.ndarray):
        return _numpy
    if array_api_compat.is_torch_array(x):
        return _torch_namespace()
    return array_api_compat.array_namespace(x)


# --- numpy, minus some Python-level wrappers -------------------------------------------
# The env steps arrays of a few hundred elements, where numpy's Python wrappers (np.clip,
# np.stack, np.max, np.take_along_axis, np.astype ...) cost several times the arithmetic. ``_numpy``
# is numpy with those replaced by the ufunc calls they end in: bit-identical results
# (tests/riskflow_env/test_array.py), anything unusual falls back to numpy's own function.


_clip_ufunc = getattr(getattr(np, "_core", None), "umath", np).clip  # numpy >= 2: the ufunc


def _clip(x: Array, /, min: Any = None, max: Any = None) -> Array:  # noqa: A002 (API names)
    # What np.clip ends in (numpy/_core/_methods.py): the clip ufunc, or one-sided
    # maximum / minimum.
    if (min is None and max is None) or not isinstance(x, np.ndarray) or x.dtype.kind != "f":
        return np.clip(x, min, max)
    if max is None:
        return np.maximum(x, min)
    if min is None:
        return np.minimum(x, max)
    return _clip_ufunc(x, min, max)


def _reduction(ufunc: np.ufunc, fallback: Any) -> Any:
    def reduce(x: Array, /, *, axis: Any = None, keepdims: bool = False, **kwargs) -> Array:
        if kwargs or not isinstance(x, np.ndarray):
            return fallback(x, axis=axis, keepdims=keepdims, **kwargs)
        return ufunc.reduce(x, axis=axis, keepdims=keepdims)

    reduce.__doc__ = fallback.__doc__
    return reduce


def _stack(arrays: Any, /, axis: int = 0) -> Array:
    arrays = list(arrays)
    if not arrays or not all(type(a) is np.ndarray for a in arrays):
        return np.stack(arrays, axis=axis)
    ndim = arrays[0].ndim + 1
    if not -ndim <= axis < ndim:
        return np.stack(arrays, axis=axis)  # raises numpy's AxisError
    index = (slice(None),) * (axis % ndim) + (None,)
    return np.concatenate([a[index] for a in arrays], axis=axis)


@functools.lru_cache(maxsize=256)
def _grid(size: int, ndim: int, dim: int) -> np.ndarray:
    """arange(size) shaped to broadcast along dimension ``dim`` of ``ndim``."""
    shape = [1] * ndim
    shape[dim] = size
    grid = np.arange(size).reshape(shape)
    grid.setflags(write=False)
    return grid


def _take_along_axis(x: Array, indices: Array, /, *, axis: int = -1) -> Array:
    ndim = x.ndim
    if not isinstance(x, np.ndarray) or indices.ndim != ndim or not -ndim <= axis < ndim:
        return np.take_along_axis(x, indices, axis=axis)
    axis %= ndim
    index = [_grid(size, ndim, dim) for dim, size in enumerate(x.shape)]
    index[axis] = indices
    return x[tuple(index)]


def _cumulative_sum(x: Array, /, *, axis: Any = None, dtype: Any = None, **kwargs) -> Array:
    if kwargs or axis is None or not isinstance(x, np.ndarray) or x.dtype.kind != "f":
        return np.cumulative_sum(x, axis=axis, dtype=dtype, **kwargs)
    return np.add.accumulate(x, axis=axis, dtype=dtype)


def _astype(x: Array, dtype: Any, /, *, copy: bool = True, device: Any = None) -> Array:
    if type(x) is not np.ndarray or device not in (None, "cpu"):
        return np.astype(x, dtype, copy=copy, device=device)
    return x.astype(dtype, copy=copy)


def _make_numpy_namespace() -> types.ModuleType:
    module = types.ModuleType("numpy", np.__doc__)
    module.__dict__.update({k: v for k, v in vars(np).items() if not k.startswith("__")})
    module.__getattr__ = lambda name: getattr(np, name)  # lazily loaded numpy submodules
    module.clip = _clip
    module.max = _reduction(np.maximum, np.max)
    module.min = _reduction(np.minimum, np.min)
    module.sum = _reduction(np.add, np.sum)
    module.stack = _stack
    module.take_along_axis = _take_along_axis
    module.cumulative_sum = _cumulative_sum
    module.astype = _astype
    return module


_numpy = _make_numpy_namespace()


# --- torch, minus some of the compat layer's Python ------------------------------------
# The policies' closed-form guidance and avoidance steps run dozens of array ops on tensors
# of a few thousand elements, where the compat wrappers' dtype checks cost as much as the
# op (its ``broadcast_arrays`` alone, through ``torch.broadcast_shapes``, was a tenth of a
# planning cycle). ``_torch_namespace()`` is the compat namespace with the hot functions
# calling torch directly where the compat layer would change nothing: tensors of one
# dtype (a 0-D tensor, which torch and the standard promote differently, goes through the
# compat function), Python scalar bounds, an integer axis. Bit-identical results
# (tests/riskflow_env/test_array.py).


def _plain(*values: Any) -> bool:
    """True when no value is a 0-D tensor (torch promotes those as scalars, the standard
    as arrays: the compat function decides) and the tensors among them share one dtype."""
    dtype = None
    for value in values:
        if isinstance(value, (int, float, bool, complex)):
            continue
        if value.ndim == 0 or (dtype is not None and value.dtype != dtype):
            return False
        dtype = value.dtype
    return True


@functools.cache
def _torch_namespace() -> types.ModuleType:
    import torch
    from array_api_compat import torch as compat

    module = types.ModuleType(compat.__name__, compat.__doc__)
    module.__dict__.update({k: v for k, v in vars(compat).items() if not k.startswith("__")})
    module.__getattr__ = lambda name: getattr(compat, name)

    def where(condition: Array, x1: Any, x2: Any, /) -> Array:
        if _plain(x1, x2):
            return torch.where(condition, x1, x2)
        return compat.where(condition, x1, x2)

    def binary(fast: Any, fallback: Any) -> Any:
        def call(x1: Any, x2: Any, /) -> Array:
            if isinstance(x1, torch.Tensor) and isinstance(x2, torch.Tensor) and _plain(x1, x2):
                return fast(x1, x2)
            return fallback(x1, x2)

        call.__doc__ = fallback.__doc__
        return call

    def clip(x: Array, /, min: Any = None, max: Any = None) -> Array:  # noqa: A002
        scalars = all(isinstance(b, float) or b is None for b in (min, max))
        if scalars and x.is_floating_point() and (min, max) != (None, None):
            if not any(b is not None and math.isnan(b) for b in (min, max)):
                return torch.clamp(x, min, max)
        return compat.clip(x, min, max)

    def cumulative_sum(x: Array, /, *, axis: Any = None, dtype: Any = None, **kwargs) -> Array:
        if isinstance(axis, int) and dtype is None and not kwargs and x.is_floating_point():
            return torch.cumsum(x, dim=axis)
        return compat.cumulative_sum(x, axis=axis, dtype=dtype, **kwargs)

    def concat(arrays: Any, /, *, axis: Any = 0) -> Array:
        if isinstance(axis, int):
            return torch.cat(tuple(arrays), dim=axis)
        return compat.concat(arrays, axis=axis)

    def flip(x: Array, /, *, axis: Any = None) -> Array:
        if isinstance(axis, int):
            return torch.flip(x, dims=(axis,))
        return compat.flip(x, axis=axis)

    def sign(x: Array, /) -> Array:
        if x.is_floating_point():  # the standard's sign keeps NaN (torch's gives 0), as +NaN
            return torch.where(torch.isnan(x), torch.abs(x), torch.sign(x))
        return compat.sign(x)

    def sum(x: Array, /, *, axis: Any = None, dtype: Any = None, keepdims: bool = False) -> Array:  # noqa: A001
        if isinstance(axis, int) and dtype is None and x.is_floating_point():
            return torch.sum(x, dim=axis, keepdim=keepdims)
        return compat.sum(x, axis=axis, dtype=dtype, keepdims=keepdims)

    module.where, module.clip, module.cumulative_sum, module.concat = (
        where, clip, cumulative_sum, concat
    )  # fmt: skip
    module.flip, module.sign, module.sum = flip, sign, sum
    module.maximum = binary(torch.maximum, compat.maximum)
    module.minimum = binary(torch.minimum, compat.minimum)
    module.broadcast_arrays = lambda *arrays: tuple(torch.broadcast_tensors(*arrays))
    return module


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


def requires_grad(x: Array) -> bool:
    """True when ``x`` is a torch tensor that autograd is recording (numpy: False)."""
    if type(x) is np.ndarray or not is_torch(x) or not x.requires_grad:
        return False
    import torch  # already imported: x is a tensor

    return torch.is_grad_enabled()


def detach(x: Array) -> Array:
    """``x`` cut from the autograd graph (torch); numpy arrays are returned as they are."""
    return x if type(x) is np.ndarray else x.detach()


def attach_gradient(
    value: Array, x: Array, gradient: Array, axis: int | tuple[int, ...] | None = -1
) -> Array:
    """``value`` with the gradient ``d value / d x = gradient`` attached, for autograd.

    Computes ``value + sum((x - detach(x)) * gradient, axis)``: the added term is
    exactly zero, so the result equals ``value`` (up to the sign of a zero), and its
    gradient with respect to ``x`` is ``gradient``. Lets a function computed without
    autograd (its value and analytic gradient in a few array ops) join a graph as one
    linear node.

    Args:
        value: (...) values computed from ``detach(x)`` (no graph), or a scalar.
        x: (..., D) the inputs, in the graph.
        gradient: (..., D) ``d value / d x`` (no graph), x's shape.
        axis: -1 for one value per (..., D) row of ``x``; a tuple of the trailing axes for
            one value per row of several axes (e.g. ``(-2, -1)``: one per (T, D) plan);
            None for a scalar ``value``.
    """
    xp = namespace(value, x, gradient)
    return value + xp.sum((x - detach(x)) * gradient, axis=axis)


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


def take(table: Array, index: Array) -> Array:
    """``table[index]`` for a 1-D ``table`` and an integer ``index`` of any shape.

    The same values as advanced indexing; torch gathers with ``index_select``, 2-4x faster
    than ``table[index]`` on a CPU, whose generic index kernel was over half the cost of
    the guidance loop's map lookups (numpy's indexing is as fast as ``np.take`` and is kept).
    Gradients flow to ``table`` as with indexing.
    """
    if type(table) is np.ndarray:
        return table[index]
    return table.index_select(0, index.reshape(-1)).reshape(index.shape)


def device(x: Array) -> Any:
    """Device of ``x`` (``array_api_compat.device``; "cpu" for numpy without the lookup)."""
    return "cpu" if type(x) is np.ndarray else array_api_compat.device(x)


def asarray_like(value: Any, like: Array) -> Array:
    """``value`` as an array of ``like``'s backend, dtype and device (a numpy scalar, such
    as one element of an array, is numpy's)."""
    if type(like) is np.ndarray or isinstance(like, np.generic):
        return np.asarray(value, dtype=like.dtype)
    xp = namespace(like)
    return xp.asarray(value, dtype=like.dtype, device=array_api_compat.device(like))
