"""Drivable maps from ScenarioNet / MetaDrive ``map_features``.

Lanes are the features whose type starts with ``LANE`` (bike lanes excepted). The
drivable area is, in order of preference:

1. the lanes' ``polygon`` outlines where they have one, plus the surfaces of the lanes
   without one (centreline offset by +-width/2, :func:`~riskflow_env.maps.road_polygons`;
   nuScenes lane connectors have no polygon), plus ``DRIVEWAY`` polygons, plus the
   area enclosed (even-odd) by closed road lines with ids ``boundary_<k>``: the
   nuScenes converter writes the rings of the map's drivable-area layer that way;
2. with no polygon at all, the lane surfaces from centrelines and widths
   (:func:`~riskflow_env.maps.from_lanes`);
3. with no lane at all, the faces enclosed by the road edges (``ROAD_EDGE_*``
   polylines, closed by their convex hull) that logged vehicles drive through.

Lane width: the feature's ``width`` when given, else polygon area / centreline length
(clipped to [2, 6] m), else the median of those, else :data:`DEFAULT_LANE_WIDTH`.
Successors come from ``exit_lanes``; files without any (nuScenes) get them from the
geometry: lane B continues lane A when B starts within :data:`SUCCESSOR_MAX_GAP` of
A's end with a heading change below :data:`SUCCESSOR_MAX_TURN`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import shapely

from riskflow_env.dynamics import wrap_angle
from riskflow_env.maps import DrivableMap, Lane, from_polygons, road_polygons

DEFAULT_LANE_WIDTH = 3.5  # [m] width of lanes whose file gives neither width nor polygon
LANE_WIDTH_RANGE = (2.0, 6.0)  # [m] bounds on widths estimated from polygons
SUCCESSOR_MAX_GAP = 1.0  # [m] farthest a successor may start from a lane's end
SUCCESSOR_MAX_TURN = np.pi / 4  # [rad] largest heading change from a lane to a successor
KMH, MPH = 1.0 / 3.6, 0.44704  # [m/s] per km/h and per mph


def _points(value: Any, what: str, min_points: int) -> np.ndarray | None:
    """(K, 2) float [m] from a (K, 2|3) sequence; None when too short or not finite."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] < 2:
        raise ValueError(f"{what} must have shape (K, 2) or (K, 3), got {array.shape}")
    array = array[:, :2]
    if len(array) < min_points or not np.all(np.isfinite(array)):
        return None
    return array


def _speed_limit(feature: Mapping) -> float | None:
    for key, unit in (("speed_limit_kmh", KMH), ("speed_limit_mph", MPH)):
        value = feature.get(key)
        if value is not None and np.ndim(value) == 0 and np.isfinite(value) and value > 0:
            return float(value) * unit
    return None


def _is_lane(feature: Mapping) -> bool:
    kind = str(feature.get("type", ""))
    return kind.startswith("LANE") and kind != "LANE_BIKE_LANE"


def build_map(
    features: Mapping[Any, Mapping],
    resolution: float = 0.5,
    margin: float = 5.0,
    name: str = "",
    vehicle_xy: np.ndarray | None = None,
    source: str = "<map_features>",
) -> DrivableMap:
    """DrivableMap with lanes from a ScenarioNet ``map_features`` dict.

    Args:
        features: feature id -> feature dict (``type``, ``polyline``, ``polygon``...).
        resolution: raster resolution [m/px].
        margin: off-road border around the road [m].
        name: label of the map.
        vehicle_xy: (P, 2) [m] logged vehicle positions; used only by the road-edge
            fallback to pick the faces that are road.
        source: name of the data quoted in errors.
    """
    if not isinstance(features, Mapping):
        raise ValueError(f"{source}: map_features must be a dict, got {type(features).__name__}")
    centrelines, outlines, widths, raw = {}, {}, {}, {}
    for key, feature in features.items():
        if not isinstance(feature, Mapping) or not _is_lane(feature):
            continue
        lane_id = str(key)
        line = _points(
            feature.get("polyline", np.zeros((0, 2))), f"{source}: lane {lane_id} polyline", 2
        )
        if line is None or np.all(line == line[0]):
            continue
        centrelines[lane_id], raw[lane_id] = line, feature
        if feature.get("polygon") is not None:
            outline = _points(feature["polygon"], f"{source}: lane {lane_id} polygon", 3)
            if outline is not None:
                polygon = shapely.make_valid(shapely.Polygon(outline))
                if polygon.area > 0:
                    outlines[lane_id] = polygon
        width = feature.get("width")
        if width is not None and np.size(width) > 0 and np.all(np.isfinite(width)):
            widths[lane_id] = float(np.median(width))
        elif lane_id in outlines:
            length = float(np.sum(np.linalg.norm(np.diff(line, axis=0), axis=1)))
            widths[lane_id] = float(np.clip(outlines[lane_id].area / length, *LANE_WIDTH_RANGE))
    default_width = float(np.median(list(widths.values()))) if widths else DEFAULT_LANE_WIDTH

    ids = list(centrelines)
    if any("exit_lanes" in raw[i] for i in ids):
        known = set(ids)
        successors = {
            i: tuple(str(e) for e in np.atleast_1d(raw[i].get("exit_lanes", ())) if str(e) in known)
            for i in ids
        }
    else:
        successors = _infer_successors(ids, centrelines)
    lanes = tuple(
        Lane(
            centrelines[i],
            widths.get(i, default_width),
            i,
            speed_limit=_speed_limit(raw[i]),
            successors=successors[i],
        )
        for i in ids
    )

    polygons = list(outlines.values())
    polygons += road_polygons(tuple(lane for lane in lanes if lane.lane_id not in outlines))
    for key, feature in features.items():
        if isinstance(feature, Mapping) and feature.get("type") == "DRIVEWAY":
            outline = _points(feature.get("polygon", np.zeros((0, 2))), f"{source}: {key}", 3)
            if outline is not None:
                polygons.append(shapely.make_valid(shapely.Polygon(outline)))
    polygons.append(_boundary_area(features))
    polygons = [p for p in polygons if isinstance(p, (shapely.Polygon, shapely.MultiPolygon))]
    polygons = [p for p in polygons if p.area > 0]
    if not polygons:
        polygons = _edge_faces(features, vehicle_xy, source)
    return from_polygons(polygons, resolution=resolution, margin=margin, lanes=lanes, name=name)


