"""DrivableMap from a highway-env road network.

The env of the family is instantiated (``gymnasium.make(id).unwrapped``) and reset
with ``seed``; every lane of ``road.network`` is sampled along its arclength with
``lane.position(s, 0)`` and becomes a :class:`Lane` with id ``"from->to#index"``;
the drivable area is the union of the lane surfaces (:func:`from_lanes`).

Environment ids used (the newest registered versions in highway-env 1.12):

=============  ===================  =================================
family         gymnasium id         road
=============  ===================  =================================
highway        highway-v0           4 straight lanes, 10 km (cut)
merge          merge-v1             3 lanes + on-ramp (sine lane)
roundabout     roundabout-v1        2-lane ring, 4 entries/exits
intersection   intersection-v2      4-way crossing, turning arcs
racetrack      racetrack-v1         2-lane closed circuit
exit           exit-v1              6 lanes + exit lane and ramp
u-turn         u-turn-v1            2 lanes each way, joined by arcs
=============  ===================  =================================
"""

from __future__ import annotations

import functools
import math
from enum import Enum

import numpy as np

from riskflow_env.maps._validate import finite_number
from riskflow_env.maps.builders import from_lanes
from riskflow_env.maps.drivable_map import DrivableMap
from riskflow_env.maps.lanes import Lane


class RoadFamily(str, Enum):
    """The highway-env road networks that maps and recorded scenes are built from."""

    HIGHWAY = "highway"
    MERGE = "merge"
    ROUNDABOUT = "roundabout"
    INTERSECTION = "intersection"
    RACETRACK = "racetrack"
    EXIT = "exit"
    U_TURN = "u-turn"


FAMILIES = tuple(family.value for family in RoadFamily)
"""The road family names, in :class:`RoadFamily`'s order (the round-robin of ``riskflow-data``)."""


def road_family(family: str | RoadFamily) -> str:
    """The name of ``family`` (a :class:`RoadFamily` or its value); ValueError naming the
    valid ones otherwise."""
    try:
        return RoadFamily(family).value
    except ValueError:
        raise ValueError(
            f"unknown family {family!r}; valid families: {', '.join(FAMILIES)}"
        ) from None


ENV_IDS = {
    "highway": "highway-v0",
    "merge": "merge-v1",
    "roundabout": "roundabout-v1",
    "intersection": "intersection-v2",
    "racetrack": "racetrack-v1",
    "exit": "exit-v1",
    "u-turn": "u-turn-v1",
}
SAMPLE_STEP = 1.0  # [m] arclength between centreline samples of curved lanes
MARGIN = 5.0  # [m] off-road border around the road network
ENTRY_APRON = 5.0  # [m] = highway-env's AbstractLane.VEHICLE_LENGTH; it spawns vehicles
# at s = 0 of entry lanes, and its on_lane test counts lanes as this much longer
SUCCESSOR_MAX_GAP = 0.75  # [lane widths] farthest a successor's start may be from the end
SUCCESSOR_MAX_TURN = math.pi / 2  # [rad] largest heading change from a lane to a successor


def from_highway_env(
    family: str,
    resolution: float = 0.5,
    max_length: float = 600.0,
    seed: int = 0,
    entry_apron: float = ENTRY_APRON,
) -> DrivableMap:
    """Drivable map and lanes of a highway-env scenario family (cached, shared).

    Maps are memoised on the arguments: the same frozen, read-only object is
    returned for the same arguments.

    Args:
        family: a :class:`RoadFamily` or its name (:data:`FAMILIES`).
        resolution: pixel size [m/px], > 0.
        max_length: lanes are cut to their first ``max_length`` metres of arclength
            [m], > 0 (highway-env's highway lanes are 10 km long); a cut lane has
            no successors. highway-v0 spawns its traffic over x in about
            [170, 1250] m: a map for that traffic needs ``max_length`` ~1600 m.
        seed: seed of the env reset (the road networks of these families do not
            depend on it).
        entry_apron: length [m], >= 0, of straight road added before every lane
            without predecessor (highway-env spawns vehicles at s = 0, whose rear
            would otherwise stick 2.5 m off the road). Lanes are not extended.

    Returns:
        A :class:`DrivableMap` named ``family`` with the network's lanes.
    """
    family = road_family(family)
    resolution = finite_number("resolution", resolution, "m/px")
    max_length = finite_number("max_length", max_length, "m")
    entry_apron = finite_number("entry_apron", entry_apron, "m", allow_zero=True)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int, got {seed!r}")
    return _build(family, resolution, max_length, int(seed), entry_apron)


