"""CommonRoad XML scenarios as :class:`~riskflow_env.scenarios.Scenario` (``[interop]`` extra).

:func:`load_commonroad` reads a file with ``commonroad-io``'s own reader and turns it into a
scene this package drives:

* Map: every lanelet's polygon (left bound, then the right bound reversed) that cars drive
  on (not :data:`NOT_FOR_CARS`: sidewalks, crosswalks, bicycle lanes), unioned and
  rasterised (:func:`~riskflow_env.maps.from_polygons`); each such lanelet is also a lane
  (centre vertices, the median distance between its bounds as width, its successors), for
  IDM traffic, route-following planners and the generator's map context.
* Ego: the first planning problem's initial state (its time step is the scene's current
  step), with the size of CommonRoad's vehicle type 2 (:data:`EGO_SIZE`, the benchmarks'
  usual ego); it has no reference future (CommonRoad gives a goal region, not a track).
* Other vehicles: the dynamic obstacles of the vehicle types (:data:`VEHICLE_TYPES`), each a
  logged track (initial state and trajectory), its kind the CommonRoad type; a rectangle
  gives length and width, a circle its diameter for both. A negative velocity (reversing)
  becomes a positive speed with the heading turned by pi (this package's headings follow
  the direction of motion).
* Time: a file whose ``dt`` is not 0.1 s is resampled to 10 Hz
  (:func:`~riskflow_env.scenarios.scenarionet_tracks.resample`). The history holds the 31
  steps up to the current one (steps before the recording are not valid), the future the
  rest of the recording, padded with invalid steps to ``min_future_steps``.

Static obstacles, traffic signs and lights, and the goal region are not used.
``commonroad-io`` pins protobuf 3.20; with a newer protobuf (tensorboard's, ray's) it
loads with protobuf's pure-Python parser (:func:`commonroad_io`).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from riskflow_env.maps import Lane, from_polygons
from riskflow_env.maps.drivable_map import MAX_MAP_COORDINATE
from riskflow_env.maps.rasterize import RepairBudget, repair_polygon
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_limits import MAX_STEPS, MAX_TRACK_STEPS, MAX_TRACKS
from riskflow_env.scenarios.scenarionet_tracks import DT, hold_nearest_valid, resample
from riskflow_env.state import HISTORY_STEPS

MIN_DT, MAX_DT = 0.01, 1.0  # [s] time steps a recorded CommonRoad scenario may have

EGO_SIZE = (4.508, 1.610)  # [m] CommonRoad vehicle type 2 (BMW 320i), length and width
NOT_FOR_CARS = frozenset({"sidewalk", "crosswalk", "bicycleLane"})
VEHICLE_TYPES = frozenset(
    {"car", "truck", "bus", "taxi", "motorcycle", "priorityVehicle", "parkedVehicle", "unknown"}
)
MIN_FUTURE_STEPS = 100  # [steps of 0.1 s] one default episode
INSTALL = (
    "pip install 'riskflow-env[interop]' (with a protobuf newer than 3.20 imported first, "
    "set PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION=python)"
)


def commonroad_io() -> Any:
    """The ``commonroad`` package; ImportError saying how to install it when it is missing
    or does not import.

    commonroad-io's generated protobuf modules load with protobuf 3.20 or with a newer
    protobuf's pure-Python parser: when nothing has imported protobuf yet,
    ``PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION`` is set to ``python`` (unless set already).
    """
    if "google.protobuf" not in sys.modules:
        os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")
    try:
        import commonroad
        from commonroad.common import file_reader, file_writer  # noqa: F401
    except Exception as err:  # protobuf's TypeError is not an ImportError
        raise ImportError(f"CommonRoad files need commonroad-io: {INSTALL} ({err})") from None
    return commonroad


def is_commonroad_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an ``.xml`` file whose root element is ``commonRoad``."""
    path = Path(path)
    if path.suffix != ".xml" or not path.is_file():
        return False
    with path.open("rb") as handle:
        head = handle.read(4096)
    return b"<commonRoad" in head


