"""Every ScenarioNet source loads: Waymo, nuScenes, nuPlan and Argoverse 2 descriptions in
their converters' exact form (tests/riskflow_env/scenarios/scenarionet_sources.py)."""

from __future__ import annotations

import collections
import pickle

import numpy as np
import pytest

from riskflow_env.scenarios.safe_pickle import load_data_pickle
from riskflow_env.scenarios.scenarionet import load_scenarionet, scenario_from_description
from riskflow_env.scenarios.scenarionet_features import lane_width
from tests.riskflow_env.scenarios.scenarionet_sources import (
    IN_LOT,
    OFF_ROAD_ON_CROSSWALK,
    SOURCES,
    description,
)


def _write(tmp_path, source: str, data: dict | None = None):
    path = tmp_path / f"sd_{source}_toy.pkl"
    path.write_bytes(pickle.dumps(description(source) if data is None else data))
    return path


@pytest.fixture(scope="module")
def scenarios(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sources")
    return {source: load_scenarionet(_write(folder, source)) for source in SOURCES}


@pytest.mark.parametrize("source", SOURCES)
def test_each_source_loads_with_vehicles_on_the_road(scenarios, source):
    scenario = scenarios[source]
    assert scenario.agent_ids[0] == description(source)["metadata"]["sdc_id"]
    assert "walker" not in scenario.agent_ids  # pedestrians dropped
    moving = scenario.valid & (scenario.states[..., 2] > 0.5)
    on_road = scenario.map.is_drivable(scenario.states[..., :2][moving])
    assert on_road.all(), f"{source}: {on_road.mean():.3f} of moving vehicle steps on the road"
    lanes = {lane.lane_id: lane for lane in scenario.map.lanes}
    assert len(lanes) == 4  # the car lanes only: no bike lane, no surface in the lane graph
    assert sum(bool(lane.successors) for lane in lanes.values()) == 2
    for lane in lanes.values():
        assert lane.width == pytest.approx(3.5, abs=0.05)
    assert not scenario.map.is_drivable(np.array(OFF_ROAD_ON_CROSSWALK))  # crosswalk: no surface


@pytest.mark.parametrize("source", ["waymo", "nuscenes"])
def test_driveways_and_carparks_are_drivable_surface(scenarios, source):
    scenario = scenarios[source]
    assert scenario.map.is_drivable(np.array(IN_LOT))
    parker = scenario.agent_ids.index("parker")
    recorded = description(source)["length"]  # then padded with invalid steps
    assert scenario.valid[parker, :recorded].all()
    assert scenario.map.is_drivable(scenario.states[parker, :recorded, :2]).all()


def test_argoverse2_bike_lane_is_not_drivable(scenarios):
    assert not scenarios["argoverse2"].map.is_drivable(np.array([0.0, -5.5]))


def test_nuscenes_sidewalk_is_not_drivable(scenarios):
    assert not scenarios["nuscenes"].map.is_drivable(np.array([0.0, -5.0]))


def test_waymo_steps_beyond_the_map_data_are_invalid(scenarios):
    scenario = scenarios["waymo"]
    runaway = scenario.agent_ids.index("runaway")
    x = description("waymo")["tracks"]["runaway"]["state"]["position"][:, 0]
    inside = x <= 150.0  # the map features end at x = 150 m
    np.testing.assert_array_equal(scenario.valid[runaway, : len(x)], inside)
    moving = scenario.valid & (scenario.states[..., 2] > 0.5)
    assert scenario.map.is_drivable(scenario.states[..., :2][moving]).all()


def test_metadata_keeps_the_defaultdict(tmp_path):
    loaded = load_data_pickle(_write(tmp_path, "waymo"))
    counts = loaded["metadata"]["number_summary"]["num_moving_objects_each_type"]
    assert isinstance(counts, collections.defaultdict) and counts.default_factory is int
    assert counts["VEHICLE"] == 4 and counts["CYCLIST"] == 0


@pytest.mark.parametrize(
    ("width", "expected"),
    [
        (np.full((6, 2), 1.75, np.float32), 3.5),  # Waymo: left + right
        (np.array([[1.75, 0.0], [0.0, 1.75], [1.75, 1.75]], np.float32), 3.5),  # one side: mirror
        (np.zeros((6, 2), np.float32), None),  # Argoverse 2 / no boundary: unknown
        (np.array([[0.0, 0.0], [1.5, 1.5], [1.5, 1.5]]), 3.0),  # both missing: ignored points
        (3.2, 3.2),  # a full width
        (np.array([3.0, 3.0, 4.0]), 3.0),
        (None, None),
    ],
)
def test_lane_width_forms(width, expected):
    got = lane_width({"width": width}, "lane 7")
    assert got == (None if expected is None else pytest.approx(expected))


def test_lane_without_width_gets_the_maps_median(scenarios):
    lanes = {lane.lane_id: lane for lane in scenarios["waymo"].map.lanes}
    assert lanes["104"].width == pytest.approx(3.5)  # all-zero width: the median of the others


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda f: f["101"].update(width=np.ones((3, 3))), r"map feature 101 .*width must be"),
        (lambda f: f["101"].update(width=np.full((3, 2), np.nan)), r"map feature 101 .*finite"),
        (lambda f: f["101"].update(width=-np.ones((3, 2))), r"map feature 101 .*>= 0"),
        (lambda f: f["102"].update(polyline=np.zeros((4, 1))), r"map feature 102 .*polyline"),
        (lambda f: f["501"].update(polygon=np.zeros(5)), r"map feature 501 \(DRIVEWAY\) polygon"),
        (
            lambda f: f["101"].update(speed_limit_kmh=None, polygon="x"),
            r"map feature 101 .*polygon",
        ),
    ],
)
def test_bad_map_features_name_the_file_and_the_feature(tmp_path, change, message):
    data = description("waymo")
    change(data["map_features"])
    path = _write(tmp_path, "waymo", data)
    with pytest.raises(ValueError, match=message) as error:
        load_scenarionet(path)
    assert str(path) in str(error.value)


