"""A test helper: numba finds no writable cache directory (a read-only install, no
writable home), as the compiled paths' fallback tests need it."""

from __future__ import annotations

import importlib
import sys

import pytest


def without_writable_cache(monkeypatch: pytest.MonkeyPatch, modules: tuple[str, ...]) -> None:
    """Make numba's cache locators fail and drop ``modules`` (numba kernel modules, whose
    ``cache=True`` decorators run at import) so that the next import meets the failure;
    ``monkeypatch.undo()`` restores both."""
    caching = pytest.importorskip("numba.core.caching")
    if not hasattr(caching, "_CacheLocator"):
        pytest.skip("numba's cache locators changed")

    def read_only(locator):
        raise PermissionError("read-only")

    monkeypatch.setattr(caching._CacheLocator, "ensure_cache_path", read_only)
    for name in modules:
        parent, _, child = name.rpartition(".")
        monkeypatch.delitem(sys.modules, name, raising=False)
        monkeypatch.delattr(importlib.import_module(parent), child, raising=False)
