"""Scenarios and rollouts as CommonRoad XML (``commonroad-io``, ``[interop]`` extra).

:func:`save_commonroad` writes, with commonroad-io's own writer (2020a format, positions
to :data:`DECIMALS` decimals):

* the road: every lane of the map as a lanelet (its left and right bounds are the lane's
  surface edges, :func:`~riskflow_env.maps.lane_polygon`; successors and predecessors
  from the lanes'), or, for a map without lanes, what is not drivable within the raster
  (the complement of :mod:`~riskflow_env.scenarios.map_outline`'s outline) as one static
  obstacle of type ``roadBoundary``, the form CommonRoad's drivability checker gives road
  boundaries (the 2020a XML format has no drivable-area shape);
* every vehicle but the ego as a dynamic obstacle (a rectangle of its length and width;
  type ``car`` or its kind where CommonRoad has it) with its track from the current step
  on as the trajectory (time step 0 is the current step; a vehicle that enters later starts
  at its first valid step; a track with a gap ends at the gap);
* the ego as the planning problem: its state at the current step as the initial state,
  the goal the scene's time span (CommonRoad has no goal the scene knows: a position
  region would be invented).

:func:`commonroad_ids` gives the obstacle id of every row, the lanelet ids follow the
map's lane order from 1. What is lost: the history before the current step, the ego's
track (the planner under test drives it; CommonRoad keeps it in a solution file, not in
the scenario), lane ids (lanelet ids are integers), the raster where the map has lanes.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from pathlib import Path

import numpy as np
import shapely

from riskflow_env.folder_lock import make_output_file
from riskflow_env.maps import lane_polygon
from riskflow_env.scenarios.commonroad_import import VEHICLE_TYPES, commonroad_io
from riskflow_env.scenarios.map_outline import drivable_outline
from riskflow_env.scenarios.scenario import Scenario

DECIMALS = 4  # positions [m] and angles [rad] written to this many decimals
COUNTRY = "ZAM"  # CommonRoad's country code of synthetic scenes ("Zamunda")
ROAD_BOUNDARY_ID = 1  # the off-road obstacle of a map without lanes


def commonroad_ids(scenario: Scenario) -> dict[int, int]:
    """Row -> obstacle id of every vehicle (the ego's is the planning problem's id), after
    the lanelet ids of the map (or its road-boundary obstacle)."""
    first = len(scenario.map.lanes) or ROAD_BOUNDARY_ID
    return {row: first + 1 + row for row in range(scenario.num_agents)}


def save_commonroad(scenario: Scenario, path: str | os.PathLike) -> Path:
    """Write ``scenario`` (module docstring) to ``path`` (``.xml``); returns the path."""
    commonroad_io()
    from commonroad.common.file_writer import CommonRoadFileWriter, OverwriteExistingFile
    from commonroad.common.util import Interval
    from commonroad.planning.goal import GoalRegion
    from commonroad.planning.planning_problem import PlanningProblem, PlanningProblemSet
    from commonroad.scenario.scenario import Scenario as CommonRoadScenario
    from commonroad.scenario.scenario import ScenarioID
    from commonroad.scenario.state import CustomState, InitialState

    name = re.sub(r"[^A-Za-z0-9]", "", (scenario.family or "riskflow").title()) or "Riskflow"
    scenario_id = ScenarioID(country_id=COUNTRY, map_name=name, map_id=1, configuration_id=1,
                             obstacle_behavior="T", prediction_id=1)  # fmt: skip
    document = CommonRoadScenario(dt=float(scenario.dt), scenario_id=scenario_id)
    _road(scenario, document)
    now, ids = scenario.current_index, commonroad_ids(scenario)
    last = scenario.states.shape[1] - 1 - now
    for row in range(scenario.num_agents):
        if row != scenario.ego_index:
            obstacle = _obstacle(scenario, row, ids[row])
            if obstacle is not None:
                document.add_objects(obstacle)
    ego = _state(scenario.states[scenario.ego_index, now], 0, InitialState)
    goal = GoalRegion([CustomState(time_step=Interval(0, max(last, 1)))])
    problems = PlanningProblemSet([PlanningProblem(ids[scenario.ego_index], ego, goal)])
    path = make_output_file(path)
    writer = CommonRoadFileWriter(document, problems, author="riskflow-env", affiliation="",
                                  source=scenario.source or "riskflow-env", tags=set(),
                                  decimal_precision=DECIMALS)  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the writer prints and warns of its own defaults
        writer.write_to_file(str(path), OverwriteExistingFile.ALWAYS)
    return path


def _road(scenario: Scenario, document) -> None:
    """The map's lanes as lanelets, or its outline as areas."""
    from commonroad.scenario.lanelet import Lanelet

    lanes = scenario.map.lanes
    if not lanes:
        document.add_objects(_road_boundary(scenario, ROAD_BOUNDARY_ID))
        return
    number = {lane.lane_id: k for k, lane in enumerate(lanes, start=1)}
    predecessors: dict[str, list[int]] = {lane.lane_id: [] for lane in lanes}
    for lane in lanes:
        for successor in lane.successors:
            if successor in predecessors:
                predecessors[successor].append(number[lane.lane_id])
    for lane in lanes:
        left, right = _bounds(lane)
        document.lanelet_network.add_lanelet(
            Lanelet(left, (left + right) / 2, right, number[lane.lane_id],
                    predecessor=predecessors[lane.lane_id],
                    successor=[number[s] for s in lane.successors if s in number])
        )  # fmt: skip


