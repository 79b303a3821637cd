"""OpenSCENARIO / OpenDRIVE export: ASAM's checkers find no issue in the files of every
shipped family and of a rollout; the roads follow the map's lanes; every vehicle's
trajectory is its track."""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import shapely

from tests.riskflow_env.scenarios.interop import asam_issues, require

require("scenariogeneration", "qc_opendrive", "qc_openscenario")

from policies.harness import ClosedLoop  # noqa: E402
from policies.planners import IDMPlanner  # noqa: E402
from riskflow_env.agents.idm import IDMPolicy  # noqa: E402
from riskflow_env.config import EnvConfig  # noqa: E402
from riskflow_env.maps import from_polygons  # noqa: E402
from riskflow_env.scenarios import shipped_bank  # noqa: E402
from riskflow_env.scenarios.exchange import export_scenario  # noqa: E402
from riskflow_env.scenarios.openscenario_export import entity_names  # noqa: E402


def one_per_family():
    scenes = {}
    for scene in shipped_bank("eval").scenarios:
        scenes.setdefault(scene.family, scene)
    return list(scenes.values())


@pytest.mark.parametrize("scene", one_per_family(), ids=lambda scene: scene.family)
def test_asam_checkers_find_no_issue_and_roads_follow_the_lanes(scene, tmp_path):
    xosc, xodr = export_scenario(scene, tmp_path / scene.family, "openscenario")
    assert (xosc.suffix, xodr.suffix) == (".xosc", ".xodr")
    assert asam_issues(xosc) == [] and asam_issues(xodr) == []
    assert ET.parse(xosc).find("RoadNetwork/LogicFile").get("filepath") == xodr.name
    roads = {road.get("name"): road for road in ET.parse(xodr).getroot().iter("road")}
    assert sorted(roads) == sorted(lane.lane_id for lane in scene.map.lanes)
    for lane in scene.map.lanes:
        centre = road_centreline(roads[lane.lane_id])
        gap = shapely.LineString(lane.centerline).hausdorff_distance(shapely.LineString(centre))
        assert gap < 0.05, lane.lane_id  # [m] (curved lanes are sampled every metre)


def road_centreline(road: ET.Element, step: float = 0.5) -> np.ndarray:
    """(K, 2) [m] centre of the road's one lane: the reference line (line or arc) moved
    left by the lane offset minus half the lane width."""
    (geometry,) = road.find("planView")
    x0, y0, h0, length = (float(geometry.get(k)) for k in ("x", "y", "hdg", "length"))
    arc = geometry.find("arc")
    curvature = 0.0 if arc is None else float(arc.get("curvature"))
    s = np.linspace(0.0, length, max(int(length / step), 1) + 1)
    heading = h0 + curvature * s
    if curvature:
        x = x0 + (np.sin(heading) - np.sin(h0)) / curvature
        y = y0 - (np.cos(heading) - np.cos(h0)) / curvature
    else:
        x, y = x0 + s * np.cos(h0), y0 + s * np.sin(h0)
    offsets = [[float(o.get(k)) for k in "sabcd"] for o in road.iter("laneOffset")]
    starts = np.array([o[0] for o in offsets])
    piece = np.searchsorted(starts, s, side="right") - 1
    ds = s - starts[piece]
    coefficients = np.array([o[1:] for o in offsets])[piece]
    offset = coefficients @ np.array([1, 0, 0, 0]) + ds * coefficients[:, 1]
    offset += ds**2 * coefficients[:, 2] + ds**3 * coefficients[:, 3]
    width = float(road.find("lanes/laneSection/right/lane/width").get("a"))
    lateral = offset - width / 2
    return np.stack([x - lateral * np.sin(heading), y + lateral * np.cos(heading)], axis=1)


def test_every_vehicle_follows_its_rollout_track(tmp_path):
    scene = shipped_bank("eval")[2]
    with ClosedLoop(IDMPlanner(), IDMPolicy(), config=EnvConfig(episode_steps=30)) as loop:
        executed = loop.run(scene, seed=0).to_scenario()
    xosc, xodr = export_scenario(executed, tmp_path / "rollout", "openscenario")
    assert asam_issues(xosc) == [] and asam_issues(xodr) == []
    root = ET.parse(xosc).getroot()
    ego = root.find("Entities/ScenarioObject[@name='Ego']/Vehicle")
    assert ego.find("Properties/Property").get("value") == "ego_vehicle"
    now = executed.current_index
    for row, name in enumerate(entity_names(executed)):
        vehicle = root.find(f"Entities/ScenarioObject[@name='{name}']/Vehicle")
        assert float(vehicle.find("BoundingBox/Dimensions").get("length")) == pytest.approx(
            executed.length[row]
        )
        group = root.find(f".//ManeuverGroup[@name='{name}_group']")
        vertices = group.findall(".//Polyline/Vertex")
        times = np.array([float(v.get("time")) for v in vertices])
        xy = np.array([[float(v.find("Position/WorldPosition").get(k)) for k in "xy"]
                       for v in vertices])  # fmt: skip
        steps = np.flatnonzero(executed.valid[row, now:])
        np.testing.assert_allclose(times, steps * executed.dt)
        np.testing.assert_allclose(xy, executed.states[row, now + steps, :2])


def test_a_map_without_a_road_network_writes_world_positions_only(tmp_path):
    scene = shipped_bank("eval")[0]
    plain = dataclasses.replace(scene, map=from_polygons(shapely.box(-50, -50, 3000, 50)))
    files = export_scenario(plain, tmp_path / "plain", "openscenario")
    assert [path.suffix for path in files] == [".xosc"]
    assert ET.parse(files[0]).find("RoadNetwork/LogicFile") is None
    assert asam_issues(files[0]) == []
