"""Builders of :class:`DrivableMap` from plain polygons and from lane centrelines."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import shapely

from riskflow_env.maps._validate import finite_number
from riskflow_env.maps.drivable_map import DrivableMap
from riskflow_env.maps.lanes import Lane
from riskflow_env.maps.rasterize import RepairBudget, fill_polygons, grid_for_bounds, repair_polygon
from riskflow_env.maps.surface import open_ends, road_polygons

OPEN_END_REACH = 2.0  # [margin + 1 px] length of the straight stub that opens a road end:
# twice the distance to the raster's border, so ends meeting it at up to 60 degrees reach


def from_polygons(
    polygons: shapely.Geometry | Iterable[shapely.Geometry],
    resolution: float = 0.5,
    margin: float = 5.0,
    lanes: Iterable[Lane] = (),
    name: str = "",
    continuations: Iterable[shapely.Geometry] = (),
) -> DrivableMap:
    """Map whose drivable area is the union of ``polygons``.

    The raster covers the polygons' bounding box plus ``margin`` on every side. A pixel
    is drivable when its centre lies in one of the polygons, a centre exactly on a left or
    lower edge counting as inside and one on a right or upper edge as outside
    (:func:`~riskflow_env.maps.rasterize.fill_polygons`: no union is computed).
    Self-intersecting polygons are repaired first, within the budget of
    :func:`~riskflow_env.maps.rasterize.repair_polygon`.

    Args:
        polygons: one shapely (Multi)Polygon or an iterable of them [m].
        resolution: pixel size [m/px], > 0.
        margin: off-road border around the polygons [m], >= 0.
        lanes: lane centrelines to keep on the map.
        name: label of the map.
        continuations: (Multi)Polygons [m] of the roads beyond the map, drawn where they
            fall on the raster without widening it, each only if it reaches past the
            raster's border: where a road leaves the map it then runs to the border,
            and the map's lookups continue it beyond (a continuation that ends on the
            map is left out, the road ending there).
    """
    resolution = finite_number("resolution", resolution, "m/px")
    margin = finite_number("margin", margin, "m", allow_zero=True)
    geometries = [polygons] if isinstance(polygons, shapely.Geometry) else list(polygons)
    repairs = RepairBudget()
    for i, geometry in enumerate(geometries):
        if not isinstance(geometry, (shapely.Polygon, shapely.MultiPolygon)):
            raise ValueError(
                f"polygons[{i}] must be a shapely Polygon or MultiPolygon, "
                f"got {type(geometry).__name__}"
            )
        geometries[i] = repair_polygon(geometry, f"polygons[{i}]", repairs)
    if not geometries or not sum(g.area for g in geometries) > 0:
        raise ValueError("polygons must cover a non-empty area")
    origin, shape = grid_for_bounds(shapely.total_bounds(geometries), resolution, margin)
    corner = origin + np.array(shape[::-1]) * resolution
    for i, geometry in enumerate(continuations):
        if not isinstance(geometry, (shapely.Polygon, shapely.MultiPolygon)):
            raise ValueError(
                f"continuations[{i}] must be a shapely Polygon or MultiPolygon, "
                f"got {type(geometry).__name__}"
            )
        low, high = np.split(np.asarray(geometry.bounds), 2)
        if np.any(low < origin) or np.any(high > corner):
            geometries.append(repair_polygon(geometry, f"continuations[{i}]", repairs))
    drivable = fill_polygons(geometries, origin, shape, resolution)
    if not drivable.any():
        raise ValueError(
            f"polygons are thinner than the resolution {resolution} m/px: no pixel centre is inside"
        )
    return DrivableMap(drivable, resolution, origin, lanes=tuple(lanes), name=name)


def from_lanes(
    lanes: Iterable[Lane],
    resolution: float = 0.5,
    margin: float = 5.0,
    name: str = "",
    entry_apron: float = 0.0,
) -> DrivableMap:
    """Map whose drivable area is the union of the lanes' surfaces; keeps the lanes.

    The surface (:func:`~riskflow_env.maps.surface.road_polygons`) is each lane's
    centreline offset by +-width/2 along its normals with flat ends (not a
    round-capped buffer, so lanes do not bulge past their ends), plus a patch
    joining each lane's end to its successors' starts (closes gaps and kinks at
    junctions), plus optional entry aprons. Where the network ends on the edge of its
    bounding box (a lane without successor, or without predecessor, whose straight
    continuation, :data:`OPEN_END_REACH` x (``margin`` + 1 px) long, runs off the
    raster), the road leaves the map: it runs straight through the margin to the
    raster's border (:func:`~riskflow_env.maps.surface.open_ends`, ``continuations``
    of :func:`from_polygons`) and on beyond it. A lane that ends farther inside is a
    dead end.

    Args:
        lanes: at least one :class:`Lane`, unique ids.
        resolution: pixel size [m/px], > 0.
        margin: off-road border around the lanes [m], >= 0.
        name: label of the map.
        entry_apron: length [m], >= 0, of a straight stub of road added before the
            start of every lane that has no predecessor; none when 0.
    """
    lanes = tuple(lanes)
    if not lanes:
        raise ValueError("lanes must hold at least one Lane")
    if not all(isinstance(lane, Lane) for lane in lanes):
        raise ValueError("lanes must hold Lane objects")
    entry_apron = finite_number("entry_apron", entry_apron, "m", allow_zero=True)
    resolution = finite_number("resolution", resolution, "m/px")
    margin = finite_number("margin", margin, "m", allow_zero=True)
    reach = OPEN_END_REACH * (margin + resolution)
    return from_polygons(
        road_polygons(lanes, entry_apron),
        resolution=resolution,
        margin=margin,
        lanes=lanes,
        name=name,
        continuations=open_ends(lanes, reach, entry_apron),
    )
