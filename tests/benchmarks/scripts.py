"""Load a script of ``benchmarks/`` as a module (the folder is not a package)."""

from __future__ import annotations

from types import ModuleType

from tests.scripts import load_script


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` imported under the module name ``name`` (tests.scripts)."""
    return load_script(f"benchmarks/{name}.py")