@functools.lru_cache(maxsize=32)
def _build(
    family: str, resolution: float, max_length: float, seed: int, entry_apron: float
) -> DrivableMap:
    lanes = highway_env_lanes(family, max_length, seed)
    return from_lanes(lanes, resolution, MARGIN, name=family, entry_apron=entry_apron)


def highway_env_lanes(family: str, max_length: float = 600.0, seed: int = 0) -> tuple[Lane, ...]:
    """The lanes of the road network of ``family`` (see :func:`from_highway_env`).

    Successors follow highway-env's ``RoadNetwork.next_lane`` rule (same index on
    a road with as many lanes, else the closest lane), keeping only those that
    continue the lane geometrically: start within ``SUCCESSOR_MAX_GAP`` lane widths
    of its end, heading within ``SUCCESSOR_MAX_TURN``. The rule alone also names
    lane changes (roundabout exits, the exit ramp) and U-turns at the edge of the
    intersection map.
    """
    network = highway_env_network(family, seed)
    lanes = []
    for start, ends in network.graph.items():
        for end, road in ends.items():
            for index, lane in enumerate(road):
                cut = lane.length > max_length
                widths = [lane.width_at(s) for s in np.linspace(0.0, lane.length, 5)]
                lanes.append(
                    Lane(
                        centerline=_sample(lane, min(lane.length, max_length)),
                        width=float(max(widths)),
                        lane_id=f"{start}->{end}#{index}",
                        speed_limit=_speed_limit(lane),
                        successors=() if cut else _successors(network, start, end, index),
                    )
                )
    return tuple(lanes)


def highway_env_network(family: str, seed: int = 0):
    """The highway-env ``RoadNetwork`` of ``family`` (its env reset with ``seed``); lane
    ``graph[start][end][index]`` is the :class:`Lane` ``"start->end#index"``."""
    family = road_family(family)
    import gymnasium
    import highway_env  # noqa: F401  (registers the envs)

    env = gymnasium.make(ENV_IDS[family]).unwrapped
    try:
        env.reset(seed=seed)
        return env.road.network
    finally:
        env.close()


def _sample(lane, length: float) -> np.ndarray:
    """(N, 2) [m] centreline points of a highway-env lane over s in [0, length]."""
    from highway_env.road.lane import StraightLane

    if type(lane) is StraightLane:  # exact with its two ends (SineLane is a subclass)
        s = np.array([0.0, length])
    else:
        s = np.linspace(0.0, length, max(int(math.ceil(length / SAMPLE_STEP)), 1) + 1)
    return np.array([lane.position(float(v), 0.0) for v in s], dtype=np.float64)


def _speed_limit(lane) -> float | None:
    limit = getattr(lane, "speed_limit", None)
    return None if limit is None or not limit > 0 else float(limit)


def _successors(network, start: str, end: str, index: int) -> tuple[str, ...]:
    """Ids of the lanes that continue (start, end, index), see :func:`highway_env_lanes`."""
    road = network.graph[start][end]
    lane = road[index]
    end_point = lane.position(lane.length, 0.0)
    end_heading = lane.heading_at(lane.length)
    successors = []
    for after, next_road in network.graph.get(end, {}).items():
        if len(next_road) == len(road):
            next_index = index
        else:
            next_index = min(range(len(next_road)), key=lambda i: next_road[i].distance(end_point))
        nxt = next_road[next_index]
        gap = np.linalg.norm(nxt.position(0.0, 0.0) - end_point)
        turn = abs((nxt.heading_at(0.0) - end_heading + math.pi) % (2 * math.pi) - math.pi)
        if gap <= SUCCESSOR_MAX_GAP * lane.width_at(lane.length) and turn < SUCCESSOR_MAX_TURN:
            successors.append(f"{end}->{after}#{next_index}")
    return tuple(successors)