def test_map_is_cropped_to_the_vehicles_region():
    data = description("nuscenes")
    full = scenario_from_description(data, crop=False).map
    cropped = scenario_from_description(data, crop_margin=10.0).map
    xy = np.concatenate([t["state"]["position"][:, :2] for t in data["tracks"].values()])
    xmin, ymin, xmax, ymax = cropped.bounds
    assert full.bounds[0] < -145 and full.bounds[2] > 145  # the whole road
    assert xmin >= -100 - 10 - 5 - 0.5 and xmax <= 100 + 10 + 5 + 0.5  # vehicles: |x| <= 100
    assert cropped.drivable.size < full.drivable.size
    assert len(cropped.lanes) == len(full.lanes)  # every lane reaches into the region
    points = np.array([[-50.0, -1.75], [IN_LOT[0], IN_LOT[1]], [95.0, 1.75], [95.0, 5.0]])
    np.testing.assert_array_equal(cropped.is_drivable(points), [True, True, True, False])
    np.testing.assert_array_equal(full.is_drivable(points), [True, True, True, False])
    # the road crosses the region's edge: it runs on through the margin and beyond
    # the raster, so traffic can drive out of the map; the ground beside it stays off-road
    assert cropped.is_drivable(np.array([[xmax - 1.0, -1.75], [130.0, -1.75]])).all()
    assert not cropped.is_drivable(np.array([130.0, 5.0]))
    assert xy[:, 1].max() <= ymax


def test_crop_drops_far_lanes_and_checks_the_margin():
    data = description("nuplan")
    lane = data["map_features"]["1000"]
    data["map_features"]["far"] = {
        "type": "LANE_SURFACE_STREET",
        "polyline": lane["polyline"] + [0.0, 2000.0],
        "polygon": lane["polygon"] + [0.0, 2000.0],
    }
    scenario = scenario_from_description(data)
    assert "far" not in {lane.lane_id for lane in scenario.map.lanes}
    assert scenario.map.bounds[3] < 200.0
    for bad in (-1.0, 0.0, float("nan")):
        with pytest.raises(ValueError, match="crop_margin"):
            scenario_from_description(data, crop_margin=bad)
    for changes, message in (  # the loader's own arguments, named before the file is read
        ({"min_future_steps": -3}, "min_future_steps must be an int in [0, "),
        ({"resolution": float("nan")}, "resolution must be a finite number"),
        ({"resolution": 0.0}, "resolution must be > 0 [m/px], got 0.0"),
        ({"current_index": 1.5}, "current_index must be an int in [0, "),
        ({"margin": -1.0}, "margin must be >= 0 [m], got -1.0"),
    ):
        with pytest.raises(ValueError) as error:
            scenario_from_description(data, **changes)
        assert str(error.value).startswith(message)