def _road_boundary(scenario: Scenario, obstacle_id: int):
    """A ``roadBoundary`` static obstacle covering the raster but the drivable area
    (triangles of a constrained Delaunay triangulation: CommonRoad polygons have no holes)."""
    from commonroad.geometry.shape import Polygon, ShapeGroup
    from commonroad.scenario.obstacle import ObstacleType, StaticObstacle
    from commonroad.scenario.state import InitialState

    offroad = shapely.box(*scenario.map.bounds).difference(drivable_outline(scenario.map))
    triangles = shapely.get_parts(shapely.constrained_delaunay_triangles(offroad))
    shape = ShapeGroup([Polygon(np.asarray(t.exterior.coords)[:-1]) for t in triangles])
    origin = _state(np.zeros(4), 0, InitialState)
    return StaticObstacle(obstacle_id, ObstacleType.ROAD_BOUNDARY, shape, origin)


def _bounds(lane) -> tuple[np.ndarray, np.ndarray]:
    """(K, 2) left and right bounds [m] of ``lane``'s surface, point by point."""
    surface = lane_polygon(lane)
    count = len(lane.centerline)
    if isinstance(surface, shapely.Polygon):
        ring = np.asarray(surface.exterior.coords)[:-1]
        if len(ring) == 2 * count:
            return ring[:count], ring[count:][::-1]
    normal = np.diff(lane.centerline, axis=0)  # a tight turn: plain per-segment normals
    normal = np.concatenate([normal, normal[-1:]]) / np.linalg.norm(
        np.concatenate([normal, normal[-1:]]), axis=1, keepdims=True
    )
    left = np.stack([-normal[:, 1], normal[:, 0]], axis=1) * lane.width / 2
    return lane.centerline + left, lane.centerline - left


def _obstacle(scenario: Scenario, row: int, obstacle_id: int):
    """The dynamic obstacle of ``row`` (its first run of valid steps from the current
    step on), or None when it is never valid from then on."""
    from commonroad.geometry.shape import Rectangle
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
    from commonroad.scenario.state import CustomState, InitialState
    from commonroad.scenario.trajectory import Trajectory

    now = scenario.current_index
    valid = scenario.valid[row, now:]
    if not valid.any():
        return None
    first = int(np.argmax(valid))
    gap = np.flatnonzero(~valid[first:])
    stop = first + (int(gap[0]) if gap.size else len(valid) - first)
    states = scenario.states[row, now:]
    kind = scenario.kinds[row] if scenario.kinds else "car"
    kind = kind if kind in VEHICLE_TYPES and kind != "unknown" else "car"
    shape = Rectangle(float(scenario.length[row]), float(scenario.width[row]))
    initial = _state(states[first], first, InitialState)
    prediction = None
    if stop - first > 1:
        track = [_state(states[k], k, CustomState) for k in range(first + 1, stop)]
        prediction = TrajectoryPrediction(Trajectory(first + 1, track), shape)
    return DynamicObstacle(obstacle_id, ObstacleType(kind), shape, initial, prediction)


def _state(state: np.ndarray, time_step: int, kind):
    """A CommonRoad state of ``state`` (x, y, v, psi) at ``time_step``."""
    x, y, speed, heading = (float(v) for v in state)
    values = dict(time_step=int(time_step), position=np.array([x, y]), orientation=heading,
                  velocity=speed)  # fmt: skip
    if kind.__name__ == "InitialState":
        values.update(acceleration=0.0, yaw_rate=0.0, slip_angle=0.0)
    return kind(**values)


__all__ = ["commonroad_ids", "save_commonroad"]
