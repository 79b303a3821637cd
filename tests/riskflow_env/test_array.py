"""The numpy namespace of ``riskflow_env._array``: identical results to numpy's own functions.

``namespace(numpy_array)`` returns numpy with a few Python-level wrappers (clip, max, min,
sum, stack, take_along_axis, cumulative_sum, astype) replaced by the ufunc calls they end in; these
tests pin that the replacements agree with numpy bit for bit (values, dtype, shape, the
sign of zeros) or raise the same exception type.
"""

from __future__ import annotations

import warnings

import array_api_compat
import numpy as np
import pytest
import torch

from riskflow_env._array import _NUMPY_IS_STANDARD, asarray_like, device, namespace, take

pytestmark = pytest.mark.skipif(
    not _NUMPY_IS_STANDARD, reason="numpy < 2.1 uses the compat namespace"
)

FAST = namespace(np.zeros(1))
DTYPES = (np.float64, np.float32, np.int64, np.int32, np.uint8, np.bool_)
SHAPES = ((), (5,), (3, 4), (2, 3, 4), (0, 3))


def _arrays():
    rng = np.random.default_rng(0)
    for dtype in DTYPES:
        for shape in SHAPES:
            if dtype is np.bool_:
                x = rng.random(shape) > 0.5
            else:
                x = (rng.normal(size=shape) * 10).astype(dtype)
            if x.dtype.kind == "f" and x.size:
                x.flat[0], x.flat[-1] = np.nan, -0.0
            yield x


def _outcome(call):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return call()
        except Exception as error:  # noqa: BLE001 - the exception type is the outcome
            return type(error)


def _assert_same(expected_call, got_call):
    expected, got = _outcome(expected_call), _outcome(got_call)
    if isinstance(expected, type) or isinstance(got, type):
        assert expected is got
        return
    assert type(got) is type(expected)
    expected, got = np.asarray(expected), np.asarray(got)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)
    if got.dtype.kind == "f":
        np.testing.assert_array_equal(np.signbit(got), np.signbit(expected))


def test_namespace_of_numpy_and_torch():
    assert FAST.__name__ == "numpy" and FAST.pi == np.pi and FAST.linalg is np.linalg
    assert namespace(np.zeros(2), 1.0, None) is FAST
    assert namespace(torch.zeros(2)) is not FAST
    with pytest.raises(TypeError):
        namespace(np.zeros(2), torch.zeros(2))
    with pytest.raises(TypeError):
        namespace(1.0, None)


@pytest.mark.parametrize(
    "bounds", [(0.0, 1.0), (None, 2), (-1, None), (0, 0), (2.0, -1.0), (-0.0, 0.0)]
)
def test_clip(bounds):
    for x in _arrays():
        _assert_same(lambda x=x: np.clip(x, *bounds), lambda x=x: FAST.clip(x, *bounds))


@pytest.mark.parametrize("name", ["max", "min", "sum"])
def test_reductions(name):
    for x in _arrays():
        for axis in (None, 0, -1, (0, 1)):
            for keepdims in (False, True):
                _assert_same(
                    lambda x=x, a=axis, k=keepdims: getattr(np, name)(x, axis=a, keepdims=k),
                    lambda x=x, a=axis, k=keepdims: getattr(FAST, name)(x, axis=a, keepdims=k),
                )


