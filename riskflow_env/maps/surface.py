"""Drivable surface of a set of lanes: lane polygons, junction patches, entry aprons and
the open ends where roads leave the map.

* Lane polygon: the centreline offset by +-width/2 along its normals, flat ends
  (not a round-capped buffer, which would bulge past lane ends).
* Junction patch: the convex hull of a lane's end edge and each successor's start
  edge. Where the two meet exactly it has no area; where a source leaves a small
  gap or a kink between them (highway-env's racetrack does), it closes the notch
  that would otherwise put vehicles driving through the junction off-road.
* Entry apron: a straight stub of the lane's width before the start of every lane
  that has no predecessor, for vehicles spawned at s = 0 of an entry lane.
* Open ends (:func:`open_ends`): straight stubs that continue every lane without
  successor beyond its end and every lane without predecessor before its start (and
  its apron), for the map builders to draw where they run off the raster: there the
  road leaves the map, and the lookups continue it beyond the border.
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

from riskflow_env.maps.lanes import Lane
from riskflow_env.maps.rasterize import RepairBudget, repair_polygon

MITER_LIMIT = 4.0  # [-] longest corner offset of lane_polygon, in half-widths


def road_polygons(
    lanes: tuple[Lane, ...], entry_apron: float = 0.0, repairs: RepairBudget | None = None
) -> list[shapely.Geometry]:
    """Polygons [m] whose union is the drivable surface of ``lanes``.

    Args:
        lanes: the lanes; successors naming lanes outside the set are ignored.
        entry_apron: length [m], >= 0, of the stub added before each lane without
            predecessor in the set; none when 0.
        repairs: for lanes read from a file, the budget their self-intersecting
            surfaces are repaired within (:func:`~riskflow_env.maps.rasterize.
            repair_polygon`); None repairs every one.
    """
    by_id = {lane.lane_id: lane for lane in lanes}
    polygons = [lane_polygon(lane, repairs) for lane in lanes]
    for lane in lanes:
        for successor in lane.successors:
            if successor in by_id:
                polygons.append(junction_polygon(lane, by_id[successor]))
    if entry_apron > 0:
        for lane in _entries(lanes):
            polygons.append(lane_polygon(_stub(lane, 0.0, -entry_apron, 0.0)))
    return [p for p in polygons if p.area > 0]


def open_ends(
    lanes: tuple[Lane, ...], length: float, entry_apron: float = 0.0
) -> list[shapely.Geometry]:
    """Straight stubs [m] of the lanes' widths where the road network ends: ``length`` [m]
    (> 0) beyond the end of each lane without successor in the set, along its final
    heading, and before the entry apron of ``entry_apron`` [m] (:func:`road_polygons`) of
    each lane without predecessor, along its initial heading."""
    by_id = {lane.lane_id: lane for lane in lanes}
    stubs = [
        _stub(lane, lane.length, 0.0, length)
        for lane in lanes
        if not any(successor in by_id for successor in lane.successors)
    ]
    stubs += [_stub(lane, 0.0, -entry_apron - length, -entry_apron) for lane in _entries(lanes)]
    return [lane_polygon(stub) for stub in stubs]


def junction_polygon(lane: Lane, successor: Lane) -> shapely.Geometry:
    """Convex hull [m] of ``lane``'s end edge and ``successor``'s start edge."""
    end_left, end_right = _edge(lane, lane.length)
    start_left, start_right = _edge(successor, 0.0)
    return shapely.MultiPoint([end_left, end_right, start_left, start_right]).convex_hull


def lane_polygon(lane: Lane, repairs: RepairBudget | None = None) -> shapely.Geometry:
    """Drivable surface of ``lane``: the centreline offset by +-width/2, flat ends.

    Each vertex moves along the bisector of its neighbouring segment normals by
    ``width/2 / cos(half turn angle)`` (a miter join, capped at ``MITER_LIMIT``
    half-widths), so straight stretches keep their exact width and sampled arcs
    keep their vertices on the offset arc. Self-intersections on the inside of very
    tight turns are repaired with ``shapely.make_valid`` (within ``repairs`` when given:
    a centreline drawn as a star made that take minutes).

    Returns:
        A shapely Polygon (or MultiPolygon after repair) [m].
    """
    points = lane.centerline
    direction = np.diff(points, axis=0)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    normal_seg = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    normal = np.empty_like(points)
    normal[0], normal[-1] = normal_seg[0], normal_seg[-1]
    bisector = normal_seg[:-1] + normal_seg[1:]
    norm = np.linalg.norm(bisector, axis=1, keepdims=True)
    cos_half = np.maximum(norm / 2.0, 1.0 / MITER_LIMIT)
    safe = np.where(norm > 1e-12, norm, 1.0)
    normal[1:-1] = np.where(norm > 1e-12, bisector / safe, normal_seg[:-1]) / cos_half
    half = 0.5 * lane.width
    left = points + half * normal
    right = points - half * normal
    polygon = Polygon(np.concatenate([left, right[::-1]]))
    if polygon.is_valid:
        return polygon
    if repairs is None:
        repaired = shapely.make_valid(polygon)
    else:
        repaired = repair_polygon(polygon, f"lane {lane.lane_id[:80]} surface", repairs)
    parts = shapely.get_parts(repaired)
    return shapely.MultiPolygon([p for p in parts if isinstance(p, Polygon) and p.area > 0])


def _edge(lane: Lane, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right lane-edge points (2,) [m] across the lane at arclength ``s``."""
    xy, heading = lane.position(np.array(s))
    left = 0.5 * lane.width * np.array([-np.sin(heading), np.cos(heading)])
    return xy + left, xy - left


def _entries(lanes: tuple[Lane, ...]) -> list[Lane]:
    """The lanes no lane names as a successor."""
    has_predecessor = {succ for lane in lanes for succ in lane.successors}
    return [lane for lane in lanes if lane.lane_id not in has_predecessor]


def _stub(lane: Lane, s: float, start: float, end: float) -> Lane:
    """Straight lane of ``lane``'s width along its heading at arclength ``s`` [m], from
    ``start`` to ``end`` [m] ahead of that point (negative: behind it)."""
    xy, heading = lane.position(np.array(s))
    direction = np.array([np.cos(heading), np.sin(heading)])
    return Lane(np.stack([xy + start * direction, xy + end * direction]), lane.width, "stub")
