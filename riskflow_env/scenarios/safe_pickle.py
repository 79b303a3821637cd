"""A restricted unpickler for data files: builtin containers and numpy arrays only.

Containers: the builtin ones, ``collections.OrderedDict`` and
``collections.defaultdict`` with a builtin factory (``list``, ``int``, ``dict``...;
ScenarioNet / MetaDrive write ``defaultdict(int)`` into
``metadata["number_summary"]``). The builtin types are reachable only as such a
factory: calling one from a file is refused.

``pickle.load`` runs whatever callable a file names, so loading a pickle from
elsewhere can execute arbitrary code. :func:`load_data_pickle` resolves only the
globals in :data:`ALLOWED_GLOBALS` and raises ``ValueError`` naming any other one,
before it is imported or called. Persistent ids are refused too.

The unpickler never hands a file a callable that can address memory: the
``numpy.ndarray`` constructor (shape, dtype, *buffer, offset*) is not reachable.
``numpy.ndarray`` and ``numpy.dtype`` resolve to inert stand-ins
(:mod:`~riskflow_env.scenarios.pickle_stand_ins`), and arrays are
built only through numpy's own reconstruction path (``_reconstruct`` followed by
``__setstate__``) after the dtype (plain numeric, bool, bytes or str kinds; no
object, structured or sub-array dtypes), the shape and the byte count have been
checked against the raw data and the limits below. Every failure, whatever its
cause (``MemoryError``, ``IndexError``, ``LookupError``, ``RecursionError``...),
is raised as one ``ValueError`` naming the file.

Limits (module constants, see docs/SECURITY.md): :data:`MAX_FILE_BYTES` (file
size), :data:`MAX_ARRAY_BYTES` (one array or byte string built by a call),
:data:`MAX_TOTAL_BYTES` (all arrays and byte strings of one file together),
:data:`MAX_DEPTH` (container nesting).
"""

from __future__ import annotations

import _compat_pickle
import builtins
import codecs
import collections
import contextlib
import io
import math
import os
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.scenarios.pickle_stand_ins import (
    FACTORY_NAMES,
    FACTORY_TOKENS,
    NDARRAY,
    BuiltinType,
    DtypeSpec,
    NdarrayRef,
    Refused,
    check_dtype,
    check_shape,
    default_dict,
)

try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
except ImportError:  # numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]

MAX_FILE_BYTES = 512 * 2**20  # [bytes] largest data pickle read
MAX_ARRAY_BYTES = 256 * 2**20  # [bytes] largest single array / bytearray built
MAX_TOTAL_BYTES = 1024 * 2**20  # [bytes] all arrays / bytearrays of one file
MAX_DEPTH = 64  # container nesting

_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")
_NUMERIC_MODULES = ("numpy.core.numeric", "numpy._core.numeric")


class _SafeArray(np.ndarray):
    """Array built by ``_reconstruct``; its ``__setstate__`` validates the state."""

    _budget: _Budget | None = None

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise Refused("bad array state")
        if len(state) == 5:
            if state[0] != 1:
                raise Refused(f"unknown array state version {state[0]!r}")
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


class _Budget:
    def __init__(self) -> None:
        self.total = 0

    def take(self, nbytes: int, what: str) -> None:
        if nbytes > MAX_ARRAY_BYTES:
            raise Refused(
                f"a {what} of {nbytes} bytes exceeds the limit MAX_ARRAY_BYTES = {MAX_ARRAY_BYTES}"
            )
        self.total += nbytes
        if self.total > MAX_TOTAL_BYTES:
            raise Refused(
                f"arrays totalling over {MAX_TOTAL_BYTES} bytes exceed the limit MAX_TOTAL_BYTES"
            )


class RestrictedUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` that resolves only :data:`ALLOWED_GLOBALS` (made safe).

    Args:
        file: a binary file object.
        source: name of the data quoted in errors (e.g. the file path).
    """

    def __init__(self, file: io.BufferedIOBase, source: str = "<pickle>") -> None:
        super().__init__(file)
        self.source = source
        budget = _Budget()
        self._budget = budget
        array_type = type("_SafeArray", (_SafeArray,), {"_budget": budget})

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

        def sized(kind: type) -> Any:
            def build(*args: Any) -> Any:
                if args and isinstance(args[0], int):
                    budget.take(int(args[0]), kind.__name__)
                elif args and isinstance(args[0], (str, bytes, bytearray, list, tuple)):
                    budget.take(len(args[0]), kind.__name__)
                elif args:
                    raise Refused(f"{kind.__name__}() of a {type(args[0]).__name__} is refused")
                return kind(*args)

            return build

        def encode(obj: Any, encoding: str = "utf-8", errors: str = "strict") -> bytes:
            if encoding not in ("latin1", "latin-1", "utf-8", "utf8", "ascii"):
                raise Refused(f"_codecs.encode with encoding {encoding!r} is refused")
            return codecs.encode(obj, encoding, errors)

        self._globals: dict[tuple[str, str], Any] = {
            **{("builtins", name): getattr(builtins, name) for name in _PLAIN_BUILTINS},
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
        except KeyError:
            raise ValueError(
                f"{self.source}: refusing to unpickle disallowed global '{module}.{name}'; "
                "data pickles may hold only builtin containers and numpy arrays"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        """Persistent ids are refused (ValueError)."""
        raise ValueError(f"{self.source}: refusing to unpickle a persistent id ({pid!r:.80})")


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


# exact types that hold nothing to finish: skipped without a call (most of a summary file)
_LEAVES = frozenset({str, int, float, bool, complex, bytes, type(None)})


def _finish(root: Any) -> Any:
    """Plain ndarrays / dtypes in place of the stand-ins; nesting depth checked.

    Each container is visited once: a file that shares one list many times over (a
    chain of ``[x, x]`` levels is a few hundred bytes for 2**60 paths) or holds a cycle
    costs no more than its size. Plain scalars and strings are passed over in the loops
    (a ScenarioNet summary holds millions of them)."""
    done: dict[int, Any] = {}

    def visit(obj: Any, depth: int) -> Any:
        if depth > MAX_DEPTH:
            raise Refused(f"containers nested deeper than MAX_DEPTH = {MAX_DEPTH}")
        if type(obj) in _LEAVES:
            return obj
        if isinstance(obj, _SafeArray):
            return obj.view(np.ndarray)
        if isinstance(obj, DtypeSpec):
            return obj.dtype
        if obj is NDARRAY:
            raise Refused("a bare numpy.ndarray reference is refused")
        if isinstance(obj, BuiltinType):
            raise Refused(f"a bare builtins.{obj.name} reference is refused")
        if not isinstance(obj, (dict, list, tuple, set, frozenset)):
            return obj
        if id(obj) in done:
            return done[id(obj)]
        if isinstance(obj, tuple) and obj.__class__ is not tuple:
            return obj
        if obj and depth >= MAX_DEPTH:  # its items lie deeper than MAX_DEPTH
            raise Refused(f"containers nested deeper than MAX_DEPTH = {MAX_DEPTH}")
        if isinstance(obj, tuple):
            done[id(obj)] = result = tuple(
                value if type(value) in _LEAVES else visit(value, depth + 1) for value in obj
            )
            return result
        done[id(obj)] = obj  # mutable containers are fixed in place (cycles end here)
        if isinstance(obj, dict):
            for key, value in obj.items():
                if isinstance(key, (BuiltinType, NdarrayRef)):
                    raise Refused("a type reference as a dict key is refused")
                if type(value) not in _LEAVES:
                    obj[key] = visit(value, depth + 1)
        elif isinstance(obj, list):
            for index, value in enumerate(obj):
                if type(value) not in _LEAVES:
                    obj[index] = visit(value, depth + 1)
        else:
            for value in obj:
                if type(value) not in _LEAVES:
                    visit(value, depth + 1)
        return obj

    return visit(root, 0)


@contextlib.contextmanager
def errors_name_the_file(source: str, what: str = "a readable data pickle") -> Iterator[None]:
    """Inside the block, every failure becomes one ``ValueError`` naming ``source``.

    ``MemoryError``, ``IndexError``, ``LookupError``, ``TypeError``, ``RecursionError``,
    ``OverflowError``... (any ``Exception``) are re-raised as ``ValueError("<source>: not
    <what> (<type>: <message>)")``; a ``ValueError`` whose message already names
    ``source`` passes unchanged. ``KeyboardInterrupt``, ``SystemExit`` and other
    ``BaseException`` s that are not ``Exception`` s pass through untouched."""
    try:
        yield
    except ValueError as err:
        if source in str(err):
            raise
        raise ValueError(f"{source}: not {what} ({err})") from None
    except Exception as err:  # MemoryError and RecursionError are Exceptions
        raise ValueError(f"{source}: not {what} ({type(err).__name__}: {err})") from None


def _load(file: io.BufferedIOBase, source: str) -> Any:
    with errors_name_the_file(source):
        return _finish(RestrictedUnpickler(file, source=source).load())


def load_data_pickle(path: str | Path) -> Any:
    """Load a pickle file with :class:`RestrictedUnpickler`.

    Args:
        path: the file.

    Raises:
        FileNotFoundError: when ``path`` does not exist.
        ValueError: naming the file when it refers to a disallowed global, exceeds a
            limit or is not a readable pickle.
    """
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ValueError(
            f"{path}: {size} bytes exceeds the limit MAX_FILE_BYTES = {MAX_FILE_BYTES}"
        )
    with path.open("rb") as file:
        return _load(file, str(path))


def read_data_file(path: str | Path) -> bytes:
    """The bytes of data file ``path``, at most :data:`MAX_FILE_BYTES` of them (read in one
    bounded call: a file that grows, or a device that never ends, is refused too).

    Raises:
        FileNotFoundError: when ``path`` does not exist.
        ValueError: naming the file when it holds more than :data:`MAX_FILE_BYTES`.
    """
    path = Path(path)
    with path.open("rb") as file:
        size = os.fstat(file.fileno()).st_size
        data = file.read(MAX_FILE_BYTES + 1) if size <= MAX_FILE_BYTES else b""
    if size > MAX_FILE_BYTES or len(data) > MAX_FILE_BYTES:
        raise ValueError(f"{path}: over {MAX_FILE_BYTES} bytes, the limit MAX_FILE_BYTES")
    return data


def loads_data_pickle(data: bytes, source: str = "<bytes>") -> Any:
    """:func:`load_data_pickle` for in-memory bytes; ``source`` names them in errors."""
    if len(data) > MAX_FILE_BYTES:
        raise ValueError(
            f"{source}: {len(data)} bytes exceeds the limit MAX_FILE_BYTES = {MAX_FILE_BYTES}"
        )
    return _load(io.BytesIO(data), source)
