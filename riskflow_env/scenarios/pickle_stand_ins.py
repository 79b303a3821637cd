"""The inert stand-ins that a data pickle's globals resolve to, and the dtype / shape checks.

:class:`~riskflow_env.scenarios.safe_pickle.RestrictedUnpickler` hands a file none of
the real objects it names where those could allocate without bound or address memory:

* ``numpy.ndarray`` is :data:`NDARRAY`, a token that refuses every call (it can only be
  ``_reconstruct``'s subtype);
* ``numpy.dtype`` is :class:`DtypeSpec`: a short type string, then a checked state
  (plain numeric, bool, bytes or str kinds; no object, structured or sub-array dtype);
* a builtin type (``list``, ``int``...) is a :class:`BuiltinType` token in
  :data:`FACTORY_TOKENS`, usable only as the factory of a ``collections.defaultdict``
  (:func:`default_dict` swaps the real type in);
* arrays are :class:`SafeArray` s, whose state is checked and charged before numpy
  copies it;
* ``set`` and ``frozenset`` are :class:`CheckedSet` s: a call checks the items and
  charges them before building (also usable as a ``defaultdict`` factory);
* :func:`check_dtype` and :func:`check_shape` vet what numpy's reconstruction receives,
  :func:`check_key` every dict key and set item.

Messages quote what a file holds only through
:func:`~riskflow_env.untrusted.brief` (bounded time and length).

Every refusal raises :class:`Refused`, which the loader re-raises naming the file.
"""

from __future__ import annotations

import builtins
import collections
import math
from typing import Any

import numpy as np

from riskflow_env.untrusted import brief

MAX_DIMS = 8  # array dimensions
ARRAY_KINDS = frozenset("biufcSU")  # bool, ints, floats, complex, bytes, str


class Refused(ValueError):
    """A refusal inside the unpickler (re-raised with the file name)."""


class NdarrayRef:
    """Stand-in for ``numpy.ndarray``: only usable as ``_reconstruct``'s subtype."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise Refused("calling numpy.ndarray directly is refused (buffer/offset access)")

    def __reduce__(self) -> Any:  # pragma: no cover - never pickled back
        raise TypeError("not picklable")


NDARRAY = NdarrayRef()


class BuiltinType:
    """Stand-in for a builtin type (``list``, ``int``...): a ``defaultdict`` factory only.

    ``collections.defaultdict(list)`` pickles as a reference to ``builtins.list``;
    calling the plain type from a file could amplify (``list`` of a long string), so
    the token refuses every call and :func:`default_dict` swaps in the real type."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise Refused(f"calling builtins.{self.name} is refused (only a defaultdict factory)")

    def __reduce__(self) -> Any:  # pragma: no cover - never pickled back
        raise TypeError("not picklable")


# builtin types a ScenarioNet / MetaDrive file may name as a ``defaultdict`` factory
# (metadrive's ScenarioDescription writes ``defaultdict(int)`` in
# ``metadata["number_summary"]``); tokens, never called.
FACTORY_NAMES = ("list", "int", "float", "dict", "str", "tuple", "bool")
FACTORY_TOKENS = {name: BuiltinType(name) for name in FACTORY_NAMES}


def default_dict(factory: Any = None, *args: Any) -> collections.defaultdict:
    """``collections.defaultdict(factory)`` for a builtin factory (or None) only; the
    items arrive afterwards through the pickle's SETITEMS."""
    if args:
        raise Refused("collections.defaultdict with initial items in its call is refused")
    if isinstance(factory, (BuiltinType, CheckedSet)):
        factory = getattr(builtins, factory.name)
    elif factory not in (None, complex):
        raise Refused(
            f"collections.defaultdict factory {type(factory).__name__} is refused "
            f"(allowed: None or builtins {', '.join(FACTORY_NAMES)}, set, frozenset, complex)"
        )
    return collections.defaultdict(factory)


class DtypeSpec:
    """Stand-in for a ``numpy.dtype`` being unpickled: ``dtype(str)`` then state."""

    def __init__(self, spec: Any, align: Any = False, copy: Any = True) -> None:
        if not isinstance(spec, str) or len(spec) > 16:
            raise Refused(f"dtype spec must be a short string, got {brief(spec)}")
        try:
            dtype = np.dtype(spec)
        except Exception:
            raise Refused(f"bad dtype {spec!r}") from None
        self.dtype = check_dtype(dtype)

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) < 2:
            raise Refused("bad dtype state")
        if any(part is not None for part in state[2:5]):
            raise Refused("structured / sub-array dtypes are refused")
        order = state[1]
        if order not in ("<", ">", "|", "="):
            raise Refused(f"bad dtype byte order {brief(order)}")
        if order != "|":
            self.dtype = self.dtype.newbyteorder(order)


