"""Loading the numba kernel modules of the compiled paths, and their switch.

Every compiled path (the simulator step, :mod:`riskflow_env.compiled`; the planning
loops; the lane lookups; the map crops; the WOSAC distances; the escape search) imports
its kernels through here: None where numba is not installed or finds no writable cache
directory (a warning names ``NUMBA_CACHE_DIR``), and the reference runs; the environment
variable ``RISKFLOW_COMPILED=0`` turns them all off. A leaf module, so that the modules
whose kernels it loads can import it.
"""

from __future__ import annotations

import functools
import importlib
import os
import warnings
from types import ModuleType

SWITCH = "RISKFLOW_COMPILED"  # environment variable; "0" turns the compiled paths off


def import_kernels(module: str, what: str) -> ModuleType | None:
    """Import the numba kernel ``module``; None where numba is not installed, or where it
    finds no writable cache directory (a warning says that ``what`` is off and names
    ``NUMBA_CACHE_DIR``)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        return None
    except RuntimeError as error:  # numba's cache=True with no writable directory
        if "cannot cache" not in str(error):
            raise
        warnings.warn(
            f"{what} is off: {error}. Set NUMBA_CACHE_DIR to a writable directory to run "
            "the compiled code; the array-API reference runs.",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


@functools.cache
def _imported(module: str, what: str) -> ModuleType | None:
    return import_kernels(module, what)


def optional_kernels(module: str, what: str) -> ModuleType | None:
    """The numba kernel ``module`` where the compiled paths are on; None with
    ``RISKFLOW_COMPILED=0`` or where :func:`import_kernels` gives None (tried once per
    process)."""
    if os.environ.get(SWITCH, "1") == "0":
        return None
    return _imported(module, what)


__all__ = ["SWITCH", "import_kernels", "optional_kernels"]