def _infer_successors(ids: list[str], centrelines: dict[str, np.ndarray]) -> dict[str, tuple]:
    """lane id -> ids of the lanes starting where it ends (see the module docstring)."""
    if not ids:
        return {}
    ends = np.stack([centrelines[i][-1] for i in ids])
    starts = np.stack([centrelines[i][0] for i in ids])
    end_heading = np.array(
        [np.arctan2(*np.diff(centrelines[i][-2:], axis=0)[0][::-1]) for i in ids]
    )
    start_heading = np.array(
        [np.arctan2(*np.diff(centrelines[i][:2], axis=0)[0][::-1]) for i in ids]
    )
    gap = np.linalg.norm(ends[:, None] - starts[None], axis=-1)  # (L, L): from i's end to j's start
    turn = np.abs(wrap_angle(start_heading[None] - end_heading[:, None]))
    linked = (gap <= SUCCESSOR_MAX_GAP) & (turn <= SUCCESSOR_MAX_TURN)
    np.fill_diagonal(linked, False)
    return {lane: tuple(ids[j] for j in np.flatnonzero(linked[i])) for i, lane in enumerate(ids)}


def _boundary_area(features: Mapping[Any, Mapping]) -> shapely.Geometry:
    """Even-odd fill of the closed road lines with ids ``boundary_<k>`` (empty if none)."""
    area = shapely.Polygon()
    rings = []
    for key, feature in features.items():
        if str(key).startswith("boundary_") and isinstance(feature, Mapping):
            points = np.asarray(feature.get("polyline", np.zeros((0, 2))), dtype=np.float64)
            if points.ndim == 2 and len(points) >= 4 and np.allclose(points[0, :2], points[-1, :2]):
                rings.append(shapely.make_valid(shapely.Polygon(points[:, :2])))
    for ring in sorted(rings, key=lambda ring: -ring.area):
        area = shapely.symmetric_difference(area, ring)
    parts = [p for p in shapely.get_parts(area) if isinstance(p, shapely.Polygon)]
    return shapely.MultiPolygon(parts) if parts else shapely.Polygon()


def _edge_faces(
    features: Mapping[Any, Mapping], vehicle_xy: np.ndarray | None, source: str
) -> list[shapely.Geometry]:
    """Faces of the road-edge arrangement that contain logged vehicle positions."""
    lines = []
    for key, feature in features.items():
        if isinstance(feature, Mapping) and str(feature.get("type", "")).startswith("ROAD_EDGE"):
            points = _points(feature.get("polyline", np.zeros((0, 2))), f"{source}: {key}", 2)
            if points is not None:
                lines.append(shapely.LineString(points))
    if not lines:
        raise ValueError(
            f"{source}: map_features hold no lane and no road edge to build a map from"
        )
    if vehicle_xy is None or len(vehicle_xy) == 0:
        raise ValueError(f"{source}: a map from road edges needs logged vehicle positions")
    network = shapely.union_all(lines + [shapely.MultiLineString(lines).convex_hull.boundary])
    faces = list(shapely.get_parts(shapely.polygonize(shapely.get_parts(network))))
    inside = [
        f for f in faces if shapely.intersects_xy(f, vehicle_xy[:, 0], vehicle_xy[:, 1]).any()
    ]
    if not inside:
        raise ValueError(f"{source}: no face of the road edges contains a logged vehicle")
    return inside
