"""Synthetic ScenarioNet descriptions in the exact form of each converter (no data files).

One small world, written four times the way ScenarioNet's converters write it
(github.com/metadriverse/scenarionet, ``scenarionet/converter/<source>/utils.py``, and
metadrive's ``ScenarioDescription`` for ``metadata["object_summary"/"number_summary"]``):

* a two-way road along x in [-150, 150] m (lanes at y = -1.75 eastbound and +1.75
  westbound, 3.5 m wide, each split at x = 0), road edges at y = +-3.5 m;
* a parking lot / driveway x in [0, 40], y in [3.5, 30] on the north side;
* a crosswalk x in [48, 52], y in [-8, 8] (reaching 4.5 m past both road edges);
* vehicles: the ego eastbound at 10 m/s, a westbound car whose log ends at 6 s, a car
  that turns off the road into the lot and parks there (``waymo``: a driveway,
  ``nuscenes``: a carpark area; the other two have no parking: it stays on its lane);
  a pedestrian on the crosswalk.
  ``waymo`` adds a car driving past the end of the map data (x > 150 m).
"""

from __future__ import annotations

import collections

import numpy as np

ROAD_X = (-150.0, 150.0)  # [m]
LANE_WIDTH = 3.5  # [m]
LOT = np.array([[0.0, 3.5], [40.0, 3.5], [40.0, 30.0], [0.0, 30.0]])  # [m]
CROSSWALK = np.array([[48.0, -8.0], [52.0, -8.0], [52.0, 8.0], [48.0, 8.0]])  # [m]
OFF_ROAD_ON_CROSSWALK = (50.0, 6.0)  # [m] on the crosswalk, past the road edge
IN_LOT = (25.0, 20.0)  # [m]
SOURCES = ("waymo", "nuscenes", "nuplan", "argoverse2")


def _centrelines(step: float = 5.0) -> dict[str, np.ndarray]:
    """Four lane centrelines (K, 2) [m]: east_a, east_b, west_a, west_b."""
    east_a = np.arange(ROAD_X[0], 0.0 + 1e-9, step)
    east_b = np.arange(0.0, ROAD_X[1] + 1e-9, step)
    lines = {
        "east_a": np.stack([east_a, np.full_like(east_a, -1.75)], 1),
        "east_b": np.stack([east_b, np.full_like(east_b, -1.75)], 1),
        "west_a": np.stack([east_b[::-1], np.full_like(east_b, 1.75)], 1),
        "west_b": np.stack([east_a[::-1], np.full_like(east_a, 1.75)], 1),
    }
    return lines


SUCCESSOR = {"east_a": "east_b", "west_a": "west_b"}


def _rect(line: np.ndarray, width: float = LANE_WIDTH) -> np.ndarray:
    """Closed outline (5, 2) [m] of a straight lane along x."""
    (x0, y), (x1, _) = line[0], line[-1]
    xa, xb = min(x0, x1), max(x0, x1)
    h = width / 2
    return np.array([[xa, y - h], [xb, y - h], [xb, y + h], [xa, y + h], [xa, y - h]])


def _xyz(points: np.ndarray, dtype=np.float32) -> np.ndarray:
    return np.concatenate([points, np.zeros((len(points), 1))], 1).astype(dtype)


def _motion(steps: int, parking: bool, dt: float = 0.1) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """id -> (xy (T, 2) [m], valid (T,) bool) of every road user; the parker stays on
    its lane when the map has no parking (``parking`` False)."""
    t = np.arange(steps) * dt
    ego = np.stack([-100.0 + 10.0 * t, np.full(steps, -1.75)], 1)
    car = np.stack([100.0 - 8.0 * t, np.full(steps, 1.75)], 1)
    car_valid = t <= 6.0 + 1e-9
    # parker: east along the lane to x = 0 at 4 s, then to the lot's centre by 8 s, parked
    along = np.stack([-20.0 + 5.0 * t, np.full(steps, -1.75)], 1)
    frac = np.clip((t - 4.0) / 4.0, 0.0, 1.0)[:, None]
    turn = (1 - frac) * np.array([0.0, -1.75]) + frac * np.array(IN_LOT)
    parker = np.where((t < 4.0)[:, None] | (not parking), along, turn)
    walker = np.stack([np.full(steps, 50.0), -6.0 + 0.5 * t], 1)
    return {
        "ego": (ego, np.ones(steps, bool)),
        "car": (car, car_valid),
        "parker": (parker, np.ones(steps, bool)),
        "walker": (walker, np.ones(steps, bool)),
    }


