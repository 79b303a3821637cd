"""Reading ScenarioNet / MetaDrive ``map_features``: types, points, lane widths, surfaces.

Field conventions come from ScenarioNet's converters
(https://github.com/metadriverse/scenarionet, ``scenarionet/converter/<source>/utils.py``):

* Lanes: type ``LANE_*`` (``LANE_SURFACE_STREET``, ``LANE_FREEWAY``,
  ``LANE_SURFACE_UNSTRUCTURE`` for nuScenes lane connectors, ``LANE_UNKNOWN``;
  ``LANE_BIKE_LANE`` is not for cars), ``polyline`` (K, 2|3), optional ``polygon``,
  ``exit_lanes``, ``speed_limit_kmh`` / ``speed_limit_mph``, optional ``width``.
* Lane ``width`` by source (:func:`lane_width`):

  - Waymo (``compute_width``): an (N, 2) float32 array per centreline point: the
    distances to the left and to the right lane boundary, a side with no boundary
    filled from the other, both 0 where the lane has no boundary at all. Full width
    = left + right per point.
  - Argoverse 2: an (N, 2) array of zeros (widths not computed): no width.
  - nuScenes, nuPlan: no ``width``; a ``polygon`` outline instead.
  - a scalar or an (N,) array: the full width (MetaDrive's own exports).

* Drivable surfaces apart from lanes (:data:`SURFACE_TYPES`, with a ``polygon``):
  Waymo ``DRIVEWAY`` (dataset 1.2+), and parking areas (``PARKING_LOT``,
  ``CARPARK_AREA``) for converters that export nuScenes' / nuPlan's carpark layer.
  Crosswalks, speed bumps, stop signs and sidewalks are not surface of their own:
  where they lie on the road, the road's own polygons cover them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import shapely

from riskflow_env.maps.rasterize import RepairBudget, repair_polygon
from riskflow_env.scenarios.scenarionet_limits import (
    COORDINATES,
    MAX_FEATURE_POINTS,
    count_numbers,
    value_size,
)

SURFACE_TYPES = frozenset({"DRIVEWAY", "PARKING_LOT", "CARPARK_AREA"})
NOT_CAR_LANES = frozenset({"LANE_BIKE_LANE"})
BOUNDARY_WIDTH_RANGE = (1.0, 12.0)  # [m] full widths taken from boundary distances (Waymo)


def real_array(
    value: Any,
    what: str,
    limit: int = COORDINATES * MAX_FEATURE_POINTS,
    limit_name: str = "MAX_FEATURE_POINTS",
) -> np.ndarray:
    """``value`` as a float64 array, its size checked before it is converted.

    Raises:
        ValueError naming ``what`` unless ``value`` holds real numbers (bool, int or
        float): complex numbers are refused, not cast (the imaginary part would be lost);
        and naming ``limit_name`` when it holds more than ``limit`` numbers
        (:func:`~riskflow_env.scenarios.scenarionet_limits.value_size`).
    """
    value_size(value, what, limit, limit_name)
    try:
        array = np.asarray(value)
        if array.dtype.kind == "c":
            raise ValueError(f"{what} holds complex numbers; expected real numbers")
        return array.astype(np.float64, copy=False)
    except (TypeError, ValueError) as err:
        if what in str(err):
            raise
        raise ValueError(f"{what} must be real numbers, got {type(value).__name__}") from None


def points(value: Any, what: str, min_points: int) -> np.ndarray | None:
    """(K, 2) float [m] from a (K, 2|3) sequence; None when too short or not finite.

    Raises:
        ValueError naming ``what`` when the array is not (K, 2|3) real numbers.
    """
    array = real_array(value, what)
    if array.ndim != 2 or array.shape[1] < 2:
        raise ValueError(f"{what} must have shape (K, 2) or (K, 3), got {array.shape}")
    array = array[:, :2]
    if len(array) < min_points or not np.all(np.isfinite(array)):
        return None
    return array


def kind(feature: Mapping) -> str:
    """A feature's ``type`` when it is a string, else ``""`` (never formatted)."""
    value = feature.get("type", "")
    return value if isinstance(value, str) else ""


