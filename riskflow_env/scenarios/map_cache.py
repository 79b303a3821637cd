"""A disk cache of the maps converted from ScenarioNet files, keyed by file content.

Building a :class:`~riskflow_env.maps.DrivableMap` from a scenario's ``map_features``
(shapely unions, rasterising, the signed distance field) is most of the time it takes to
load a ScenarioNet scene; the map is a pure function of the file's bytes and the build
settings. :class:`MapCache` keeps each built map as a map file
(``schema="riskflow-map"``, :mod:`~riskflow_env.scenarios.map_files`) named by a SHA-256 of

* the file's content hash (SHA-256 of its bytes: a renamed or copied file hits, an
  edited one misses),
* the build settings (resolution, margin, crop region, map name) and
* the source of the map-building code (:data:`BUILDER_MODULES`), so that a new version
  of the converter never reads a map built by an old one.

The file holds the map's lanes, drivable mask and signed distance field (the same
arrays as the built map, bit for bit: a scene reads the same from the cache as built, so
a rollout does not depend on the cache's state); about 0.4-0.5 MB for a cropped nuScenes
map. The default folder is ``maps/`` in the user cache (:mod:`riskflow_env.user_cache`:
``~/.cache/riskflow-env`` on Linux, ``RISKFLOW_CACHE_DIR`` overrides it). Each map is
written to a temporary file of its own and renamed into place, so concurrent writers
(evaluation workers, several runs) never expose a partial file: the last rename wins, and
every writer wrote the same map. A file that cannot be read back (damaged on disk) is
a miss: rebuilt and replaced, with a warning. Delete the folder to reclaim the space.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path

from riskflow_env.maps import DrivableMap
from riskflow_env.scenarios.map_files import map_to_arrays, read_map, write_map_arrays
from riskflow_env.user_cache import user_cache

_FORMAT = 1  # bump when the cached file's meaning changes
_PACKAGE = Path(__file__).resolve().parents[1]
#: the modules whose source is part of every key (the converter and the map builders)
BUILDER_MODULES = (
    "scenarios/scenarionet_map.py",
    "scenarios/scenarionet_features.py",
    "scenarios/logged_surface.py",
    "maps/builders.py",
    "maps/rasterize.py",
    "maps/surface.py",
    "maps/lanes.py",
    "maps/drivable_map.py",
)


@functools.cache
def builder_fingerprint() -> str:
    """SHA-256 of the source of :data:`BUILDER_MODULES` (read once per process)."""
    digest = hashlib.sha256()
    for name in BUILDER_MODULES:
        digest.update(name.encode() + b"\0" + (_PACKAGE / name).read_bytes() + b"\0")
    return digest.hexdigest()


def file_digest(data: bytes) -> str:
    """The content hash of a file's bytes (SHA-256, hex)."""
    return hashlib.sha256(data).hexdigest()


class MapCache:
    """Built maps on disk, one map file per (file content, build settings, builder code).

    Args:
        folder: where the map files go; None: ``<user cache>/maps``, resolved when the
            first map is read or written (so ``RISKFLOW_CACHE_DIR`` set later applies).

    Attributes:
        hits, misses: lookups answered from disk / built (this object's, for reports).
    """

    def __init__(self, folder: str | os.PathLike | None = None) -> None:
        self._folder = None if folder is None else Path(folder)
        self.hits = 0
        self.misses = 0

    @property
    def folder(self) -> Path:
        """The cache folder."""
        return self._folder if self._folder is not None else user_cache() / "maps"

    def __repr__(self) -> str:
        return f"MapCache({str(self.folder)!r}, hits={self.hits}, misses={self.misses})"

    @staticmethod
    def key(digest: str, **settings: object) -> str:
        """The cache key (64 hex digits) of a file with content hash ``digest`` built with
        ``settings`` (JSON-able values: floats, tuples, strings, None)."""
        parts = [_FORMAT, builder_fingerprint(), digest, sorted(settings.items())]
        return hashlib.sha256(json.dumps(parts).encode()).hexdigest()

    def path(self, key: str) -> Path:
        """The map file of ``key``."""
        return self.folder / f"{key}.npz"

    def get_or_build(self, key: str, build: Callable[[], DrivableMap]) -> DrivableMap:
        """The cached map of ``key``, or ``build()``'s, written to the cache first."""
        path = self.path(key)
        if path.is_file():
            try:
                drivable_map = read_map(path)
            except (OSError, ValueError) as err:  # damaged on disk: rebuild it
                warnings.warn(f"map cache: rebuilding unreadable {path} ({err})", stacklevel=2)
            else:
                self.hits += 1
                return drivable_map
        drivable_map = build()
        self.misses += 1
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_map_arrays(path, map_to_arrays(drivable_map, include_sdf=True))
        except OSError as err:  # read-only or full disk: the scene still loads
            warnings.warn(f"map cache: cannot write {path} ({err})", stacklevel=2)
        return drivable_map
