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
* :func:`check_dtype` and :func:`check_shape` vet what numpy's reconstruction receives.

Every refusal raises :class:`Refused`, which the loader re-raises naming the file.
"""

from __future__ import annotations

import builtins
import collections
from typing import Any

import numpy as np

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
    if isinstance(factory, BuiltinType):
        factory = getattr(builtins, factory.name)
    elif factory not in (None, set, frozenset, complex):
        raise Refused(
            f"collections.defaultdict factory {type(factory).__name__} is refused "
            f"(allowed: None or builtins {', '.join(FACTORY_NAMES)}, set, frozenset, complex)"
        )
    return collections.defaultdict(factory)


class DtypeSpec:
    """Stand-in for a ``numpy.dtype`` being unpickled: ``dtype(str)`` then state."""

    def __init__(self, spec: Any, align: Any = False, copy: Any = True) -> None:
        if not isinstance(spec, str) or len(spec) > 16:
            raise Refused(f"dtype spec must be a short string, got {type(spec).__name__}")
        try:
            dtype = np.dtype(spec)
        except Exception as err:
            raise Refused(f"bad dtype {spec!r}: {err}") from None
        self.dtype = check_dtype(dtype)

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) < 2:
            raise Refused("bad dtype state")
        if any(part is not None for part in state[2:5]):
            raise Refused("structured / sub-array dtypes are refused")
        order = state[1]
        if order not in ("<", ">", "|", "="):
            raise Refused(f"bad dtype byte order {order!r}")
        if order != "|":
            self.dtype = self.dtype.newbyteorder(order)


def check_dtype(dtype: Any) -> np.dtype:
    if isinstance(dtype, DtypeSpec):
        dtype = dtype.dtype
    if not isinstance(dtype, np.dtype):
        raise Refused(f"expected a dtype, got {type(dtype).__name__}")
    if dtype.kind not in ARRAY_KINDS or dtype.hasobject or dtype.fields or dtype.subdtype:
        raise Refused(f"dtype {dtype!r} is refused (only bool, numeric, bytes and str)")
    if not 0 < dtype.itemsize <= 4096:
        raise Refused(f"dtype {dtype!r} has an unsupported item size")
    return dtype


def check_shape(shape: Any) -> tuple[int, ...]:
    if isinstance(shape, int) and not isinstance(shape, bool):
        shape = (shape,)
    if not isinstance(shape, tuple) or len(shape) > MAX_DIMS:
        raise Refused(f"bad array shape {shape!r:.80}")
    for dim in shape:
        if not isinstance(dim, int) or isinstance(dim, bool) or not 0 <= dim <= 2**40:
            raise Refused(f"bad array shape {shape!r:.80}")
    return shape


__all__ = [
    "ARRAY_KINDS",
    "FACTORY_NAMES",
    "FACTORY_TOKENS",
    "MAX_DIMS",
    "NDARRAY",
    "BuiltinType",
    "DtypeSpec",
    "NdarrayRef",
    "Refused",
    "check_dtype",
    "check_shape",
    "default_dict",
]