def is_lane(feature: Mapping) -> bool:
    """Whether a feature is a lane that cars drive on (type ``LANE_*``, not a bike lane)."""
    return kind(feature).startswith("LANE") and kind(feature) not in NOT_CAR_LANES


def is_surface(feature: Mapping) -> bool:
    """Whether a feature is a drivable surface polygon (:data:`SURFACE_TYPES`)."""
    return kind(feature) in SURFACE_TYPES


def lane_width(feature: Mapping, what: str) -> float | None:
    """Full lane width [m] from a feature's ``width`` (module docstring), or None.

    None when the feature has no width or only zeros (Argoverse 2, lanes without
    boundaries); the caller falls back to the polygon, then the map's median.

    Raises:
        ValueError naming ``what`` for widths of another shape, negative or not finite.
    """
    raw = feature.get("width")
    if raw is None:
        return None
    width = real_array(raw, f"{what} width")
    if width.size == 0:
        return None
    if width.ndim > 2 or (width.ndim == 2 and width.shape[1] not in (1, 2)):
        raise ValueError(
            f"{what} width must be a number, (N,) or (N, 2) [m] (distances to the left and "
            f"right boundary, as ScenarioNet's Waymo converter writes), got shape {width.shape}"
        )
    if not np.all(np.isfinite(width)) or np.any(width < 0):
        raise ValueError(f"{what} width must be finite and >= 0 [m]")
    if width.ndim == 2 and width.shape[1] == 2:
        left, right = width[:, 0], width[:, 1]
        full = np.where(left > 0, left, right) + np.where(right > 0, right, left)
        full = full[full > 0]
        if not full.size:
            return None
        return float(np.clip(np.median(full), *BOUNDARY_WIDTH_RANGE))
    full = width.reshape(-1)
    full = full[full > 0]
    return float(np.median(full)) if full.size else None


def polygon(value: Any, what: str, repairs: RepairBudget | None = None) -> shapely.Geometry | None:
    """Valid shapely polygon [m] from a (K, 2|3) outline, or None when it has no area; a
    self-intersecting outline is repaired within the budget of
    :func:`~riskflow_env.maps.rasterize.repair_polygon` (ValueError naming ``what``
    beyond it)."""
    outline = points(value, what, 3)
    if outline is None:
        return None
    shape = repair_polygon(shapely.Polygon(outline), what, repairs)
    parts = [p for p in shapely.get_parts(shape) if isinstance(p, shapely.Polygon) and p.area > 0]
    if not parts:
        return None
    return parts[0] if len(parts) == 1 else shapely.MultiPolygon(parts)


def feature_bounds(features: Mapping[Any, Any]) -> tuple[float, float, float, float] | None:
    """(xmin, ymin, xmax, ymax) [m] of every finite point of every feature's
    ``polyline`` / ``polygon`` (K, 2|3) and ``position`` (2|3,): how far the map data
    reaches. None when there is no point. Values of other shapes are skipped here
    (the map builder reports malformed features)."""
    arrays = []
    for feature in features.values():
        if not isinstance(feature, Mapping):
            continue
        for key in ("polyline", "polygon", "position"):
            value = feature.get(key)
            if value is None:
                continue
            size = count_numbers(value, COORDINATES * MAX_FEATURE_POINTS)  # before converting
            if size is None or size > COORDINATES * MAX_FEATURE_POINTS:
                continue
            array = np.asarray(value)
            if array.dtype.kind not in "fiu" or array.ndim not in (1, 2) or array.shape[-1] < 2:
                continue
            arrays.append(array[None, :2] if array.ndim == 1 else array[:, :2])
    if not arrays:
        return None
    xy = np.concatenate(arrays).astype(np.float64)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return None
    low, high = xy.min(axis=0), xy.max(axis=0)
    return float(low[0]), float(low[1]), float(high[0]), float(high[1])


def touches(array: np.ndarray, region: tuple[float, float, float, float] | None) -> bool:
    """Whether the bounding box of ``array`` (K, 2) [m] meets ``region`` (None: always)."""
    if region is None:
        return True
    low, high = array.min(axis=0), array.max(axis=0)
    return bool(
        low[0] <= region[2]
        and high[0] >= region[0]
        and low[1] <= region[3]
        and high[1] >= region[1]
    )
