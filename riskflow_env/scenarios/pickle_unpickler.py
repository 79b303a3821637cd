"""The restricted unpickler of :mod:`~riskflow_env.scenarios.safe_pickle`: the opcode engine.

It runs on pickle's own opcode loop (``pickle._Unpickler``) with these opcodes replaced,
so that every step is checked before it allocates (the C unpickler gives no hook between
opcodes: a 10-byte memo index of 2**28 made it allocate 4 GiB, and a dict filled with
100,000 keys of one hash took minutes):

* globals resolve only through :data:`ALLOWED_GLOBALS`, to stand-ins where the plain
  object could run code, address memory or allocate without a charge
  (:mod:`~riskflow_env.scenarios.pickle_stand_ins`);
* ``REDUCE`` takes a tuple of at most :data:`MAX_CALL_ARGS` arguments; the object forms
  (``INST``, ``OBJ``, ``NEWOBJ``, ``NEWOBJ_EX``), the extension registry, persistent ids
  and out-of-band buffers are refused (``pickle`` writes none of them for data);
* ``SETITEM(S)`` fill dicts only, ``APPEND(S)`` lists only, ``ADDITEMS`` sets only,
  ``BUILD`` only an array or a dtype; every dict key and set item passes
  :func:`~riskflow_env.scenarios.pickle_stand_ins.check_key` (no hash-collision flood);
* what a call allocates (arrays, ``bytes``, ``bytearray``, ``str.encode``, sets;
  ``BYTEARRAY8``) is charged to the budget before it is allocated.
"""

from __future__ import annotations

import _compat_pickle
import codecs
import collections
import io
import math
import pickle
import struct
from typing import Any

import numpy as np

from riskflow_env.scenarios.pickle_stand_ins import (
    FACTORY_NAMES,
    FACTORY_TOKENS,
    NDARRAY,
    CheckedSet,
    DtypeSpec,
    Refused,
    SafeArray,
    check_dtype,
    check_key,
    check_shape,
    default_dict,
)
from riskflow_env.untrusted import MAX_QUOTE, brief

try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
except ImportError:  # numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]

MAX_CALL_ARGS = 6  # arguments of one REDUCE call (numpy's dtype takes 3)
SET_ENTRY_BYTES = 64  # [bytes] charged per item of a set built by a call (its hash table)
ENCODINGS = {"latin1": 1, "latin-1": 1, "ascii": 1, "utf-8": 4, "utf8": 4}  # [bytes/char]

_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")
_NUMERIC_MODULES = ("numpy.core.numeric", "numpy._core.numeric")


def _refuse(what: str) -> Any:
    def load(self: RestrictedUnpickler) -> None:
        raise Refused(f"the pickle opcode {what} is refused (data pickles do not need it)")

    return load


class _Dispatch(dict):
    def __missing__(self, opcode: int) -> Any:
        raise Refused(f"unknown pickle opcode {opcode:#04x}")


