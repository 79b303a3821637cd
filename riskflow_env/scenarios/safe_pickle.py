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

Limits (module constants, see docs/reference/security.md), each measured against the largest of
the four nuScenes samples of ScenarioNet (4.1 MB file, 510,000 elements, 3.5 MB of
arrays): :data:`MAX_FILE_BYTES` (file size), :data:`MAX_ARRAY_BYTES` (one array, byte
string or set built by a call), :data:`MAX_TOTAL_BYTES` (all that the calls of one file
allocate, charged before they allocate), :data:`MAX_ELEMENTS` (what the loaded value
expands to: every container entry and array element, counted again wherever a shared
container or array is referenced; about 0.12 per byte of a file without shared
references, so a file of :data:`MAX_FILE_BYTES` fits), :data:`MAX_DEPTH` (container
nesting). The opcode engine (:mod:`~riskflow_env.scenarios.pickle_unpickler`) bounds
what each opcode may allocate or hash.
"""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.scenarios.pickle_stand_ins import (
    NDARRAY,
    BuiltinType,
    CheckedSet,
    DtypeSpec,
    Refused,
    SafeArray,
)
from riskflow_env.scenarios.pickle_unpickler import ALLOWED_GLOBALS, RestrictedUnpickler
from riskflow_env.untrusted import MAX_MESSAGE, error_text

MAX_FILE_BYTES = 512 * 2**20  # [bytes] largest data pickle read
MAX_ARRAY_BYTES = 64 * 2**20  # [bytes] largest single array / byte string / set built by a call
MAX_TOTAL_BYTES = 256 * 2**20  # [bytes] all that the calls of one file allocate
MAX_ELEMENTS = 2**26  # container entries + array elements, counted once per reference
MAX_DEPTH = 64  # container nesting


class Budget:
    """What one load may allocate and expand to (the module's limits, read when it is
    made): :meth:`take` charges a call's allocation, :meth:`expand` the loaded value."""

    def __init__(self) -> None:
        self.total = 0
        self.elements = 0
        self.array_limit, self.total_limit = MAX_ARRAY_BYTES, MAX_TOTAL_BYTES
        self.element_limit = MAX_ELEMENTS

    def take(self, nbytes: int, what: str) -> None:
        """Charge ``nbytes`` that a call is about to allocate for a ``what``."""
        if nbytes > self.array_limit:
            raise Refused(
                f"a {what} of {nbytes} bytes exceeds the limit MAX_ARRAY_BYTES = {self.array_limit}"
            )
        self.total += nbytes
        if self.total > self.total_limit:
            raise Refused(
                f"arrays, byte strings and sets totalling over {self.total_limit} bytes exceed "
                "the limit MAX_TOTAL_BYTES"
            )

    def expand(self, count: int) -> None:
        """Charge ``count`` elements that the loaded value holds (once per reference)."""
        self.elements += count
        if self.elements > self.element_limit:
            raise Refused(
                f"the data expands to over MAX_ELEMENTS = {self.element_limit} elements "
                "(container entries and array elements, counted once per reference: "
                "shared containers count again wherever they are referenced)"
            )


# exact types that hold nothing to finish: skipped without a call (most of a summary file)
_LEAVES = frozenset({str, int, float, bool, complex, bytes, type(None)})


def _finish(root: Any, budget: Budget) -> Any:
    """Plain ndarrays / dtypes in place of the stand-ins; nesting depth checked; what
    the value expands to charged to ``budget`` (:meth:`Budget.expand`).

    Each container is visited once (a chain of ``[x, x]`` levels is a few hundred bytes
    for 2**60 paths; a cycle ends at a container seen before); a container referenced
    again is charged the count of everything below it, once per reference, without a
    walk. Plain scalars and strings are passed over in the loops (a ScenarioNet summary
    holds millions of them)."""
    done: dict[int, Any] = {}
    weight: dict[int, int] = {}  # elements below a finished container, itself included

    def visit(obj: Any, depth: int) -> Any:
        if depth > MAX_DEPTH:
            raise Refused(f"containers nested deeper than MAX_DEPTH = {MAX_DEPTH}")
        if type(obj) in _LEAVES:
            return obj
        if isinstance(obj, SafeArray):
            budget.expand(obj.size)
            return obj.view(np.ndarray)
        if isinstance(obj, DtypeSpec):
            return obj.dtype
        if obj is NDARRAY:
            raise Refused("a bare numpy.ndarray reference is refused")
        if isinstance(obj, (BuiltinType, CheckedSet)):
            raise Refused(f"a bare builtins.{obj.name} reference is refused")
        if not isinstance(obj, (dict, list, tuple, set, frozenset)):
            return obj
        if id(obj) in done:
            budget.expand(weight.get(id(obj), 1))  # 1: a cycle back to an open container
            return done[id(obj)]
        if isinstance(obj, tuple) and obj.__class__ is not tuple:
            return obj
        if obj and depth >= MAX_DEPTH:  # its items lie deeper than MAX_DEPTH
            raise Refused(f"containers nested deeper than MAX_DEPTH = {MAX_DEPTH}")
        before = budget.elements
        budget.expand(len(obj))
        if isinstance(obj, tuple):
            done[id(obj)] = result = tuple(
                value if type(value) in _LEAVES else visit(value, depth + 1) for value in obj
            )
            weight[id(obj)] = budget.elements - before
            return result
        done[id(obj)] = obj  # mutable containers are fixed in place (cycles end here)
        if isinstance(obj, dict):
            for key, value in obj.items():
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
        weight[id(obj)] = budget.elements - before
        return obj

    return visit(root, 0)


