"""Drivable maps from ScenarioNet / MetaDrive ``map_features``.

Feature types, lane widths and surfaces are read as each ScenarioNet converter writes
them (:mod:`~riskflow_env.scenarios.scenarionet_features`). The drivable area is, in
order of preference:

1. the lanes' ``polygon`` outlines where they have one, plus the surfaces of the lanes
   without one (centreline offset by +-width/2, :func:`~riskflow_env.maps.road_polygons`;
   nuScenes lane connectors and every Waymo lane have no polygon), plus the area
   enclosed (even-odd) by closed road lines with ids ``boundary_<k>`` (the nuScenes and
   nuPlan converters write the rings of the map's drivable-area layer that way);
2. with no polygon at all, the lane surfaces from centrelines and widths;
3. with no lane at all, the faces enclosed by the road edges (``ROAD_EDGE_*``
   polylines, closed by their convex hull) that logged vehicles drive through;

plus, in every case, the drivable surfaces that are not lanes (driveways, parking:
:data:`~riskflow_env.scenarios.scenarionet_features.SURFACE_TYPES`). Those count as
drivable area only: the lane graph (``DrivableMap.lanes``) holds lanes alone. Last,
the ground the logged vehicles stand and drive on, where the map data does not draw it
(:mod:`~riskflow_env.scenarios.logged_surface`: the nuScenes car parks).

Cropping: with ``region`` (xmin, ymin, xmax, ymax) [m], only the features that reach
into it are read and the drivable area is clipped to it, so the raster's size and the
build time follow the region the scenario uses, not the whole recording area. The roads
that cross the region's edge run on through the raster's margin to its border
(``continuations`` of :func:`~riskflow_env.maps.from_polygons`), beyond which the map
continues them: traffic can drive out of the cropped map.

Lane width: the feature's ``width`` when it gives one, else polygon area / centreline
length (clipped to [2, 6] m), else the median of those, else :data:`DEFAULT_LANE_WIDTH`.
Successors come from ``exit_lanes`` (at most ``MAX_EXIT_LANES`` per lane); files
without any (nuScenes) get them from the geometry: lane B continues lane A when B starts
within :data:`SUCCESSOR_MAX_GAP` of A's end with a heading change below
:data:`SUCCESSOR_MAX_TURN`, among the ``MAX_EXIT_LANES`` starts nearest to A's end (a
k-d tree query: linear in the number of lanes, where comparing every pair took an
L x L matrix, 3 GB for 8,000 lanes). A malformed feature raises ``ValueError`` naming
the file and the feature id; the counts are checked first
(:mod:`~riskflow_env.scenarios.scenarionet_limits`), and self-intersecting polygons are
repaired within one :class:`~riskflow_env.maps.rasterize.RepairBudget` per map.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import numpy as np
import shapely
from scipy.spatial import cKDTree

from riskflow_env.dynamics import wrap_angle
from riskflow_env.maps import DrivableMap, Lane, from_polygons, road_polygons
from riskflow_env.maps.rasterize import RepairBudget, line_crossings, repair_polygon
from riskflow_env.scenarios import scenarionet_features as feat
from riskflow_env.scenarios.logged_surface import LoggedBoxes, missing_ground
from riskflow_env.scenarios.scenarionet_limits import (
    MAX_BOUNDARY_RINGS,
    MAX_EDGE_CROSSINGS,
    MAX_EDGE_SEGMENTS,
    MAX_EXIT_LANES,
    check_lane_links,
    check_raster,
)
from riskflow_env.untrusted import MAX_QUOTE, brief, entry_id

DEFAULT_LANE_WIDTH = 3.5  # [m] width of lanes whose file gives neither width nor polygon
LANE_WIDTH_RANGE = (2.0, 6.0)  # [m] bounds on widths estimated from polygons
SUCCESSOR_MAX_GAP = 1.0  # [m] farthest a successor may start from a lane's end
SUCCESSOR_MAX_TURN = np.pi / 4  # [rad] largest heading change from a lane to a successor
REGION_SLACK = 20.0  # [m] features this close to the region are read (their surface may reach in)
KMH, MPH = 1.0 / 3.6, 0.44704  # [m/s] per km/h and per mph


def _speed_limit(feature: Mapping) -> float | None:
    for key, unit in (("speed_limit_kmh", KMH), ("speed_limit_mph", MPH)):
        value = feature.get(key)
        if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
            if np.isfinite(value) and value > 0:
                return float(value) * unit
    return None


def _name(key: Any, feature: Mapping) -> str:
    """``map feature <id> (<type>)`` for messages, in bounded length."""
    label = key[:MAX_QUOTE] if isinstance(key, str) else brief(key)
    return f"map feature {label} ({feat.kind(feature)[:MAX_QUOTE]})"


def _exit_lanes(feature: Mapping, known: set[str], what: str) -> tuple[str, ...]:
    """The ids among ``feature["exit_lanes"]`` (a list, tuple or array of str or int ids,
    at most :data:`MAX_EXIT_LANES`) that name a lane in ``known``."""
    value = feature.get("exit_lanes", ())
    if isinstance(value, np.ndarray):
        size = value.size
    else:
        size = len(value) if isinstance(value, (list, tuple)) else 1
    if size > MAX_EXIT_LANES:
        raise ValueError(f"{what} exit_lanes lists over MAX_EXIT_LANES = {MAX_EXIT_LANES} lanes")
    if isinstance(value, np.ndarray):
        value = value.reshape(-1).tolist()
    elif not isinstance(value, (list, tuple)):
        value = [value]
    ids = (str(e) if isinstance(e, str) else _int_id(e) for e in value)
    return tuple(i for i in ids if i in known)


def _int_id(value: Any) -> str | None:
    if isinstance(value, (int, np.integer)) and int(value).bit_length() <= 64:
        return str(int(value))
    return None


def build_map(
    features: Mapping[Any, Mapping],
    resolution: float = 0.5,
    margin: float = 5.0,
    name: str = "",
    vehicle_xy: np.ndarray | None = None,
    source: str = "<map_features>",
    region: tuple[float, float, float, float] | None = None,
    logged: LoggedBoxes | None = None,
) -> DrivableMap:
    """DrivableMap with lanes from a ScenarioNet ``map_features`` dict.

    Args:
        features: feature id -> feature dict (``type``, ``polyline``, ``polygon``...).
        resolution: raster resolution [m/px].
        margin: off-road border around the road [m].
        name: label of the map.
        vehicle_xy: (P, 2) [m] logged vehicle positions; used only by the road-edge
            fallback to pick the faces that are road.
        source: name of the data quoted in errors (the file).
        region: (xmin, ymin, xmax, ymax) [m] to crop the map to, or None for all of it.
        logged: the logged vehicle boxes
            (:func:`~riskflow_env.scenarios.logged_surface.logged_boxes`); those the map
            data does not cover are drivable too. None adds nothing.
    """
    if not isinstance(features, Mapping):
        raise ValueError(f"{source}: map_features must be a dict, got {type(features).__name__}")
    if region is not None:
        region = tuple(float(v) for v in region)
        if (
            len(region) != 4
            or not np.all(np.isfinite(region))
            or region[2] <= region[0]
            or (region[3] <= region[1])
        ):
            raise ValueError(f"region must be finite (xmin, ymin, xmax, ymax) [m], got {region}")
    reach = None if region is None else _grow(region, REGION_SLACK)
    centrelines, outlines, widths, raw, surfaces = {}, {}, {}, {}, []
    repairs = RepairBudget()
    for key, feature in features.items():
        if not isinstance(feature, Mapping):
            continue
        what = f"{source}: {_name(key, feature)}"
        if feat.is_surface(feature):
            outline = feature.get("polygon", np.zeros((0, 2)))
            surface = feat.polygon(outline, f"{what} polygon", repairs)
            if surface is not None and feat.touches(_outline(surface), reach):
                surfaces.append(surface)
            continue
        if not feat.is_lane(feature):
            continue
        lane_id = entry_id(key, f"{source}: a lane's map feature id")
        line = feat.points(feature.get("polyline", np.zeros((0, 2))), f"{what} polyline", 2)
        if line is None or np.all(line == line[0]) or not feat.touches(line, reach):
            continue
        centrelines[lane_id], raw[lane_id] = line, feature
        if feature.get("polygon") is not None:
            outline = feat.polygon(feature["polygon"], f"{what} polygon", repairs)
            if outline is not None:
                outlines[lane_id] = outline
        width = feat.lane_width(feature, what)
        if width is not None:
            widths[lane_id] = width
        elif lane_id in outlines:
            length = float(np.sum(np.linalg.norm(np.diff(line, axis=0), axis=1)))
            widths[lane_id] = float(np.clip(outlines[lane_id].area / length, *LANE_WIDTH_RANGE))
    default_width = float(np.median(list(widths.values()))) if widths else DEFAULT_LANE_WIDTH

    ids = list(centrelines)
    if any("exit_lanes" in raw[i] for i in ids):
        known = set(ids)
        successors = {i: _exit_lanes(raw[i], known, f"{source}: map feature {i}") for i in ids}
    else:
        successors = _infer_successors(ids, centrelines)
    check_lane_links(sum(len(found) for found in successors.values()), source)
    lanes = []
    for i in ids:
        try:
            lanes.append(
                Lane(
                    centrelines[i],
                    widths.get(i, default_width),
                    i,
                    speed_limit=_speed_limit(raw[i]),
                    successors=successors[i],
                )
            )
        except ValueError as err:
            raise ValueError(f"{source}: {_name(i, raw[i])}: {err}") from None
    lanes = tuple(lanes)

    polygons = list(outlines.values())
    polygons += road_polygons(
        tuple(lane for lane in lanes if lane.lane_id not in outlines), repairs=repairs
    )
    polygons.append(_boundary_area(features, reach, repairs))
    polygons = [p for p in polygons if isinstance(p, (shapely.Polygon, shapely.MultiPolygon))]
    polygons = [p for p in polygons if p.area > 0]
    if not polygons:
        polygons = _edge_faces(features, vehicle_xy, source)
    polygons += surfaces
    beyond = []
    if region is not None:  # the raster covers the drivable area inside the region
        polygons, beyond = (
            _clip(polygons, box) for box in (region, _grow(region, margin + 2 * resolution))
        )
        if not polygons:
            raise ValueError(f"{source}: no drivable area inside the region {region} [m]")
    check_raster(shapely.total_bounds(polygons), resolution, margin, source)
    build = functools.partial(
        from_polygons,
        resolution=resolution,
        margin=margin,
        lanes=lanes,
        name=name,
        continuations=beyond,
    )
    drawn = build(polygons)
    missing = [] if logged is None else missing_ground(logged, drawn)
    if not len(missing):
        return drawn
    check_raster(shapely.total_bounds([*polygons, *missing]), resolution, margin, source)
    return build([*polygons, *missing])


def _clip(polygons: list, box: tuple[float, float, float, float]) -> list[shapely.Polygon]:
    """The parts of ``polygons`` inside ``box`` (xmin, ymin, xmax, ymax) [m] with an area."""
    clipped = shapely.clip_by_rect(np.asarray(polygons, dtype=object), *box)
    return [p for p in shapely.get_parts(clipped) if isinstance(p, shapely.Polygon) and p.area > 0]


def _grow(region: tuple[float, float, float, float], by: float) -> tuple:
    return region[0] - by, region[1] - by, region[2] + by, region[3] + by


def _outline(shape: shapely.Geometry) -> np.ndarray:
    """(2, 2) [m] corners of a geometry's bounding box (for :func:`feat.touches`)."""
    xmin, ymin, xmax, ymax = shape.bounds
    return np.array([[xmin, ymin], [xmax, ymax]])


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
    count = min(MAX_EXIT_LANES + 1, len(ids))  # + 1: a lane may find its own start
    reach = SUCCESSOR_MAX_GAP * (1 + 1e-9) + 1e-12  # candidates; the test below is exact
    near = cKDTree(starts).query(ends, k=count, distance_upper_bound=reach)[1].reshape(len(ids), -1)
    lane, other = np.nonzero(near < len(ids))  # (L, k): from lane's end to other's start
    other = near[lane, other]
    gap = np.linalg.norm(ends[lane] - starts[other], axis=-1)
    turn = np.abs(wrap_angle(start_heading[other] - end_heading[lane]))
    linked = (gap <= SUCCESSOR_MAX_GAP) & (turn <= SUCCESSOR_MAX_TURN) & (lane != other)
    successors: dict[str, list[int]] = {i: [] for i in ids}
    for i, j in zip(lane[linked].tolist(), other[linked].tolist(), strict=True):
        successors[ids[i]].append(j)
    return {key: tuple(ids[j] for j in sorted(found)) for key, found in successors.items()}


