"""highway-env road networks as ASAM OpenDRIVE 1.7 (``.xodr``, ``[interop]`` extra).

:func:`save_opendrive` writes the road of a scene whose map is a highway-env family's
(:func:`~riskflow_env.maps.from_highway_env`: ``map.name`` is the family and every lane id
``"start->end#index"`` names a lane of its network), with ``scenariogeneration``'s writer:

* every lane of the map is one OpenDRIVE road (named by the lane id) with one driving lane
  of the lane's width, centred on the road's reference line by a lane offset of half the
  width;
* the reference line follows highway-env's geometry exactly: a ``StraightLane`` is a
  ``line`` (cut to the map's lane length, 600 m at most), a ``CircularLane`` an ``arc``
  (curvature +-1 / radius, positive counter-clockwise); a ``SineLane`` is a ``line`` along
  its straight axis with the sine in the lane offset, cubic pieces of at most
  :data:`SINE_PIECE` (Hermite: the offset and its slope exact at each piece's ends);
* roads are not linked (highway-env's lanes fork and merge without junctions, which
  OpenDRIVE would need), and the elevation is flat.

Any other map (recorded data, CommonRoad lanelets, plain polygons) has no OpenDRIVE road:
:func:`is_highway_env_map` says which.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.folder_lock import make_output_file
from riskflow_env.maps import FAMILIES, DrivableMap
from riskflow_env.maps.highway import highway_env_network

SINE_PIECE = 5.0  # [m] longest cubic piece of a SineLane's lane offset
OPENDRIVE_MINOR = "7"  # OpenDRIVE 1.7


def _split(lane_id: str) -> tuple[str, str, int] | None:
    start, _, rest = lane_id.partition("->")
    end, _, index = rest.rpartition("#")
    return (start, end, int(index)) if start and end and index.isdigit() else None


def is_highway_env_map(drivable_map: DrivableMap) -> bool:
    """Whether ``drivable_map`` is a highway-env family's map (module docstring)."""
    return (
        drivable_map.name in FAMILIES
        and bool(drivable_map.lanes)
        and all(_split(lane.lane_id) for lane in drivable_map.lanes)
    )


def highway_env_lane(network: Any, lane_id: str) -> Any:
    """The highway-env lane ``"start->end#index"`` of ``network``; ValueError naming it when
    the network has no such lane."""
    parts = _split(lane_id)
    try:
        start, end, index = parts  # type: ignore[misc]
        return network.graph[start][end][index]
    except (TypeError, KeyError, IndexError):
        raise ValueError(f"lane {lane_id!r} is not a lane of the highway-env network") from None


def save_opendrive(drivable_map: DrivableMap, path: str | os.PathLike) -> Path:
    """Write the road network of a highway-env map (module docstring) to ``path``."""
    from highway_env.road.lane import CircularLane, SineLane, StraightLane
    from scenariogeneration import xodr

    if not is_highway_env_map(drivable_map):
        raise ValueError(
            f"map {drivable_map.name!r} is not a highway-env family's map: OpenDRIVE roads are "
            "written for highway-env road networks only"
        )
    network = highway_env_network(drivable_map.name)
    opendrive = xodr.OpenDrive(drivable_map.name, revMinor=OPENDRIVE_MINOR)
    for number, lane in enumerate(drivable_map.lanes, start=1):
        source = highway_env_lane(network, lane.lane_id)
        width = float(lane.width)
        offsets = [(0.0, width / 2.0, 0.0, 0.0, 0.0)]
        if isinstance(source, SineLane):
            length = float(source.length)
            start, heading = np.asarray(source.start, float), float(source.heading)
            offsets = _sine_offsets(source, length, width)
            geometry = xodr.Line(length)
        elif isinstance(source, StraightLane):
            length = float(lane.length)  # the map's cut
            start, heading = np.asarray(source.start, float), float(source.heading)
            geometry = xodr.Line(length)
        elif isinstance(source, CircularLane):
            length = float(source.length)
            start, heading = np.asarray(source.position(0.0, 0.0)), float(source.heading_at(0))
            geometry = xodr.Arc(float(source.direction) / float(source.radius), length=length)
        else:
            raise ValueError(
                f"lane {lane.lane_id!r} is a highway-env {type(source).__name__}; OpenDRIVE "
                "export knows StraightLane, CircularLane and SineLane"
            )
        planview = xodr.PlanView(float(start[0]), float(start[1]), heading)
        planview.add_geometry(geometry)
        section = xodr.LaneSection(0, xodr.Lane())
        driving = xodr.Lane(a=width)
        driving.add_roadmark(xodr.RoadMark(xodr.RoadMarkType.solid))
        section.add_right_lane(driving)
        lanes = xodr.Lanes()
        lanes.add_lanesection(section)
        for s, a, b, c, d in offsets:
            lanes.add_laneoffset(xodr.LaneOffset(s, a, b, c, d))
        road = xodr.Road(number, planview, lanes, name=lane.lane_id)
        road.add_elevation(0.0, 0.0, 0.0, 0.0, 0.0)
        planview.adjust_geometries()
        opendrive.add_road(road)
    path = make_output_file(path)
    opendrive.write_xml(str(path))
    return path


def _sine_offsets(lane: Any, length: float, width: float) -> list[tuple[float, ...]]:
    """(s, a, b, c, d) lane-offset pieces: width / 2 plus the SineLane's lateral sine."""
    amplitude, pulsation, phase = (float(v) for v in (lane.amplitude, lane.pulsation, lane.phase))
    nodes = np.linspace(0.0, length, max(math.ceil(length / SINE_PIECE), 1) + 1)
    value = width / 2.0 + amplitude * np.sin(pulsation * nodes + phase)
    slope = amplitude * pulsation * np.cos(pulsation * nodes + phase)
    pieces = []
    for k in range(len(nodes) - 1):
        h = nodes[k + 1] - nodes[k]
        delta = value[k + 1] - value[k]
        c = (3 * delta - (2 * slope[k] + slope[k + 1]) * h) / h**2
        d = ((slope[k] + slope[k + 1]) * h - 2 * delta) / h**3
        pieces.append((float(nodes[k]), float(value[k]), float(slope[k]), float(c), float(d)))
    return pieces


__all__ = ["highway_env_lane", "is_highway_env_map", "save_opendrive"]