@contextlib.contextmanager
def errors_name_the_file(source: str, what: str = "a readable data pickle") -> Iterator[None]:
    """Inside the block, every failure becomes one ``ValueError`` naming ``source``.

    ``MemoryError``, ``IndexError``, ``LookupError``, ``TypeError``, ``RecursionError``,
    ``OverflowError``... (any ``Exception``) are re-raised as ``ValueError("<source>: not
    <what> (<type>: <message>)")``, the message cut to a few hundred characters and built
    without formatting what the file holds
    (:func:`~riskflow_env.untrusted.error_text`); a ``ValueError`` whose
    message already names ``source`` passes (cut the same way). ``KeyboardInterrupt``,
    ``SystemExit`` and other ``BaseException`` s that are not ``Exception`` s pass
    through untouched."""
    try:
        yield
    except Exception as err:  # MemoryError and RecursionError are Exceptions
        message = err.args[0] if len(err.args) == 1 else None
        if isinstance(err, ValueError) and isinstance(message, str) and source in message:
            if len(message) <= len(source) + MAX_MESSAGE:
                raise
            raise ValueError(message[: len(source) + MAX_MESSAGE] + "...") from None
        text = error_text(err)
        if isinstance(err, ValueError):
            text = text.removeprefix("ValueError: ").removeprefix("Refused: ")
        raise ValueError(f"{source}: not {what} ({text})") from None


def _load(data: bytes, source: str) -> Any:
    with errors_name_the_file(source):
        budget = Budget()
        return _finish(RestrictedUnpickler(io.BytesIO(data), source, budget).load(), budget)


def load_data_pickle(path: str | Path) -> Any:
    """Load a pickle file with :class:`RestrictedUnpickler`.

    Args:
        path: the file.

    Raises:
        FileNotFoundError: when ``path`` does not exist.
        ValueError: naming the file when it refers to a disallowed global, exceeds a
            limit or is not a readable pickle.
    """
    return _load(read_data_file(path), str(path))


def read_data_file(path: str | Path) -> bytes:
    """The bytes of data file ``path``, at most :data:`MAX_FILE_BYTES` of them (read in one
    bounded call: a file that grows, or a device that never ends, is refused too).

    Raises:
        FileNotFoundError: when ``path`` does not exist.
        ValueError: naming the file when it holds more than :data:`MAX_FILE_BYTES`.
    """
    path = Path(path)
    parts, total = [], 0
    with path.open("rb") as file:
        size = os.fstat(file.fileno()).st_size
        while size <= MAX_FILE_BYTES and total <= MAX_FILE_BYTES:
            want = size + 1 if not parts else 2**20  # the stated size, then 1 MiB reads
            part = file.read(min(want, MAX_FILE_BYTES + 1 - total))
            if not part:
                break
            parts.append(part)
            total += len(part)
    if size > MAX_FILE_BYTES or total > MAX_FILE_BYTES:
        raise ValueError(f"{path}: over {MAX_FILE_BYTES} bytes, the limit MAX_FILE_BYTES")
    return b"".join(parts)


def loads_data_pickle(data: bytes, source: str = "<bytes>") -> Any:
    """:func:`load_data_pickle` for in-memory bytes; ``source`` names them in errors."""
    if len(data) > MAX_FILE_BYTES:
        raise ValueError(
            f"{source}: {len(data)} bytes exceeds the limit MAX_FILE_BYTES = {MAX_FILE_BYTES}"
        )
    return _load(data, source)


__all__ = [
    "ALLOWED_GLOBALS",
    "MAX_ARRAY_BYTES",
    "MAX_DEPTH",
    "MAX_ELEMENTS",
    "MAX_FILE_BYTES",
    "MAX_TOTAL_BYTES",
    "Budget",
    "RestrictedUnpickler",
    "errors_name_the_file",
    "load_data_pickle",
    "loads_data_pickle",
    "read_data_file",
]
