"""Import a script of ``examples/`` or ``benchmarks/`` as a module (neither folder is a package)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(path: str | Path) -> ModuleType:
    """``path`` (relative to the repository) executed afresh as the module of its stem,
    registered in ``sys.modules`` (its dataclasses look their module up), with its folder on
    ``sys.path`` as when it runs (its helper modules: ``timing``, ``evaluate_ego``)."""
    path = ROOT / path
    if str(path.parent) not in sys.path:
        sys.path.append(str(path.parent))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
