"""Drivable-area maps: raster + signed distance field + lane centrelines
(docs/explanation/architecture.md).

Public names:

* :class:`Lane` — centreline polyline with width, id, speed limit and successors.
* :class:`DrivableMap` — boolean raster, SDF [m] (negative on the road), lanes;
  ``sdf_at`` / ``is_drivable`` / ``crop`` work on numpy arrays and torch tensors.
* :class:`MapStack` — several maps' SDFs looked up in one call (a map per query row).
* Builders: :func:`from_polygons`, :func:`from_lanes`, :func:`from_highway_env`
  (families in :data:`FAMILIES`).
"""

from __future__ import annotations

from riskflow_env.maps.builders import from_lanes, from_polygons
from riskflow_env.maps.drivable_map import DrivableMap
from riskflow_env.maps.highway import (
    FAMILIES,
    RoadFamily,
    from_highway_env,
    highway_env_lanes,
    road_family,
)
from riskflow_env.maps.lanes import Lane
from riskflow_env.maps.stack import MapStack
from riskflow_env.maps.surface import lane_polygon, road_polygons

__all__ = [
    "FAMILIES",
    "RoadFamily",
    "DrivableMap",
    "Lane",
    "MapStack",
    "from_highway_env",
    "from_lanes",
    "from_polygons",
    "highway_env_lanes",
    "lane_polygon",
    "road_family",
    "road_polygons",
]
