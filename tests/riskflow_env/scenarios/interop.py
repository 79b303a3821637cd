"""Skip a test module, with the reason, when a library of the ``[interop]`` extra is absent.

commonroad-io's generated protobuf modules need protobuf 3.20, or its pure-Python parser
with a newer protobuf: the variable is set before anything here imports protobuf.
"""

from __future__ import annotations

import importlib
import os

import pytest

os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")


def require(*modules: str) -> None:
    """Skip the calling module unless every module of ``modules`` imports."""
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as err:  # protobuf's TypeError is not an ImportError
            pytest.skip(
                f"{module} does not import ({type(err).__name__}: {str(err)[:200]}): "
                "pip install -e '.[interop]' (docs/how-to/exchange.md)",
                allow_module_level=True,
            )