def _boundary_area(
    features: Mapping[Any, Mapping], reach: tuple | None, repairs: RepairBudget
) -> shapely.Geometry:
    """Even-odd fill of the closed road lines with ids ``boundary_<k>`` (empty if none).

    A ring is kept whole when its bounding box meets ``reach`` (a ring around a hole
    must stay with the ring around it; the caller clips the result)."""
    area = shapely.Polygon()
    rings = []
    for key, feature in features.items():
        if isinstance(key, str) and key.startswith("boundary_") and isinstance(feature, Mapping):
            what = f"map feature {key[:MAX_QUOTE]} (boundary ring) polyline"
            points = feat.real_array(feature.get("polyline", np.zeros((0, 2))), what)
            if points.ndim == 2 and len(points) >= 4 and np.allclose(points[0, :2], points[-1, :2]):
                if feat.touches(points[:, :2], reach):
                    if len(rings) == MAX_BOUNDARY_RINGS:
                        raise ValueError(
                            f"{what}: over MAX_BOUNDARY_RINGS = {MAX_BOUNDARY_RINGS} boundary rings"
                        )
                    ring = shapely.Polygon(points[:, :2])
                    rings.append(repair_polygon(ring, what, repairs))
    rings = sorted(rings, key=lambda ring: -ring.area)
    while len(rings) > 1:  # pairwise, a balanced tree: O(V log n) for n rings of V points
        pairs = range(0, len(rings) - 1, 2)
        rings = [shapely.symmetric_difference(rings[i], rings[i + 1]) for i in pairs] + (
            rings[-1:] if len(rings) % 2 else []
        )
    area = rings[0] if rings else area
    parts = [p for p in shapely.get_parts(area) if isinstance(p, shapely.Polygon)]
    return shapely.MultiPolygon(parts) if parts else shapely.Polygon()