def test_stack_take_along_axis_cumulative_sum():
    for x in _arrays():
        for axis in range(-x.ndim - 2, x.ndim + 2):
            _assert_same(
                lambda x=x, a=axis: np.stack([x, x, x], axis=a),
                lambda x=x, a=axis: FAST.stack([x, x, x], axis=a),
            )
            if x.ndim and -x.ndim <= axis < x.ndim:
                _assert_same(
                    lambda x=x, a=axis: np.cumulative_sum(x, axis=a),
                    lambda x=x, a=axis: FAST.cumulative_sum(x, axis=a),
                )
                if x.shape[axis]:
                    index = np.take(np.argsort(x, axis=axis), [0, 1, 0], axis=axis, mode="clip")
                    for idx in (index, index.astype(float)):
                        _assert_same(
                            lambda x=x, i=idx, a=axis: np.take_along_axis(x, i, axis=a),
                            lambda x=x, i=idx, a=axis: FAST.take_along_axis(x, i, axis=a),
                        )
    for arrays in (
        [np.zeros(3), np.zeros(4)],
        [np.zeros((2, 3)), np.zeros((3, 2))],
        [],
        [np.zeros(3), [1, 2, 3]],
    ):
        for axis in (0, -1):
            _assert_same(
                lambda a=arrays, x=axis: np.stack(a, axis=x),
                lambda a=arrays, x=axis: FAST.stack(a, axis=x),
            )


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.bool_])
def test_astype_device_asarray_like(dtype):
    for x in _arrays():
        for copy in (True, False):
            _assert_same(
                lambda x=x, c=copy: np.astype(x, dtype, copy=c),
                lambda x=x, c=copy: FAST.astype(x, dtype, copy=c),
            )
        assert (FAST.astype(x, x.dtype, copy=False) is x) == (
            np.astype(x, x.dtype, copy=False) is x
        )
    like = np.zeros(3, dtype=dtype)
    assert device(like) == "cpu" == array_api_compat.device(like)
    assert asarray_like([1, 0, 2], like).dtype == dtype
    tensor = torch.zeros(3, dtype=torch.float32)
    assert asarray_like([1.0, 2.0], tensor).dtype == torch.float32
    assert device(tensor) == tensor.device


def test_attach_gradient_keeps_the_value_and_sets_the_gradient():
    from riskflow_env._array import attach_gradient, detach, requires_grad

    torch.manual_seed(0)
    x = torch.randn(3, 5, 2, requires_grad=True)
    value, gradient = torch.randn(3, 5), torch.randn(3, 5, 2)
    assert requires_grad(x) and not requires_grad(x.detach()) and not requires_grad(np.ones(2))
    with torch.no_grad():
        assert not requires_grad(x)
    out = attach_gradient(value, x, gradient)
    assert torch.equal(out.detach(), value)
    (grad,) = torch.autograd.grad(out.sum(), x)
    assert torch.equal(grad, gradient)
    scalar = attach_gradient(value.sum(), x, gradient, axis=None)
    assert torch.equal(scalar.detach(), value.sum())
    assert torch.equal(torch.autograd.grad(2.0 * scalar, x)[0], 2.0 * gradient)
    rows = attach_gradient(value.sum(dim=1), x, gradient, axis=(-2, -1))  # one per (5, 2) row
    assert torch.equal(rows.detach(), value.sum(dim=1))
    assert torch.equal(torch.autograd.grad(rows.sum(), x)[0], gradient)
    array = np.ones(3)
    assert detach(array) is array


@pytest.mark.parametrize("shape", [(), (7,), (3, 5), (2, 3, 4), (0, 4)])
def test_take_gathers_what_indexing_gathers(shape):
    rng = np.random.default_rng(1)
    table = rng.normal(size=50)
    index = rng.integers(0, 50, size=shape)
    assert np.array_equal(take(table, index), table[index])
    for dtype in (torch.float64, torch.float32):
        t_table = torch.tensor(table, dtype=dtype, requires_grad=True)
        t_index = torch.as_tensor(index)
        gathered = take(t_table, t_index)
        assert gathered.shape == t_index.shape and gathered.dtype == dtype
        assert torch.equal(gathered, t_table[t_index])
        gathered.sum().backward()  # the gradient reaches the table as with indexing
        counts = np.bincount(index.reshape(-1), minlength=50)
        assert np.array_equal(t_table.grad.numpy(), counts.astype(t_table.grad.numpy().dtype))