def load_commonroad(
    path: str | os.PathLike,
    resolution: float = 0.5,
    margin: float = 5.0,
    min_future_steps: int = MIN_FUTURE_STEPS,
) -> Scenario:
    """Load one CommonRoad XML scenario (module docstring).

    Args:
        path: the ``.xml`` file.
        resolution: map raster resolution [m/px].
        margin: off-road border around the lanelets [m].
        min_future_steps: the reference future has at least this many steps [0.1 s].

    Returns:
        A Scenario named ``"commonroad/<scenario id>"``, the ego row 0, ``dt`` 0.1 s.

    Raises:
        FileNotFoundError: no such file.
        ImportError: without ``commonroad-io`` (the ``[interop]`` extra).
        ValueError: naming the file, for a file the reader refuses, one without a planning
            problem or without a lanelet cars drive on.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_commonroad: no such file {path}")
    commonroad_io()
    from commonroad.common.file_reader import CommonRoadFileReader

    try:
        scenario, problems = CommonRoadFileReader(str(path)).open()
    except Exception as err:
        raise ValueError(f"{path}: not a readable CommonRoad scenario ({err})") from None
    if not problems.planning_problem_dict:
        raise ValueError(f"{path}: no planning problem: the ego starts from one")
    problem = problems.planning_problem_dict[min(problems.planning_problem_dict)]
    drivable_map = _map(scenario, path, resolution, margin)
    rows = [(str(problem.planning_problem_id), "car", EGO_SIZE, [problem.initial_state])]
    for obstacle in scenario.dynamic_obstacles:
        kind = obstacle.obstacle_type.value
        if kind not in VEHICLE_TYPES:
            continue
        trajectory = getattr(obstacle.prediction, "trajectory", None)
        states = [obstacle.initial_state, *(trajectory.state_list if trajectory else [])]
        rows.append((str(obstacle.obstacle_id), kind, _size(obstacle, path), states))
    now = int(problem.initial_state.time_step)
    tracks = [row[3] for row in rows]
    _check_tracks(tracks, float(scenario.dt), path)
    states, valid = _tracks(tracks, now, float(scenario.dt), min_future_steps)
    size = np.array([row[2] for row in rows], dtype=np.float64)
    name = str(scenario.scenario_id)
    return Scenario(
        map=drivable_map,
        states=states,
        valid=valid,
        length=size[:, 0],
        width=size[:, 1],
        ego_index=0,
        agent_ids=tuple(row[0] for row in rows),
        name=f"commonroad/{name}",
        dt=DT,
        history_steps=HISTORY_STEPS,
        kinds=tuple(row[1] for row in rows),
        source=str(path),
        family=name.split("_")[1].split("-")[0] if name.count("_") >= 2 else "",
    )


def _map(scenario: Any, path: Path, resolution: float, margin: float):
    """The drivable map of the lanelets cars drive on (module docstring)."""
    polygons, lanes = [], []
    repairs = RepairBudget()
    for lanelet in scenario.lanelet_network.lanelets:
        if {kind.value for kind in lanelet.lanelet_type} & NOT_FOR_CARS:
            continue
        left, right = np.asarray(lanelet.left_vertices), np.asarray(lanelet.right_vertices)
        what = f"{path}: lanelet {lanelet.lanelet_id} polygon"
        bound = np.concatenate([left, right, np.asarray(lanelet.center_vertices)])
        if not (np.all(np.isfinite(bound)) and np.all(np.abs(bound) <= MAX_MAP_COORDINATE)):
            raise ValueError(
                f"{what} has vertices that are NaN, inf or beyond +-{MAX_MAP_COORDINATE:g} m"
            )
        outline = shapely.Polygon(np.concatenate([left, right[::-1]]))
        polygons.append(repair_polygon(outline, what, repairs))
        centre = np.asarray(lanelet.center_vertices, dtype=np.float64)
        if len(np.unique(centre, axis=0)) < 2:
            continue
        width = float(np.median(np.linalg.norm(left - right, axis=1)))
        successors = tuple(str(s) for s in lanelet.successor)
        lanes.append(Lane(centre, max(width, 0.5), str(lanelet.lanelet_id), successors=successors))
    polygons = [p for p in polygons if not p.is_empty and p.area > 0]
    if not polygons:
        raise ValueError(f"{path}: no lanelet that cars drive on (all {sorted(NOT_FOR_CARS)})")
    known = {lane.lane_id for lane in lanes}
    lanes = [
        Lane(lane.centerline, lane.width, lane.lane_id,
             successors=tuple(s for s in lane.successors if s in known))
        for lane in lanes
    ]  # fmt: skip
    name = f"commonroad/{scenario.scenario_id}"
    try:
        return from_polygons(polygons, resolution=resolution, margin=margin, lanes=lanes, name=name)
    except ValueError as err:  # a raster over the size limits, a lane out of range
        raise ValueError(f"{path}: {err}") from None


def _size(obstacle: Any, path: Path) -> tuple[float, float]:
    """(length, width) [m] of a dynamic obstacle's shape."""
    shape = obstacle.obstacle_shape
    if hasattr(shape, "length") and hasattr(shape, "width"):
        return float(shape.length), float(shape.width)
    if hasattr(shape, "radius"):
        return 2.0 * float(shape.radius), 2.0 * float(shape.radius)
    raise ValueError(
        f"{path}: obstacle {obstacle.obstacle_id} has a {type(shape).__name__} shape; "
        "expected a Rectangle or a Circle"
    )


