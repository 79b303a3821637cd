"""Scenarios as ScenarioNet / MetaDrive scenario-description pickles.

The description follows MetaDrive 0.4's ``metadrive/scenario/scenario_description.py``
(:data:`DESCRIPTION_VERSION`; the format ScenarioNet's converters write and MetaDrive's
``ScenarioDescription.sanity_check`` accepts, its ``valid_check`` included: every value is
zero at the steps a track is not valid):

* top level: ``id``, ``version``, ``length`` (T), ``tracks``, ``dynamic_map_states`` ({}),
  ``map_features``, ``metadata``;
* ``tracks[id]``: ``type`` ``"VEHICLE"``, ``state`` with ``position`` (T, 3) float32 (z = 0),
  ``heading`` (T,) float32 [rad], ``velocity`` (T, 2) float32 [m/s] (speed along the
  heading), ``valid`` (T,) bool, ``length`` / ``width`` / ``height`` (T, 1) float32 [m];
  ``metadata`` with ``type``, ``object_id``, ``track_length`` and the scene's ``kind``;
* ``metadata``: ``ts`` (T,) [s], ``metadrive_processed`` False, ``coordinate``
  ``"right-handed"``, ``sdc_id`` (the ego), ``sdc_track_index``, ``current_time_index``,
  ``dataset`` ``"riskflow"``, ``scenario_id``, ``source``, ``family``. ``ts`` is float64
  (the description's example shows float32, whose rounding of 0.1 s steps over a long
  scene would make a reader resample them);
* ``map_features``: every lane as ``LANE_SURFACE_STREET`` (centreline ``polyline``,
  full ``width`` per point, ``exit_lanes`` / ``entry_lanes``, ``speed_limit_kmh``), and
  the drivable raster's outline (:mod:`~riskflow_env.scenarios.map_outline`) as
  closed ``ROAD_LINE_SOLID_SINGLE_WHITE`` rings named ``boundary_<k>``, the nuScenes and
  nuPlan converters' convention for the drivable-area layer.

Read back with :func:`~riskflow_env.scenarios.scenarionet.load_scenarionet`
(``current_index=scenario.current_index``, ``min_future_steps=0``, ``crop=False``, the
map's ``resolution``), the tracks come back to float32 precision and the raster pixel for
pixel on the map's grid (the lanes' own surfaces add what lies outside it: nothing for
maps built from those lanes). What is lost: the reader keeps one vehicle size per track
and drops the kinds; steps beyond the map features' extent (a vehicle far off the road)
read back as not valid.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.atomic_files import atomic_file
from riskflow_env.folder_lock import make_output_file
from riskflow_env.scenarios.map_outline import outline_rings
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_limits import MAX_FEATURE_POINTS

DESCRIPTION_VERSION = "MetaDrive v0.4.2.1"
LANE_TYPE = "LANE_SURFACE_STREET"
BOUNDARY_TYPE = "ROAD_LINE_SOLID_SINGLE_WHITE"
VEHICLE = "VEHICLE"
HEIGHT = 1.5  # [m] vehicle height written (the scenes are 2-D)
KMH = 3.6  # [km/h] per m/s


def track_ids(scenario: Scenario) -> list[str]:
    """The agents' ids in the file: ``scenario.agent_ids`` when they name every agent once,
    else the rows' numbers."""
    ids = list(scenario.agent_ids)
    if len(ids) != scenario.num_agents or len(set(ids)) != len(ids) or not all(ids):
        ids = [str(row) for row in range(scenario.num_agents)]
    return ids


def to_description(scenario: Scenario) -> dict[str, Any]:
    """The scenario-description dict of ``scenario`` (module docstring)."""
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    steps = scenario.states.shape[1]
    ids = track_ids(scenario)
    tracks = {}
    for row, track_id in enumerate(ids):
        valid = scenario.valid[row]
        state = np.where(valid[:, None], scenario.states[row], 0.0)
        x, y, speed, heading = state.T
        position = np.stack([x, y, np.zeros(steps)], axis=1)
        velocity = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
        column = valid[:, None].astype(np.float64)

        def size(value: float, column: np.ndarray = column) -> np.ndarray:
            return (column * value).astype(np.float32)

        tracks[track_id] = {
            "type": VEHICLE,
            "state": {
                "position": position.astype(np.float32),
                "heading": heading.astype(np.float32),
                "velocity": velocity.astype(np.float32),
                "valid": valid.astype(bool),
                "length": size(float(scenario.length[row])),
                "width": size(float(scenario.width[row])),
                "height": size(HEIGHT),
            },
            "metadata": {
                "type": VEHICLE,
                "object_id": track_id,
                "track_length": steps,
                "kind": scenario.kinds[row] if scenario.kinds else "",
            },
        }
    name = scenario.name or "scenario"
    metadata = {
        "ts": np.arange(steps, dtype=np.float64) * float(scenario.dt),
        "metadrive_processed": False,
        "coordinate": "right-handed",
        "sdc_id": ids[scenario.ego_index],
        "sdc_track_index": int(scenario.ego_index),
        "current_time_index": int(scenario.current_index),
        "dataset": "riskflow",
        "scenario_id": name,
        "source": scenario.source,
        "family": scenario.family,
    }
    return {
        "id": name,
        "version": DESCRIPTION_VERSION,
        "length": steps,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": map_features(scenario),
        "metadata": metadata,
    }


def map_features(scenario: Scenario) -> dict[str, dict[str, Any]]:
    """Lanes and the drivable outline's rings of ``scenario.map`` (module docstring)."""
    drivable_map = scenario.map
    features: dict[str, dict[str, Any]] = {}
    entries: dict[str, list[str]] = {lane.lane_id: [] for lane in drivable_map.lanes}
    for lane in drivable_map.lanes:
        for successor in lane.successors:
            if successor in entries:
                entries[successor].append(lane.lane_id)
    for lane in drivable_map.lanes:
        if lane.lane_id.startswith("boundary_"):
            raise ValueError(
                f"scenario.map: lane id {lane.lane_id!r} starts with 'boundary_', the prefix "
                "ScenarioNet readers keep for drivable-area rings"
            )
        feature = {
            "type": LANE_TYPE,
            "polyline": np.asarray(lane.centerline, dtype=np.float64),
            "width": np.full(len(lane.centerline), lane.width, dtype=np.float64),
            "exit_lanes": [s for s in lane.successors if s in entries],
            "entry_lanes": entries[lane.lane_id],
        }
        if lane.speed_limit is not None:
            feature["speed_limit_kmh"] = float(lane.speed_limit) * KMH
        features[lane.lane_id] = feature
    for k, ring in enumerate(outline_rings(drivable_map)):
        if len(ring) > MAX_FEATURE_POINTS:
            raise ValueError(
                f"scenario.map: the drivable outline's ring {k} has {len(ring)} points, over "
                f"the ScenarioNet reader's MAX_FEATURE_POINTS = {MAX_FEATURE_POINTS}"
            )
        features[f"boundary_{k}"] = {"type": BOUNDARY_TYPE, "polyline": ring}
    return features


def save_scenarionet(scenario: Scenario, path: str | os.PathLike) -> Path:
    """Write ``scenario`` as a ScenarioNet pickle (module docstring); returns the path."""
    path = Path(path)
    description = to_description(scenario)
    path = make_output_file(path)
    with atomic_file(path) as handle:
        pickle.dump(description, handle, protocol=4)
    return path


__all__ = ["DESCRIPTION_VERSION", "map_features", "save_scenarionet", "to_description"]