def check_dtype(dtype: Any) -> np.dtype:
    if isinstance(dtype, DtypeSpec):
        dtype = dtype.dtype
    if not isinstance(dtype, np.dtype):
        raise Refused(f"expected a dtype, got {brief(dtype)}")
    if dtype.kind not in ARRAY_KINDS or dtype.hasobject or dtype.fields or dtype.subdtype:
        raise Refused(f"dtype {dtype!r} is refused (only bool, numeric, bytes and str)")
    if not 0 < dtype.itemsize <= 4096:
        raise Refused(f"dtype {dtype!r} has an unsupported item size")
    return dtype


def check_shape(shape: Any) -> tuple[int, ...]:
    if isinstance(shape, int) and not isinstance(shape, bool):
        shape = (shape,)
    if not isinstance(shape, tuple) or len(shape) > MAX_DIMS:
        raise Refused(f"bad array shape {brief(shape)}")
    for dim in shape:
        if not isinstance(dim, int) or isinstance(dim, bool) or not 0 <= dim <= 2**40:
            raise Refused(f"bad array shape {brief(shape)}")
    return shape


class SafeArray(np.ndarray):
    """Array built by ``_reconstruct``; its ``__setstate__`` validates the state and charges
    the unpickler's budget (set on a subclass made per unpickler) before it copies the data."""

    _budget: Any = None

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise Refused("bad array state")
        if len(state) == 5:
            if state[0] != 1:
                raise Refused(f"unknown array state version {brief(state[0])}")
            state = state[1:]
        shape, dtype, fortran, raw = state
        shape = check_shape(shape)
        dtype = check_dtype(dtype)
        if not isinstance(fortran, bool):
            raise Refused("bad array order flag")
        nbytes = math.prod(shape) * dtype.itemsize
        if self._budget is None:
            raise Refused("array built outside an unpickler")
        self._budget.take(nbytes, "array")
        if not isinstance(raw, (bytes, bytearray)) or len(raw) != nbytes:
            held = len(raw) if isinstance(raw, (bytes, bytearray)) else type(raw).__name__
            raise Refused(f"array data holds {held} bytes, shape {shape} x {dtype} needs {nbytes}")
        super().__setstate__((shape, dtype, fortran, bytes(raw)))


# keys whose hash a file cannot choose (str, bytes: salted) or that share a hash with at
# most a few dozen others (ints of at most 64 bits, floats): no hash-collision flood
_KEY_TYPES = (str, bytes, float, bool, type(None), np.str_, np.bytes_, np.floating, np.bool_)


def check_key(key: Any) -> None:
    """Refuse a dict key or set item whose hash a file can make collide with many others
    (tuples, frozensets, complex numbers, ints of more than 64 bits): each insertion then
    costs at most a few dozen comparisons, whatever the file."""
    if isinstance(key, _KEY_TYPES):
        return
    if isinstance(key, (int, np.integer)) and int(key).bit_length() <= 64:
        return
    raise Refused(
        f"a dict key or set item of type {type(key).__name__} is refused (allowed: str, "
        "bytes, int of at most 64 bits, float, bool, None)"
    )


class CheckedSet:
    """Stand-in for ``builtins.set`` / ``frozenset``: ``kind(items)`` from a sequence
    built by the file, after :func:`check_key` on each item and ``charge(len(items))``
    (the unpickler's budget); the real type when it is a ``defaultdict`` factory."""

    def __init__(self, kind: type, charge: Any) -> None:
        self.name = kind.__name__
        self._kind, self._charge = kind, charge

    def __call__(self, items: Any = ()) -> Any:
        if not isinstance(items, (list, tuple, set, frozenset)):
            raise Refused(f"{self.name}() of {brief(items)} is refused")
        self._charge(len(items), self.name)
        for item in items:
            check_key(item)
        return self._kind(items)

    def __reduce__(self) -> Any:  # pragma: no cover - never pickled back
        raise TypeError("not picklable")


__all__ = [
    "ARRAY_KINDS",
    "FACTORY_NAMES",
    "FACTORY_TOKENS",
    "MAX_DIMS",
    "NDARRAY",
    "BuiltinType",
    "CheckedSet",
    "DtypeSpec",
    "NdarrayRef",
    "Refused",
    "SafeArray",
    "check_dtype",
    "check_key",
    "check_shape",
    "default_dict",
]