def _tensors():
    generator = torch.Generator().manual_seed(0)
    for dtype in (torch.float64, torch.float32, torch.int64, torch.bool):
        for shape in ((), (5,), (3, 4), (2, 3, 4)):
            x = (torch.randn(shape, generator=generator, dtype=torch.float64) * 10).to(dtype)
            if dtype.is_floating_point and x.numel():
                x.view(-1)[0], x.view(-1)[-1] = float("nan"), -0.0
            yield x


def _assert_same_tensor(expected_call, got_call):
    expected, got = _outcome(expected_call), _outcome(got_call)
    if isinstance(expected, type) or isinstance(got, type):
        assert expected is got
        return
    expected = expected if isinstance(expected, tuple) else (expected,)
    got = got if isinstance(got, tuple) else (got,)
    assert len(got) == len(expected)
    for mine, theirs in zip(got, expected, strict=True):
        assert mine.dtype == theirs.dtype and mine.shape == theirs.shape
        torch.testing.assert_close(mine, theirs, rtol=0, atol=0, equal_nan=True)
        if mine.is_floating_point():
            assert torch.equal(torch.signbit(mine), torch.signbit(theirs))


def test_the_torch_namespace_gives_what_the_compat_namespace_gives():
    """``namespace(tensor)`` calls torch directly where the compat wrappers would change
    nothing (same dtype, no 0-D tensor, Python scalar bounds, an integer axis) and hands
    anything else to them: the same values, dtypes and shapes either way."""
    compat = array_api_compat.array_namespace(torch.zeros(1))
    fast = namespace(torch.zeros(1))
    assert fast is not compat and namespace(torch.zeros(2), 1.0) is fast
    for x in _tensors():
        scalar = torch.tensor(1.5, dtype=torch.float64)  # 0-D: promoted as an array
        others = (x, 2.0, 0, scalar, x.to(torch.float64), torch.ones_like(x))
        for other in others:
            _assert_same_tensor(
                lambda o=other, x=x: compat.where(x > 0, x, o),
                lambda o=other, x=x: fast.where(x > 0, x, o),
            )
            for name in ("maximum", "minimum"):
                _assert_same_tensor(
                    lambda n=name, o=other, x=x: getattr(compat, n)(x, o),
                    lambda n=name, o=other, x=x: getattr(fast, n)(x, o),
                )
        if x.is_floating_point() and x.numel():
            _assert_same_tensor(
                lambda x=x: compat.where(x > 0, x, 1j), lambda x=x: fast.where(x > 0, x, 1j)
            )
            signed = -x.abs()  # a NaN with its sign bit set
            _assert_same_tensor(lambda y=signed: compat.sign(y), lambda y=signed: fast.sign(y))
        for bounds in ((0.0, 1.0), (None, 2.0), (-1.0, None), (0, 3), (float("nan"), 1.0)):
            _assert_same_tensor(
                lambda b=bounds, x=x: compat.clip(x, *b), lambda b=bounds, x=x: fast.clip(x, *b)
            )
        _assert_same_tensor(lambda x=x: compat.sign(x), lambda x=x: fast.sign(x))
        for axis in (None, 0, -1, (0, 1)):
            for call in (
                lambda xp, x=x, a=axis: xp.cumulative_sum(x, axis=a),
                lambda xp, x=x, a=axis: xp.sum(x, axis=a),
                lambda xp, x=x, a=axis: xp.sum(x, axis=a, keepdims=True),
                lambda xp, x=x, a=axis: xp.flip(x, axis=a),
                lambda xp, x=x, a=axis: xp.concat([x, x], axis=a),
            ):
                _assert_same_tensor(lambda c=call: c(compat), lambda c=call: c(fast))
        for shapes in (((3, 1), (1, 4)), ((2,), (2,)), ((), (3,))):
            parts = [torch.zeros(s, dtype=x.dtype) for s in shapes]
            _assert_same_tensor(
                lambda p=parts: compat.broadcast_arrays(*p),
                lambda p=parts: fast.broadcast_arrays(*p),
            )
