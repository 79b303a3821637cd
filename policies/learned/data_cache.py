"""Where files derived from a scene folder (window caches, action statistics) are written.

Beside the data (``<folder>/cache/``, ``<folder>/norm_stats.json``) when the folder is
writable and outside the installed packages; otherwise (the shipped bank in
``riskflow_env/assets``, anything inside the ``riskflow_env`` or ``policies`` package
folders, a read-only folder) in the user cache, ``platformdirs.user_cache_dir("riskflow-env")``
(``~/.cache/riskflow-env`` on Linux; ``RISKFLOW_CACHE_DIR`` overrides it:
:mod:`riskflow_env.user_cache`), under
``data/<folder name>-<16 hex digits of a SHA-256 of its absolute path and contents
signature>/``, so an install never changes. The signature (name, size and modification
time of each file directly in the folder) changes when the scenes do, e.g. after an
upgrade that ships new scenes, so stale statistics are never read back.

In a folder of your own, ``norm_stats.json`` is kept until you delete it: delete it (and
``cache/``, though window caches check their scenes anyway) after regenerating the scenes.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import policies
import riskflow_env
from riskflow_env.folder_lock import writable_folder
from riskflow_env.user_cache import CACHE_ENV, user_cache

PACKAGE_DIRS = tuple(
    Path(package.__file__).resolve().parent for package in (riskflow_env, policies)
)


def derived_dir(folder: str | os.PathLike) -> Path:
    """The folder that receives the files derived from scene folder ``folder``."""
    folder = Path(folder).resolve()
    inside = any(folder.is_relative_to(package) for package in PACKAGE_DIRS)
    if not inside and writable_folder(folder):
        return folder
    key = hashlib.sha256(f"{folder}\n{contents_signature(folder)}".encode()).hexdigest()[:16]
    return user_cache() / "data" / f"{folder.name}-{key}"


def contents_signature(folder: Path) -> str:
    """``name size mtime_ns`` of every file directly in ``folder``, one a line, sorted."""
    entries = sorted((e for e in os.scandir(folder) if e.is_file()), key=lambda e: e.name)
    return "\n".join(f"{e.name} {e.stat().st_size} {e.stat().st_mtime_ns}" for e in entries)


__all__ = ["CACHE_ENV", "PACKAGE_DIRS", "contents_signature", "derived_dir", "user_cache"]
