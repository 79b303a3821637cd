"""What one ScenarioNet description may hold, checked before any array is built.

A description is counted as it is read, each shared value once per reference (one
track or polyline referenced a million times counts a million times), with ``len`` and
``size`` only, before anything is converted, stacked or rasterised. The limits are
about 20-100 times what the largest of the four nuScenes samples of ScenarioNet holds
(``sd_nuscenes_v1.0-mini_scene-0061``: 226 tracks of 201 steps, 111 of them vehicles;
586 map features, 460 of them lanes; 20,378 polyline and polygon points, at most 1,510
in one), leaving room for Waymo, nuPlan and Argoverse 2 scenes:

=====================  ==========  ===========================================
limit                  value       counts
=====================  ==========  ===========================================
``MAX_STEPS``          20,000      recorded steps, and steps at 10 Hz (2,000 s)
``MAX_TRACKS``         10,000      tracks of every type
``MAX_TRACK_STEPS``    1,000,000   vehicle tracks x steps (recorded or at 10 Hz)
``MAX_MAP_FEATURES``   20,000      map features of every type
``MAX_FEATURE_POINTS`` 20,000      points of one polyline, polygon or width
``MAX_MAP_POINTS``     1,000,000   points of all polylines and polygons
``MAX_EXIT_LANES``     64          successors listed by one lane
``MAX_BOUNDARY_RINGS`` 256         ``boundary_<k>`` rings (the sample: 29)
``MAX_MAP_PIXELS``     8,000,000   pixels of the map raster (the sample, whole
                                   map: 1,332 x 1,244 = 1.7 M at 0.5 m/px)
``MAX_EDGE_SEGMENTS``  4,096       road-edge segments, and ``MAX_EDGE_CROSSINGS``
                                   16,384 crossings among them, of a map without
                                   lanes or polygons (built from its road edges)
``MAX_LANE_LINKS``     20,000      successor links of all lanes, listed or inferred
                                   (the sample: 476; each one adds a junction patch)
=====================  ==========  ===========================================

The drivable polygons are never unioned (a union's cost grows as the crossings of their
outlines: 20 crossing combs took 12-49 s): the raster is filled from their outlines,
within :data:`~riskflow_env.maps.rasterize.MAX_FILL_CROSSINGS` crossings of edges with
pixel rows (the samples: 12,000-31,000).

At these limits a file loads in under 5 s and 500 MB (measured: 1,000,000 track-steps
1.5 s, 254 MB; 1,000,000 map points in 49 lanes 2.4 s, 450 MB; 19,990 lanes 2.9 s;
256 crossing rings of 3,900 points 4.4 s, 389 MB). The boundary rings are bounded by
count because their even-odd fill costs as their crossings (5,000 overlapping rings of
100 points: 26 s, 1 GB, then ``bad_alloc``); the raster by its pixels because the
signed distance field takes about 24 bytes a pixel.

A point has 2 or 3 coordinates; arrays are counted in numbers (3 per point). Beyond a
limit, or for a value that is not numbers (or rows of numbers), ``ValueError`` names
the file, the entry and the limit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from riskflow_env.untrusted import brief

MAX_STEPS = 20_000  # [0.1 s] recorded steps, and steps after resampling to 10 Hz (2000 s)
MAX_TRACKS = 10_000  # tracks of one description, every type
MAX_TRACK_STEPS = 1_000_000  # vehicle tracks x steps stacked into arrays
MAX_MAP_FEATURES = 20_000  # map features of one description, every type
MAX_FEATURE_POINTS = 20_000  # points of one polyline / polygon / width array
MAX_MAP_POINTS = 1_000_000  # points of all polylines and polygons of one description
MAX_EXIT_LANES = 64  # successors one lane may list
MAX_BOUNDARY_RINGS = 256  # closed boundary_<k> rings filled even-odd into the drivable area
MAX_MAP_PIXELS = 8_000_000  # pixels of the map raster (H x W)
MAX_EDGE_SEGMENTS = 4096  # road-edge segments a map without lanes is built from
MAX_EDGE_CROSSINGS = 16_384  # crossings among them (their arrangement grows as these)
MAX_LANE_LINKS = 20_000  # successor links of all lanes (listed or inferred) of one map
COORDINATES = 3  # numbers per point counted against the point limits (x, y, z)

_NUMBERS = (int, float, bool, np.number, np.bool_)


def count_numbers(value: Any, limit: int) -> int | None:
    """How many numbers ``value`` holds (an array, a number, or a list / tuple of numbers
    or of rows of numbers), counted without converting it and at most to ``limit + 1``;
    None for any other value."""
    if isinstance(value, np.ndarray):
        return value.size
    if isinstance(value, _NUMBERS):
        return 1
    if not isinstance(value, (list, tuple)):
        return None
    size = 0
    for row in value:
        if isinstance(row, _NUMBERS):
            size += 1
        elif isinstance(row, np.ndarray):
            size += row.size
        elif isinstance(row, (list, tuple)):
            if len(row) > limit:
                return limit + 1
            if not all(isinstance(number, _NUMBERS) for number in row):
                return None
            size += len(row)
        else:
            return None
        if size > limit:
            break
    return size


def value_size(value: Any, what: str, limit: int, limit_name: str) -> int:
    """:func:`count_numbers` of ``value``.

    Raises:
        ValueError naming ``what`` when ``value`` is not numbers or rows of numbers, and
        naming ``limit_name`` when it holds more than ``limit`` numbers.
    """
    size = count_numbers(value, limit)
    if size is None:
        raise ValueError(f"{what} must be numbers or rows of numbers, got {brief(value)}")
    if size > limit:
        raise ValueError(f"{what} holds over {limit} numbers, the limit {limit_name}")
    return size


def check_counts(description: Mapping[str, Any], source: str) -> None:
    """The counts of ``description`` (its ``tracks`` and ``map_features`` dicts) against the
    limits (module docstring); ValueError naming ``source`` and the entry beyond one."""
    tracks, features = description["tracks"], description["map_features"]
    for what, items, limit, name in (
        ("tracks", tracks, MAX_TRACKS, "MAX_TRACKS"),
        ("map_features", features, MAX_MAP_FEATURES, "MAX_MAP_FEATURES"),
    ):
        if len(items) > limit:
            raise ValueError(f"{source}: {len(items)} {what}, over the limit {name} = {limit}")
    total = 0
    per_feature = COORDINATES * MAX_FEATURE_POINTS
    for key, feature in features.items():
        if not isinstance(feature, Mapping):
            continue
        for field in ("polyline", "polygon", "position"):
            size = count_numbers(feature.get(field), per_feature) or 0  # malformed: 0 here
            if size > per_feature:
                raise ValueError(
                    f"{source}: map feature {brief(key)} {field} holds over {per_feature} "
                    "numbers, the limit MAX_FEATURE_POINTS (x, y, z)"
                )
            total += size
        if total > COORDINATES * MAX_MAP_POINTS:
            raise ValueError(
                f"{source}: the map features hold over {MAX_MAP_POINTS} points (x, y, z; a "
                "shared polyline counts wherever it is referenced), the limit MAX_MAP_POINTS"
            )


def check_track_steps(tracks: int, steps: int, source: str) -> None:
    """ValueError naming ``source`` when ``tracks`` x ``steps`` exceeds the limits."""
    if steps > MAX_STEPS or tracks * steps > MAX_TRACK_STEPS:
        raise ValueError(
            f"{source}: {tracks} vehicle tracks of {steps} steps exceed the limits "
            f"MAX_STEPS = {MAX_STEPS} and MAX_TRACK_STEPS = {MAX_TRACK_STEPS} (tracks x steps)"
        )


def check_lane_links(links: int, source: str) -> None:
    """ValueError naming ``source`` when the lanes hold more than :data:`MAX_LANE_LINKS`
    successor links (thousands of lanes that end where as many others start link to 64
    each: 160,000 junction patches took minutes)."""
    if links > MAX_LANE_LINKS:
        raise ValueError(
            f"{source}: the lanes hold {links} successor links, over MAX_LANE_LINKS = "
            f"{MAX_LANE_LINKS}"
        )


def check_raster(bounds: Any, resolution: float, margin: float, source: str) -> None:
    """ValueError naming ``source`` when a raster of ``bounds`` (xmin, ymin, xmax, ymax)
    [m] plus ``margin`` [m] at ``resolution`` [m/px] exceeds :data:`MAX_MAP_PIXELS` (a bad
    resolution or margin is left to the map builder to report)."""
    if not (np.isfinite(resolution) and resolution > 0 and np.isfinite(margin)):
        return
    width, height = (np.asarray(bounds[2:]) - np.asarray(bounds[:2]) + 2 * margin) / resolution
    if width * height > MAX_MAP_PIXELS:
        raise ValueError(
            f"{source}: a map of {width:.0f} x {height:.0f} px ({resolution} m/px) exceeds "
            f"MAX_MAP_PIXELS = {MAX_MAP_PIXELS}; use a coarser resolution or crop=True"
        )


__all__ = [
    "COORDINATES",
    "MAX_BOUNDARY_RINGS",
    "MAX_EDGE_CROSSINGS",
    "MAX_EDGE_SEGMENTS",
    "MAX_MAP_PIXELS",
    "MAX_EXIT_LANES",
    "MAX_LANE_LINKS",
    "MAX_FEATURE_POINTS",
    "MAX_MAP_FEATURES",
    "MAX_MAP_POINTS",
    "MAX_STEPS",
    "MAX_TRACKS",
    "MAX_TRACK_STEPS",
    "check_counts",
    "check_lane_links",
    "check_raster",
    "check_track_steps",
    "count_numbers",
    "value_size",
]
