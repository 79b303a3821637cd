"""A restricted unpickler for data files: builtin containers and numpy arrays only.

``pickle.load`` runs whatever callable a file names, so loading a pickle from
elsewhere can execute arbitrary code. :func:`load_data_pickle` resolves only the
globals in :data:`ALLOWED_GLOBALS` (builtin containers and scalars, numpy array,
dtype and scalar reconstruction) and raises ``ValueError`` naming any other one,
before it is imported or called. Persistent ids are refused too.
"""

from __future__ import annotations

import builtins
import codecs
import collections
import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np

try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
    from numpy._core import numeric as _numeric
except ImportError:  # numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]
    from numpy.core import numeric as _numeric  # type: ignore[no-redef]

_BUILTINS = ("dict", "list", "tuple", "set", "frozenset", "bytearray", "bytes", "str")
_BUILTINS += ("int", "float", "complex", "bool")
_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")
_NUMERIC_MODULES = ("numpy.core.numeric", "numpy._core.numeric")

#: (module, name) -> object: everything a data pickle may refer to.
ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    **{("builtins", name): getattr(builtins, name) for name in _BUILTINS},
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("_codecs", "encode"): codecs.encode,  # protocol-2 pickles store bytes this way
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    **{(module, "_reconstruct"): _multiarray._reconstruct for module in _NUMPY_MODULES},
    **{(module, "scalar"): _multiarray.scalar for module in _NUMPY_MODULES},
    **{(module, "_frombuffer"): _numeric._frombuffer for module in _NUMERIC_MODULES},
}


class RestrictedUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` that resolves only :data:`ALLOWED_GLOBALS`.

    Args:
        file: a binary file object.
        source: name of the data quoted in errors (e.g. the file path).
    """

    def __init__(self, file: io.BufferedIOBase, source: str = "<pickle>") -> None:
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        """The allowed object ``module.name``; ValueError for anything else."""
        module = {"__builtin__": "builtins"}.get(module, module)  # protocol 0-2 name
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise ValueError(
                f"{self.source}: refusing to unpickle disallowed global '{module}.{name}'; "
                "data pickles may hold only builtin containers and numpy arrays"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        """Persistent ids are refused (ValueError)."""
        raise ValueError(f"{self.source}: refusing to unpickle a persistent id ({pid!r})")


def load_data_pickle(path: str | Path) -> Any:
    """Load a pickle file with :class:`RestrictedUnpickler`.

    Args:
        path: the file.

    Raises:
        FileNotFoundError: when ``path`` does not exist.
        ValueError: naming the file when it refers to a disallowed global or is not a
            readable pickle.
    """
    path = Path(path)
    with path.open("rb") as file:
        try:
            return RestrictedUnpickler(file, source=str(path)).load()
        except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, TypeError) as err:
            raise ValueError(f"{path}: not a readable data pickle ({err})") from err


def loads_data_pickle(data: bytes, source: str = "<bytes>") -> Any:
    """:func:`load_data_pickle` for in-memory bytes; ``source`` names them in errors."""
    try:
        return RestrictedUnpickler(io.BytesIO(data), source=source).load()
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, TypeError) as err:
        raise ValueError(f"{source}: not a readable data pickle ({err})") from err
