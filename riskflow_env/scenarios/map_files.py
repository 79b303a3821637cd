"""Map files: a :class:`DrivableMap` as arrays, in a versioned ``.npz`` file or inline.

A map (inline in a scene file with the ``map_`` prefix,
:mod:`~riskflow_env.scenarios.io`, or alone in a ``schema="riskflow-map"`` file):
``drivable`` (H, W) bool, ``resolution`` () [m/px], ``origin`` (2,) [m], ``name``,
``sdf`` (H, W) float32 [m] only when saved with ``include_sdf`` (else recomputed on
load: 0.2 s of CPU and about 40 bytes a pixel, so a raster without it holds at most
:data:`MAX_SDF_PIXELS`, checked from the headers), and the lanes: ``lane_points``
(M, 2) [m] (all centrelines concatenated), ``lane_offsets`` (L + 1,) (lane i is
``lane_points[off[i]:off[i+1]]``), ``lane_widths`` (L,) [m], ``lane_ids`` (L,),
``lane_speed_limits`` (L,) [m/s] (NaN for none), ``lane_successors`` (S,) and
``lane_successor_offsets`` (L + 1,).

:func:`map_hash` names a map by its content (16 hex digits of a SHA-256 of its arrays);
:func:`load_map` keeps one in-memory copy per hash (the last :data:`MAP_CACHE_SIZE`),
shared by every scene that refers to it; :func:`read_map` reads afresh.
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np

from riskflow_env.maps import DrivableMap, Lane
from riskflow_env.maps.drivable_map import MAX_MAP_COORDINATE
from riskflow_env.scenarios._npz import (
    VERSION,
    ScenarioFormatError,
    check_arrays,
    read_npz,
    write_npz,
)

MAP_SCHEMA = "riskflow-map"
# key -> (shape with named dims, allowed dtype kinds: f float, b bool, i/u int, U str)
MAP_KEYS = {
    "drivable": (("H", "W"), "b"),
    "resolution": ((), "f"),
    "origin": ((2,), "f"),
    "name": ((), "U"),
    "lane_points": (("M", 2), "f"),
    "lane_offsets": (("L+1",), "iu"),
    "lane_widths": (("L",), "f"),
    "lane_ids": (("L",), "U"),
    "lane_speed_limits": (("L",), "f"),
    "lane_successors": (("S",), "U"),
    "lane_successor_offsets": (("L+1",), "iu"),
}
OPTIONAL_MAP_KEYS = {"sdf": (("H", "W"), "f")}
MAX_LANES = 20_000  # [-] lanes of one map (a city-scale ScenarioNet map has a few thousand)
MAX_LANE_POINTS = 2_000_000  # [-] centreline points of all lanes of one map together
MAX_LANE_SUCCESSORS = 200_000  # [-] successor links of all lanes of one map together
MAX_SDF_PIXELS = 8_000_000  # [-] H * W of a raster stored without its SDF (computed on load)
# named dim -> (limit's name, value), checked from the .npy headers before anything is loaded
MAP_LIMITS = {
    "L": ("MAX_LANES", MAX_LANES),
    "L+1": ("MAX_LANES + 1", MAX_LANES + 1),
    "M": ("MAX_LANE_POINTS", MAX_LANE_POINTS),
    "S": ("MAX_LANE_SUCCESSORS", MAX_LANE_SUCCESSORS),
}
_MAP_CACHE: OrderedDict[str, DrivableMap] = OrderedDict()
MAP_CACHE_SIZE = 64


def load_map(path: str | os.PathLike, expected_hash: str | None = None) -> DrivableMap:
    """Read a map file (``schema="riskflow-map"``); one shared copy per content hash.

    Args:
        path: the ``.npz`` map file.
        expected_hash: the hash the referring scene recorded; a mismatch is an error.
    """
    path = Path(path)
    if expected_hash is not None and expected_hash in _MAP_CACHE:
        _MAP_CACHE.move_to_end(expected_hash)
        return _MAP_CACHE[expected_hash]
    arrays = read_map_arrays(path)
    digest = map_hash(arrays)
    if expected_hash is not None and digest != expected_hash:
        raise ScenarioFormatError(
            f"{path}: map content hash {digest} differs from the referenced {expected_hash}"
        )
    if digest not in _MAP_CACHE:
        _MAP_CACHE[digest] = map_from_arrays(path, arrays)
        while len(_MAP_CACHE) > MAP_CACHE_SIZE:
            _MAP_CACHE.popitem(last=False)
    return _MAP_CACHE[digest]


def read_map_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The checked arrays of map file ``path`` (no in-memory sharing: see :func:`load_map`).

    Raises:
        FileNotFoundError: no such file.
        ScenarioFormatError: naming the file, when it is not a readable map file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"map file {path} not found")
    arrays = read_npz(path, MAP_SCHEMA, check_map_members)
    return {key: value for key, value in arrays.items() if key not in ("schema", "version")}


def check_map_members(path: Path, members) -> None:
    """A map file's keys, dtypes, shapes and counts (:data:`MAP_LIMITS`), from the
    ``.npy`` headers (:func:`~riskflow_env.scenarios._npz.check_arrays`)."""
    check_arrays(path, members, MAP_KEYS, OPTIONAL_MAP_KEYS, MAP_LIMITS)
    check_sdf_budget(path, members)


def check_sdf_budget(path: Path, members, prefix: str = "") -> None:
    """ScenarioFormatError naming ``path`` when the raster ``<prefix>drivable`` has more
    than :data:`MAX_SDF_PIXELS` pixels and no ``<prefix>sdf`` member (its signed distance
    field would be computed on load: about 40 bytes and 0.2 us of CPU a pixel)."""
    height, width = members[f"{prefix}drivable"].shape
    if f"{prefix}sdf" not in members and height * width > MAX_SDF_PIXELS:
        raise ScenarioFormatError(
            f"{path}: a {height} x {width} px map without its SDF exceeds MAX_SDF_PIXELS = "
            f"{MAX_SDF_PIXELS} (the SDF would be computed on load); store it (include_sdf=True)"
        )


def read_map(path: str | os.PathLike) -> DrivableMap:
    """The map of map file ``path``, read afresh (see :func:`read_map_arrays`)."""
    return map_from_arrays(Path(path), read_map_arrays(path))


def write_map_arrays(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """Write :func:`map_to_arrays`' output as a map file (``schema="riskflow-map"``),
    atomically (a temporary file renamed over ``path``)."""
    header = {"schema": np.array(MAP_SCHEMA), "version": np.array(VERSION)}
    write_npz(Path(path), header | arrays)


def map_to_arrays(drivable_map: DrivableMap, include_sdf: bool = False) -> dict[str, np.ndarray]:
    """The arrays that store ``drivable_map`` (keys as in the module docstring)."""
    lanes = drivable_map.lanes
    points = [lane.centerline for lane in lanes]
    successors = [successor for lane in lanes for successor in lane.successors]
    arrays = {
        "drivable": drivable_map.drivable,
        "resolution": np.array(float(drivable_map.resolution)),
        "origin": drivable_map.origin.astype(np.float64),
        "name": np.array(drivable_map.name),
        "lane_points": np.concatenate(points) if points else np.zeros((0, 2)),
        "lane_offsets": np.cumsum([0] + [len(p) for p in points]).astype(np.int64),
        "lane_widths": np.array([lane.width for lane in lanes], dtype=np.float64),
        "lane_ids": string_array([lane.lane_id for lane in lanes]),
        "lane_speed_limits": np.array(
            [np.nan if lane.speed_limit is None else lane.speed_limit for lane in lanes],
            dtype=np.float64,
        ),
        "lane_successors": string_array(successors),
        "lane_successor_offsets": np.cumsum([0] + [len(lane.successors) for lane in lanes]).astype(
            np.int64
        ),
    }
    if include_sdf:
        arrays["sdf"] = drivable_map.sdf
    return arrays


def map_hash(arrays: dict[str, np.ndarray]) -> str:
    """16 hex digits of a SHA-256 over the map arrays (names, dtypes, shapes, bytes)."""
    digest = hashlib.sha256()
    for key in sorted(arrays):
        value = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}|{value.dtype.str}|{value.shape}|".encode())
        digest.update(value.tobytes())
    return digest.hexdigest()[:16]


def string_array(values) -> np.ndarray:
    """(n,) str array of ``values`` (a (0,) one when empty)."""
    values = [str(v) for v in values]
    return np.array(values, dtype=str) if values else np.zeros(0, dtype="<U1")


def map_from_arrays(path: Path, arrays: dict[str, np.ndarray]) -> DrivableMap:
    """The map of checked map arrays; ScenarioFormatError naming ``path`` when invalid."""
    try:
        points, offsets = arrays["lane_points"], arrays["lane_offsets"]
        successors, succ_offsets = arrays["lane_successors"], arrays["lane_successor_offsets"]
        for name, off, total in (
            ("lane_offsets", offsets, len(points)),
            ("lane_successor_offsets", succ_offsets, len(successors)),
        ):
            if off[0] != 0 or off[-1] != total or np.any(np.diff(off) < 0):
                raise ValueError(
                    f"'{name}' must rise from 0 to {total}, got {off[0]} .. {off[-1]}"
                    + (" (falling in between)" if np.any(np.diff(off) < 0) else "")
                )
        if np.any(np.abs(points) > MAX_MAP_COORDINATE):  # before any lane computes with them
            raise ValueError(
                f"'lane_points' holds a point beyond MAX_MAP_COORDINATE = "
                f"+-{MAX_MAP_COORDINATE:g} m"
            )
        lanes = tuple(
            Lane(
                centerline=points[offsets[i] : offsets[i + 1]],
                width=float(arrays["lane_widths"][i]),
                lane_id=str(arrays["lane_ids"][i]),
                speed_limit=None
                if np.isnan(arrays["lane_speed_limits"][i])
                else float(arrays["lane_speed_limits"][i]),
                successors=tuple(str(s) for s in successors[succ_offsets[i] : succ_offsets[i + 1]]),
            )
            for i in range(len(arrays["lane_ids"]))
        )
        return DrivableMap(
            drivable=arrays["drivable"],
            resolution=float(arrays["resolution"]),
            origin=arrays["origin"],
            sdf=arrays.get("sdf"),
            lanes=lanes,
            name=str(arrays["name"]),
        )
    except (ValueError, TypeError, IndexError) as error:
        raise ScenarioFormatError(f"{path}: invalid map ({error})") from None


__all__ = [
    "MAP_CACHE_SIZE",
    "MAP_KEYS",
    "MAP_LIMITS",
    "MAX_LANES",
    "MAX_LANE_POINTS",
    "MAX_LANE_SUCCESSORS",
    "MAX_SDF_PIXELS",
    "MAP_SCHEMA",
    "OPTIONAL_MAP_KEYS",
    "check_map_members",
    "check_sdf_budget",
    "load_map",
    "map_from_arrays",
    "map_hash",
    "map_to_arrays",
    "read_map",
    "read_map_arrays",
    "string_array",
    "write_map_arrays",
]
