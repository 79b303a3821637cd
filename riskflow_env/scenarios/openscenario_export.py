"""Scenarios and rollouts as ASAM OpenSCENARIO 1.3 (``.xosc``, ``[interop]`` extra).

:func:`save_openscenario` writes, with ``scenariogeneration``'s writer, every vehicle of
the scene that is valid at its current step (the ones the env puts on the road):

* an entity per vehicle (``Vehicle`` of category ``car``, or ``truck`` / ``bus`` /
  ``motorbike`` by its kind), its bounding box the vehicle's length and width (height
  :data:`HEIGHT`) centred on the reference point, which is the box centre the scene's
  states give; the ego is the entity ``"Ego"`` (the entity under test, with CARLA
  ScenarioRunner's ``type = ego_vehicle`` property), the others named by their ids;
* ``Init``: each entity teleported to its state at the current step (world position and
  heading) with its speed;
* one act whose maneuver groups make every vehicle, the ego included, follow its track
  from the current step on (the reference future; for a rollout, the executed states) as a
  timed polyline (``FollowTrajectoryAction``, following mode ``position``, absolute time
  from the start), one vertex per valid step;
* the stop trigger at the end of the last track.

Where the map is a highway-env family's, the road network is written beside it as
OpenDRIVE (:mod:`~riskflow_env.scenarios.opendrive_export`) and referenced by the
``RoadNetwork``'s ``LogicFile``; otherwise the ``.xosc`` has world positions only. What is
lost: the history before the current step, vehicles that appear later, the raster map
(tools read roads from the ``.xodr`` instead).
"""

from __future__ import annotations

import datetime
import os
from pathlib import Path

import numpy as np

from riskflow_env.folder_lock import make_output_file
from riskflow_env.scenarios.opendrive_export import is_highway_env_map, save_opendrive
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_export import track_ids

HEIGHT = 1.5  # [m] vehicle height written (the scenes are 2-D)
OPENSCENARIO_MINOR = 3  # OpenSCENARIO 1.3
EGO = "Ego"
CREATED = datetime.datetime(2000, 1, 1)  # a fixed header date: equal scenes, equal files
CATEGORIES = {"truck": "truck", "bus": "bus", "motorcycle": "motorbike"}


def entity_names(scenario: Scenario) -> list[str]:
    """The entity name of every row: ``"Ego"`` for the ego, the agent's id otherwise
    (``"Vehicle_<id>"`` for an id that is ``"Ego"``)."""
    ids = track_ids(scenario)
    return [
        EGO if row == scenario.ego_index else (f"Vehicle_{i}" if i == EGO else i)
        for row, i in enumerate(ids)
    ]


def save_openscenario(scenario: Scenario, path: str | os.PathLike) -> list[Path]:
    """Write ``scenario`` (module docstring) to ``path`` (``.xosc``) and, for a highway-env
    map, ``path`` with suffix ``.xodr``; returns the files written."""
    from scenariogeneration import xosc

    path = make_output_file(path)
    written = []
    road = xosc.RoadNetwork()
    if is_highway_env_map(scenario.map):
        xodr_path = save_opendrive(scenario.map, path.with_suffix(".xodr"))
        road = xosc.RoadNetwork(roadfile=xodr_path.name)
        written.append(xodr_path)
    now = scenario.current_index
    rows = [row for row in range(scenario.num_agents) if scenario.valid[row, now]]
    rows.sort(key=lambda row: row != scenario.ego_index)  # the ego first
    names = entity_names(scenario)
    entities, init = xosc.Entities(), xosc.Init()
    act = xosc.Act("rollout", _time_trigger("start", 0.0, xosc.Rule.greaterThan))
    end = 0.0
    for row in rows:
        name = names[row]
        entities.add_scenario_object(name, _vehicle(scenario, row, name, xosc))
        x, y, speed, heading = (float(v) for v in scenario.states[row, now])
        init.add_init_action(name, xosc.TeleportAction(xosc.WorldPosition(x, y, 0.0, heading)))
        step = xosc.TransitionDynamics(xosc.DynamicsShapes.step, xosc.DynamicsDimension.time, 0.0)
        init.add_init_action(name, xosc.AbsoluteSpeedAction(speed, step))
        steps = np.flatnonzero(scenario.valid[row, now:])
        if len(steps) < 2:
            continue
        times = steps * float(scenario.dt)
        end = max(end, float(times[-1]))
        states = scenario.states[row, now + steps]
        positions = [xosc.WorldPosition(float(s[0]), float(s[1]), 0.0, float(s[3])) for s in states]
        trajectory = xosc.Trajectory(f"{name}_track", False)
        trajectory.add_shape(xosc.Polyline(times.tolist(), positions))
        follow = xosc.FollowTrajectoryAction(
            trajectory, xosc.FollowingMode.position, xosc.ReferenceContext.absolute, 1, 0
        )
        event = xosc.Event(f"{name}_follows", xosc.Priority.override)
        event.add_action(f"{name}_track", follow)
        event.add_trigger(_time_trigger(f"{name}_start", 0.0, xosc.Rule.greaterOrEqual))
        maneuver = xosc.Maneuver(f"{name}_maneuver")
        maneuver.add_event(event)
        group = xosc.ManeuverGroup(f"{name}_group")
        group.add_actor(name)
        group.add_maneuver(maneuver)
        act.add_maneuver_group(group)
    story = xosc.Story("rollout")
    story.add_act(act)
    storyboard = xosc.StoryBoard(init, _time_trigger("stop", end, xosc.Rule.greaterThan, "stop"))
    storyboard.add_story(story)
    document = xosc.Scenario(
        scenario.name or "scenario",
        "riskflow-env",
        xosc.ParameterDeclarations(),
        entities,
        storyboard,
        road,
        xosc.Catalog(),
        osc_minor_version=OPENSCENARIO_MINOR,
        creation_date=CREATED,
    )
    document.write_xml(str(path))
    return [path, *written]


def _vehicle(scenario: Scenario, row: int, name: str, xosc):
    """The ``Vehicle`` entity of ``row``."""
    length, width = float(scenario.length[row]), float(scenario.width[row])
    kind = scenario.kinds[row] if scenario.kinds else ""
    category = getattr(xosc.VehicleCategory, CATEGORIES.get(kind, "car"))
    box = xosc.BoundingBox(width, length, HEIGHT, 0.0, 0.0, HEIGHT / 2)
    wheel = 0.3 * length  # axles at +-0.3 of the length from the box centre
    front = xosc.Axle(0.5, 0.6, 0.9 * width, wheel, 0.3)
    rear = xosc.Axle(0.0, 0.6, 0.9 * width, -wheel, 0.3)
    vehicle = xosc.Vehicle(name, category, box, front, rear, 40.0, 5.0, 8.0)
    if name == EGO:
        vehicle.add_property("type", "ego_vehicle")
    return vehicle


def _time_trigger(name: str, value: float, rule, edge: str = "start"):
    """A trigger when the simulation time passes ``value`` [s]."""
    from scenariogeneration import xosc

    condition = xosc.SimulationTimeCondition(value, rule)
    trigger = xosc.ValueTrigger(name, 0, xosc.ConditionEdge.none, condition, edge)
    return trigger


__all__ = ["EGO", "entity_names", "save_openscenario"]