def _check_tracks(tracks: list[list[Any]], dt: float, path: Path) -> None:
    """ValueError naming ``path`` before any array is built when the time step or the
    tracks exceed what a recorded scene needs (the ScenarioNet reader's limits:
    ``MAX_TRACKS``, ``MAX_STEPS`` and ``MAX_TRACK_STEPS`` at 10 Hz)."""
    if not (np.isfinite(dt) and MIN_DT <= dt <= MAX_DT):
        raise ValueError(f"{path}: the time step dt = {dt:.6g} s, expected {MIN_DT} to {MAX_DT} s")
    if len(tracks) > MAX_TRACKS:
        raise ValueError(f"{path}: {len(tracks)} vehicles, over MAX_TRACKS = {MAX_TRACKS}")
    steps = [int(state.time_step) for track in tracks for state in track]
    span = (max(steps) - min(steps) + 1) * max(1.0, dt / DT)  # steps recorded and at 10 Hz
    if span > MAX_STEPS or span * len(tracks) > MAX_TRACK_STEPS:
        raise ValueError(
            f"{path}: {len(tracks)} vehicles over {span:.0f} steps, over MAX_STEPS = "
            f"{MAX_STEPS} or MAX_TRACK_STEPS = {MAX_TRACK_STEPS}"
        )


def _tracks(
    tracks: list[list[Any]], now: int, dt: float, min_future_steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """(N, T, 4) states and (N, T) valid on the 10 Hz window around time step ``now``."""
    steps = [int(state.time_step) for track in tracks for state in track]
    first, last = min(steps), max(steps)
    count = last - first + 1
    xy = np.zeros((len(tracks), count, 2))
    heading = np.zeros((len(tracks), count))
    speed = np.zeros((len(tracks), count, 1))
    valid = np.zeros((len(tracks), count), dtype=bool)
    for row, track in enumerate(tracks):
        for state in track:
            k = int(state.time_step) - first
            velocity = float(getattr(state, "velocity", 0.0) or 0.0)
            xy[row, k] = np.asarray(state.position, dtype=np.float64)[:2]
            heading[row, k] = float(state.orientation) + (np.pi if velocity < 0 else 0.0)
            speed[row, k, 0] = abs(velocity)
            valid[row, k] = True
    times = (np.arange(count) + first) * dt
    if abs(dt - DT) > 1e-9:  # onto the 10 Hz grid
        grid = np.arange(times[0], times[-1] + 1e-9, DT)
        xy, heading, speed, valid = resample(times, grid, xy, heading, speed, valid)
        times = grid
    current = int(np.argmin(np.abs(times - now * dt)))
    future = max(len(times) - current - 1, int(min_future_steps))
    index = current - (HISTORY_STEPS - 1) + np.arange(HISTORY_STEPS + future)
    inside = (index >= 0) & (index < len(times))
    index = np.clip(index, 0, len(times) - 1)
    states = np.concatenate([xy[:, index], speed[:, index], heading[:, index, None]], axis=-1)
    window_valid = valid[:, index] & inside
    states = hold_nearest_valid(states, window_valid)
    states[..., 3] = np.unwrap(states[..., 3], axis=1)
    return states, window_valid


__all__ = ["EGO_SIZE", "is_commonroad_file", "load_commonroad"]