def _edge_faces(
    features: Mapping[Any, Mapping], vehicle_xy: np.ndarray | None, source: str
) -> list[shapely.Geometry]:
    """Faces of the road-edge arrangement that contain logged vehicle positions (at most
    ``MAX_EDGE_SEGMENTS`` segments crossing at most ``MAX_EDGE_CROSSINGS`` times: the
    arrangement grows as its crossings, 1,000 x 1,000 crossing edges took 16 s and 1.2 GB)."""
    lines = []
    for key, feature in features.items():
        if isinstance(feature, Mapping) and feat.kind(feature).startswith("ROAD_EDGE"):
            what = f"{source}: {_name(key, feature)} polyline"
            points = feat.points(feature.get("polyline", np.zeros((0, 2))), what, 2)
            if points is not None:
                lines.append(points)
    segments = sum(len(line) - 1 for line in lines)
    if (
        segments > MAX_EDGE_SEGMENTS
        or line_crossings(lines, MAX_EDGE_CROSSINGS) > MAX_EDGE_CROSSINGS
    ):
        raise ValueError(
            f"{source}: the road edges (a map without lanes is built from them) hold "
            f"{segments} segments; at most MAX_EDGE_SEGMENTS = {MAX_EDGE_SEGMENTS} crossing at "
            f"most MAX_EDGE_CROSSINGS = {MAX_EDGE_CROSSINGS} times are read"
        )
    lines = [shapely.LineString(line) for line in lines]
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