def _heading(xy: np.ndarray, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Heading along the motion (held when stopped) and velocity (T, 2) [m/s]."""
    velocity = np.gradient(xy, dt, axis=0)
    moving = np.linalg.norm(velocity, axis=1) > 1e-6
    heading = np.arctan2(velocity[:, 1], velocity[:, 0])
    index = np.maximum.accumulate(np.where(moving, np.arange(len(xy)), 0))
    return heading[index], velocity


def _summaries(tracks: dict, map_features: dict, dynamic: dict) -> dict:
    """metadata["object_summary"], ["number_summary"] as metadrive's ScenarioDescription
    writes them (``num_moving_objects_each_type`` is a ``collections.defaultdict(int)``)."""
    objects, moving = {}, collections.defaultdict(int)
    for key, track in tracks.items():
        valid = np.asarray(track["state"]["valid"]).astype(bool)
        xy = np.asarray(track["state"]["position"])[valid, :2]
        distance = float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))
        objects[key] = {
            "type": track["type"],
            "object_id": key,
            "track_length": len(valid),
            "moving_distance": distance,
            "valid_length": int(valid.sum()),
            "continuous_valid_length": int(valid.sum()),
        }
        if distance > 1:
            moving[track["type"]] += 1
    counts = collections.Counter(track["type"] for track in tracks.values())
    number = {
        "num_objects": len(tracks),
        "object_types": set(counts),
        "num_objects_each_type": dict(counts),
        "num_moving_objects": int(sum(moving.values())),
        "num_moving_objects_each_type": moving,
        "num_traffic_lights": len(dynamic),
        "num_traffic_light_types": {"LANE_STATE_GO"} if dynamic else set(),
        "num_traffic_light_each_step": {"LANE_STATE_GO": 5} if dynamic else {},
        "num_map_features": len(map_features),
        "map_height_diff": 0.0,
    }
    return {"object_summary": objects, "number_summary": number}


def _tracks(source: str, steps: int, sdc: str) -> dict:
    motion = _motion(steps, parking=source in ("waymo", "nuscenes"))
    if source == "waymo":
        t = np.arange(steps) * 0.1
        motion["runaway"] = (np.stack([120.0 + 12.0 * t, np.full(steps, -1.75)], 1), t >= 0)
    names = {"ego": sdc}
    tracks = {}
    for key, (xy, valid) in motion.items():
        heading, velocity = _heading(xy)
        kind = "PEDESTRIAN" if key == "walker" else "VEHICLE"
        length, width = (0.6, 0.6) if kind == "PEDESTRIAN" else (4.6, 1.9)
        if source == "argoverse2":  # the AV2 converter writes fixed sizes per type
            length, width = (0.5, 0.5) if kind == "PEDESTRIAN" else (4.0, 2.0)
        xy = np.where(valid[:, None], xy, 0.0)  # converters leave zeros at invalid steps
        heading, velocity = np.where(valid, heading, 0.0), np.where(valid[:, None], velocity, 0.0)
        state = {"position": _xyz(xy, np.float64), "heading": heading, "velocity": velocity}
        if source in ("waymo", "argoverse2"):  # float32 arrays, sizes (T,), valid bool
            state = {k: v.astype(np.float32) for k, v in state.items()}
            for name, value in (("length", length), ("width", width), ("height", 1.5)):
                state[name] = np.where(valid, value, 0.0).astype(np.float32)
            state["valid"] = valid.copy()
        else:  # nuScenes / nuPlan: float64, sizes (T, 1), valid as 0/1 floats
            for name, value in (("length", length), ("width", width), ("height", 1.5)):
                state[name] = np.where(valid, value, 0.0)[:, None]
            state["valid"] = valid.astype(np.float64)
        object_id = names.get(key, key)
        if source == "nuscenes" and key == "ego":  # the nuScenes SDC's sizes come swapped
            state["length"], state["width"] = state["width"].copy(), state["length"].copy()
        tracks[object_id] = {
            "type": kind,
            "state": state,
            "metadata": {"track_length": steps, "type": kind, "object_id": object_id},
        }
    return tracks


def _waymo_map() -> dict:
    lines = _centrelines()
    ids = {"east_a": "101", "east_b": "102", "west_a": "103", "west_b": "104"}
    features = {}
    for name, line in lines.items():
        width = np.full((len(line), 2), LANE_WIDTH / 2, dtype=np.float32)
        if name == "east_a":
            width[:3] = 0.0  # no boundary at all: both sides 0
            width[3:6, 1] = 0.0  # a side without boundary (the converter fills it from the other)
        if name == "west_b":
            width[:] = 0.0  # a lane with no boundary anywhere
        boundary = {
            "lane_start_index": "0",
            "lane_end_index": str(len(line) - 1),
            "boundary_type": "ROAD_LINE_SOLID_SINGLE_WHITE",
            "boundary_feature_id": "301",
        }
        features[ids[name]] = {
            "speed_limit_mph": 25.0,
            "speed_limit_kmh": 25.0 * 1.609344,
            "type": "LANE_SURFACE_STREET",
            "polyline": _xyz(line),
            "interpolating": False,
            "entry_lanes": [int(ids[k]) for k, v in SUCCESSOR.items() if v == name],
            "exit_lanes": [int(ids[SUCCESSOR[name]])] if name in SUCCESSOR else [],
            "left_boundaries": [boundary],
            "right_boundaries": [],
            "left_neighbor": [],
            "right_neighbor": [],
            "width": width,
        }
    x = np.linspace(*ROAD_X, 61)
    features["201"] = {
        "type": "ROAD_LINE_SOLID_DOUBLE_YELLOW",
        "polyline": _xyz(np.stack([x, 0 * x], 1)),
    }
    for key, y in (("301", -3.5), ("302", 3.5)):
        edge = np.stack([x, np.full_like(x, y)], 1)
        features[key] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": _xyz(edge)}
    features["401"] = {"type": "CROSSWALK", "polygon": _xyz(CROSSWALK)}
    bump = np.array([[60.0, -3.5], [61.0, -3.5], [61.0, 3.5], [60.0, 3.5]])
    features["402"] = {"type": "SPEED_BUMP", "polygon": _xyz(bump)}
    stop = np.array([45.0, -1.75, 0.0], dtype=np.float32)
    features["403"] = {"type": "STOP_SIGN", "lane": [102], "position": stop}
    features["501"] = {"type": "DRIVEWAY", "polygon": _xyz(LOT)}
    return features


def _polygon_lanes(lane_type: str, ids: dict, connector: str | None, exits: bool) -> dict:
    """nuScenes / nuPlan lanes: polyline, polygon outline; ``connector`` without polygon."""
    features = {}
    for name, line in _centrelines(1.0).items():
        key = ids[name]
        feature = {"type": lane_type}
        if exits:  # nuScenes: discretize_lane gives (x, y, yaw); token lists
            yaw = np.where(name.startswith("east"), 0.0, np.pi)
            feature["polyline"] = np.concatenate([line, np.full((len(line), 1), yaw)], 1)
            feature["entry_lanes"] = [ids[k] for k, v in SUCCESSOR.items() if v == name]
            feature["exit_lanes"] = [ids[SUCCESSOR[name]]] if name in SUCCESSOR else []
            feature["left_neighbor"], feature["right_neighbor"] = [], []
        else:  # nuPlan: (K, 2) baseline path, no lane graph
            feature["polyline"] = line.copy()
        if name == connector:
            feature["type"] = "LANE_SURFACE_UNSTRUCTURE"
            feature["speed_limit_kmh"] = 100
        else:
            feature["polygon"] = _rect(line)[:-1]
        features[key] = feature
    return features


def _road_ring() -> np.ndarray:
    """Closed outline of the road's drivable area, as ``boundary_<k>`` lines hold it."""
    (x0, x1), h = ROAD_X, 3.5
    return np.array([[x0, -h], [x1, -h], [x1, h], [x0, h], [x0, -h]])


def _nuscenes_map() -> dict:
    ids = {k: f"{i:08x}-5b2c-4a2e-9c7a-nuscenes" for i, k in enumerate(_centrelines())}
    features = _polygon_lanes("LANE_SURFACE_STREET", ids, connector="east_b", exits=True)
    features["boundary_0"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": _road_ring()}
    x = np.linspace(*ROAD_X, 31)
    features["divider-0"] = {
        "type": "ROAD_LINE_SOLID_SINGLE_YELLOW",
        "polyline": np.stack([x, 0 * x], 1),
    }
    features["ped-0"] = {"type": "CROSSWALK", "polygon": CROSSWALK.copy()}
    walk = np.array([[-150.0, -6.0], [150.0, -6.0], [150.0, -3.5], [-150.0, -3.5]])
    features["walk-0"] = {"type": "BOUNDARY_SIDEWALK", "polygon": walk}
    # nuScenes' carpark_area layer, as a converter that exports it writes a polygon
    features["carpark-0"] = {"type": "CARPARK_AREA", "polygon": LOT.copy()}
    return features


def _nuplan_map() -> dict:
    ids = {k: str(1000 + i) for i, k in enumerate(_centrelines())}
    features = _polygon_lanes("LANE_SURFACE_STREET", ids, connector=None, exits=False)
    x = np.linspace(*ROAD_X, 31)
    features["2000"] = {
        "type": "ROAD_LINE_BROKEN_SINGLE_WHITE",
        "polyline": np.stack([x, 0 * x], 1),
    }
    features["boundary_0"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": _road_ring()}
    return features


def _argoverse2_map() -> dict:
    lines = _centrelines()
    ids = {"east_a": "30", "east_b": "31", "west_a": "32", "west_b": "33"}
    max_id = 34
    features = {}
    bike = np.stack([np.linspace(-150, 150, 31), np.full(31, -5.5)], 1)
    for name, line in [*lines.items(), ("bike", bike)]:
        seg = int(ids.get(name, max_id))
        features[str(seg + max_id + 1)] = {
            "type": "ROAD_LINE_BROKEN_SINGLE_WHITE",
            "polyline": _xyz(line + [0.0, LANE_WIDTH / 2]),
        }
        features[str(seg + max_id + 2)] = {
            "type": "UNKNOWN_LINE",
            "polyline": _xyz(line - [0, 1.75]),
        }
        features[str(seg)] = {
            "speed_limit_mph": 85.0,
            "speed_limit_kmh": 85.0 * 1.609344,
            "type": "LANE_BIKE_LANE" if name == "bike" else "LANE_SURFACE_STREET",
            "polyline": _xyz(line),
            "interpolating": True,
            "entry_lanes": [ids[k] for k, v in SUCCESSOR.items() if v == name],
            "exit_lanes": [ids[SUCCESSOR[name]]] if name in SUCCESSOR else [],
            "left_boundaries": [],
            "right_boundaries": [],
            "left_neighbor": [],
            "right_neighbor": [],
            "width": np.zeros((len(line), 2), dtype=np.float32),
        }
    features["9001"] = {"type": "CROSSWALK", "polygon": _xyz(CROSSWALK)}
    return features


def description(source: str) -> dict:
    """A scenario description as ScenarioNet's ``source`` converter writes it."""
    steps = {"waymo": 91, "nuscenes": 201, "nuplan": 150, "argoverse2": 110}[source]
    sdc = {"waymo": "1001", "nuscenes": "ego", "nuplan": "ego", "argoverse2": "AV"}[source]
    tracks = _tracks(source, steps, sdc)
    map_features = {
        "waymo": _waymo_map,
        "nuscenes": _nuscenes_map,
        "nuplan": _nuplan_map,
        "argoverse2": _argoverse2_map,
    }[source]()
    dynamic = {}
    ts = np.arange(steps) * 0.1
    metadata = {
        "id": f"{source}-toy",
        "scenario_id": f"{source}-toy",
        "dataset": source if source != "argoverse2" else "av2",
        "metadrive_processed": False,
        "sdc_id": sdc,
        "ts": ts,
    }
    if source == "waymo":
        dynamic["102"] = {
            "type": "TRAFFIC_LIGHT",
            "state": {"object_state": ["LANE_STATE_GO"] * 5 + [None] * (steps - 5)},
            "lane": 102,
            "stop_point": np.array([45.0, -1.75, 0.0], dtype=np.float32),
            "metadata": {"track_length": steps, "type": "TRAFFIC_LIGHT", "object_id": "102"},
        }
        metadata.update(
            coordinate="waymo",
            ts=ts.astype(np.float32),
            source_file="training_20s.tfrecord-00000-of-01000",
            track_length=steps,
            current_time_index=10,
            sdc_track_index=0,
            objects_of_interest=[],
            tracks_to_predict={
                "car": {
                    "track_index": 1,
                    "track_id": "car",
                    "difficulty": 1,
                    "object_type": "VEHICLE",
                }
            },
        )
    elif source == "nuscenes":
        metadata.update(
            map="boston-seaport",
            date="2018-07-24",
            coordinate="right-handed",
            sample_rate=0.1,
            scenario_token="scene-toy",
        )
    elif source == "nuplan":
        dynamic["1001"] = {
            "type": "TRAFFIC_LIGHT",
            "state": {"object_state": ["TRAFFIC_LIGHT_GREEN"] * steps},
            "stop_point": [45.0, -1.75],
            "lane": "1001",
            "metadata": {"track_length": steps, "type": "TRAFFIC_LIGHT", "object_id": "1001"},
        }
        metadata.update(
            map="us-nv-las-vegas-strip",
            map_version="nuplan-maps-v1.0",
            log_name="2021.toy",
            scenario_extraction_info={"scenario_name": "toy", "scenario_duration": 15.0},
            ego_vehicle_parameters={"width": 2.297, "length": 5.176, "height": 1.777},
            coordinate="right-handed",
            scenario_token="toy",
            scenario_type="unknown",
            sample_rate=0.1,
        )
    else:
        metadata.update(
            coordinate="waymo",
            source_file=f"{source}-toy",
            track_length=steps,
            current_time_index=49,
            sdc_track_index="AV",
            objects_of_interest=[],
            tracks_to_predict={},
        )
    metadata.update(_summaries(tracks, map_features, dynamic))
    return {
        "id": f"{source}-toy",
        "version": f"{source}-toy-v0",
        "length": steps,
        "tracks": tracks,
        "dynamic_map_states": dynamic,
        "map_features": map_features,
        "metadata": metadata,
    }