class RestrictedUnpickler(pickle._Unpickler):
    """``pickle``'s unpickler that resolves only :data:`ALLOWED_GLOBALS` (made safe) and
    checks every opcode that could allocate or hash without bound (module docstring).

    Args:
        file: a binary file object (an ``io.BytesIO``: reads never allocate more than
            the data holds).
        source: name of the data quoted in errors (e.g. the file path).
        budget: the ``take(nbytes, what)`` that charges what calls allocate (the
            loader's limits, :mod:`~riskflow_env.scenarios.safe_pickle`).
    """

    def __init__(self, file: io.BufferedIOBase, source: str, budget: Any) -> None:
        super().__init__(file)
        self.source = source
        self._budget = budget
        array_type = type("SafeArray", (SafeArray,), {"_budget": budget})

        def reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
            if subtype is not NDARRAY:
                raise Refused("numpy _reconstruct of a type other than numpy.ndarray")
            return _multiarray._reconstruct(array_type, (0,), b"b")

        def scalar(dtype: Any, data: Any = None) -> Any:
            dtype = check_dtype(dtype)
            if not isinstance(data, bytes) or len(data) != dtype.itemsize:
                raise Refused("bad numpy scalar data")
            return np.frombuffer(data, dtype=dtype)[0]

        def frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
            dtype = check_dtype(dtype)
            shape = check_shape(shape)
            if isinstance(buf, pickle.PickleBuffer):
                buf = bytes(buf.raw())
            if not isinstance(buf, (bytes, bytearray)):
                raise Refused("numpy _frombuffer needs bytes")
            nbytes = math.prod(shape) * dtype.itemsize
            budget.take(nbytes, "array")
            if len(buf) != nbytes or order not in ("C", "F"):
                raise Refused("numpy _frombuffer size / order mismatch")
            return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order).copy(order="K")

        def encoded(text: Any, encoding: Any, errors: Any, kind: str) -> bytes:
            if encoding not in ENCODINGS or errors != "strict":
                raise Refused(f"{kind} with encoding {brief(encoding)} is refused")
            if not isinstance(text, str):
                raise Refused(f"{kind} of {brief(text)} is refused")
            budget.take(len(text) * ENCODINGS[encoding], kind)
            return codecs.encode(text, encoding, errors)

        def sized(kind: type) -> Any:
            def build(data: Any = b"", encoding: Any = None, errors: Any = "strict") -> Any:
                if encoding is not None:
                    return kind(encoded(data, encoding, errors, kind.__name__))
                if isinstance(data, int) and not isinstance(data, bool):
                    budget.take(data, kind.__name__)
                elif isinstance(data, (bytes, bytearray, list, tuple)):
                    budget.take(len(data), kind.__name__)
                else:
                    raise Refused(f"{kind.__name__}() of {brief(data)} is refused")
                return kind(data)

            return build

        def encode(text: Any, encoding: Any = "utf-8", errors: Any = "strict") -> bytes:
            return encoded(text, encoding, errors, "_codecs.encode")

        def charge_set(count: int, what: str) -> None:
            budget.take(SET_ENTRY_BYTES * count, what)

        self._globals: dict[tuple[str, str], Any] = {
            ("builtins", "set"): CheckedSet(set, charge_set),
            ("builtins", "frozenset"): CheckedSet(frozenset, charge_set),
            ("builtins", "complex"): complex,
            ("builtins", "bytearray"): sized(bytearray),
            ("builtins", "bytes"): sized(bytes),
            **{("builtins", name): token for name, token in FACTORY_TOKENS.items()},
            ("collections", "OrderedDict"): collections.OrderedDict,
            ("collections", "defaultdict"): default_dict,
            ("_codecs", "encode"): encode,
            ("numpy", "ndarray"): NDARRAY,
            ("numpy", "dtype"): DtypeSpec,
            **{(module, "_reconstruct"): reconstruct for module in _NUMPY_MODULES},
            **{(module, "scalar"): scalar for module in _NUMPY_MODULES},
            **{(module, "_frombuffer"): frombuffer for module in _NUMERIC_MODULES},
        }

    def find_class(self, module: str, name: str) -> Any:
        """The allowed object ``module.name``; ValueError for anything else."""
        # Python 2 names (protocols 0-2 write ``__builtin__.long`` for ``int``), mapped as
        # pickle's own find_class does; the result is still looked up in the allowlist
        key = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
        key = (_compat_pickle.IMPORT_MAPPING.get(key[0], key[0]), key[1])
        try:
            return self._globals[key]
        except (KeyError, TypeError):
            raise ValueError(
                f"{self.source}: refusing to unpickle disallowed global "
                f"'{str(module)[:MAX_QUOTE]}.{str(name)[:MAX_QUOTE]}'; data pickles may hold "
                "only builtin containers and numpy arrays"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        """Persistent ids are refused (ValueError)."""
        raise ValueError(f"{self.source}: refusing to unpickle a persistent id ({brief(pid)})")

    def load(self) -> Any:
        """The object the data holds. pickle's own loop, reading the in-memory data
        directly: a ``FRAME`` only announces how many bytes follow (the data is all in
        memory already, so frames are read through, not copied out)."""
        self.read, self.readline = self._file_read, self._file_readline
        self.metastack, self.stack, self.proto = [], [], 0
        self.append = self.stack.append
        read, dispatch = self.read, self.dispatch
        try:
            while True:
                opcode = read(1)
                if not opcode:
                    raise EOFError("the data ends before its STOP opcode")
                dispatch[opcode[0]](self)
        except pickle._Stop as stop:
            return stop.value

    def load_frame(self) -> None:
        if len(self.read(8)) != 8:
            raise EOFError("the data ends inside a FRAME opcode")

    def load_reduce(self) -> None:
        args = self.stack.pop()
        if type(args) is not tuple or len(args) > MAX_CALL_ARGS:
            raise Refused(f"a call's arguments must be a tuple of at most {MAX_CALL_ARGS}")
        if self.stack[-1] is collections.OrderedDict and args:  # items come by SETITEMS
            raise Refused("collections.OrderedDict with items in its call is refused")
        self.stack[-1] = self.stack[-1](*args)

    def load_build(self) -> None:
        state = self.stack.pop()
        target = self.stack[-1]
        if not isinstance(target, (SafeArray, DtypeSpec)):
            raise Refused(f"setting the state of {brief(target)} is refused")
        target.__setstate__(state)

    def load_setitem(self) -> None:
        value, key = self.stack.pop(), self.stack.pop()
        self._fill(dict, [key, value])

    def load_setitems(self) -> None:
        self._fill(dict, self.pop_mark())

    def load_dict(self) -> None:
        items = self.pop_mark()
        self.append({})
        self._fill(dict, items)

    def load_additems(self) -> None:
        self._fill(set, self.pop_mark())

    def load_frozenset(self) -> None:
        items = self.pop_mark()
        for item in items:
            check_key(item)
        self.append(frozenset(items))

    def load_appends(self) -> None:
        self._fill(list, self.pop_mark())

    def load_append(self) -> None:
        self._fill(list, [self.stack.pop()])

    def load_bytearray8(self) -> None:
        (size,) = struct.unpack("<Q", self.read(8))
        self._budget.take(size, "bytearray")
        data = self.read(size)
        if len(data) != size:
            raise Refused("BYTEARRAY8 runs past the end of the data")
        self.append(bytearray(data))

    def _fill(self, kind: type, items: list) -> None:
        """Add ``items`` to the ``kind`` (dict: key, value pairs; set; list) on top of the
        stack, each dict key and set item checked first."""
        target = self.stack[-1]
        if not isinstance(target, kind):
            raise Refused(
                f"adding items to {brief(target)} is refused (expected a {kind.__name__})"
            )
        if kind is list:
            target.extend(items)
            return
        keys = items[::2] if kind is dict else items
        for key in keys:
            if type(key) is not str:
                check_key(key)
        if kind is set:
            target.update(items)
        elif len(items) % 2:
            raise Refused("dict items must come in key, value pairs")
        else:
            target.update(zip(keys, items[1::2], strict=True))

    dispatch = _Dispatch(pickle._Unpickler.dispatch)
    for _name in ("INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "EXT1", "EXT2", "EXT4", "NEXT_BUFFER"):
        dispatch[getattr(pickle, _name)[0]] = _refuse(_name)
    for _name, _load in (
        ("READONLY_BUFFER", _refuse("READONLY_BUFFER")),
        ("FRAME", load_frame),
        ("REDUCE", load_reduce),
        ("BUILD", load_build),
        ("SETITEM", load_setitem),
        ("SETITEMS", load_setitems),
        ("DICT", load_dict),
        ("ADDITEMS", load_additems),
        ("FROZENSET", load_frozenset),
        ("APPENDS", load_appends),
        ("APPEND", load_append),
        ("BYTEARRAY8", load_bytearray8),
    ):
        dispatch[getattr(pickle, _name)[0]] = _load
    del _name, _load


# the builtins that pickle itself writes as globals (protocols 0-5): sets before protocol 4,
# complex numbers. dict, list, tuple, str, int, float and bool have opcodes of their own,
# and a file calling them could only amplify (``str`` of a shared structure is exponential).
_PLAIN_BUILTINS = ("set", "frozenset", "complex")

#: (module, name): every global a data pickle may refer to (each through a checked
#: stand-in where the plain object could allocate without bound or address memory).
ALLOWED_GLOBALS: frozenset[tuple[str, str]] = frozenset(
    {("builtins", name) for name in _PLAIN_BUILTINS + ("bytearray", "bytes") + FACTORY_NAMES}
    | {
        ("collections", "OrderedDict"),
        ("collections", "defaultdict"),
        ("_codecs", "encode"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }
    | {(module, name) for module in _NUMPY_MODULES for name in ("_reconstruct", "scalar")}
    | {(module, "_frombuffer") for module in _NUMERIC_MODULES}
)


__all__ = ["ALLOWED_GLOBALS", "MAX_CALL_ARGS", "RestrictedUnpickler", "SET_ENTRY_BYTES"]
