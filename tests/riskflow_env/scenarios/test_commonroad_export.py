"""CommonRoad export: commonroad-io reads the files back (lanelets, obstacles, the ego's
planning problem) and its collision checker finds the ego's collision at the step the
event log gives."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import shapely

from tests.riskflow_env.scenarios.interop import require

require("commonroad.common.file_reader")

from commonroad.common.file_reader import CommonRoadFileReader  # noqa: E402

from policies.harness import ClosedLoop  # noqa: E402
from policies.planners import ConstantVelocityPlanner  # noqa: E402
from riskflow_env.agents.replay import ReplayPolicy  # noqa: E402
from riskflow_env.config import EnvConfig  # noqa: E402
from riskflow_env.maps import from_polygons  # noqa: E402
from riskflow_env.scenarios import shipped_bank  # noqa: E402
from riskflow_env.scenarios.commonroad_export import commonroad_ids  # noqa: E402
from riskflow_env.scenarios.exchange import export_scenario  # noqa: E402
from tests.riskflow_env.hand_made_scenes import make_scenario  # noqa: E402

PRECISION = 1e-4  # [m, rad, m/s] the writer's 4 decimals


def read(path):
    scenario, problems = CommonRoadFileReader(str(path)).open()
    return scenario, next(iter(problems.planning_problem_dict.values()))


@pytest.mark.parametrize("index", [0, 2, 3])  # highway, roundabout, intersection
def test_commonroad_io_reads_back_lanelets_obstacles_and_the_ego(index, tmp_path):
    scene = shipped_bank("eval")[index]
    (path,) = export_scenario(scene, tmp_path / "scene", "commonroad")
    assert path.suffix == ".xml"
    document, problem = read(path)
    now, ids = scene.current_index, commonroad_ids(scene)
    lanelets = document.lanelet_network.lanelets
    assert len(lanelets) == len(scene.map.lanes)
    for number, lane in enumerate(scene.map.lanes, start=1):
        lanelet = document.lanelet_network.find_lanelet_by_id(number)
        np.testing.assert_allclose(lanelet.center_vertices, lane.centerline, atol=PRECISION)
        width = np.linalg.norm(lanelet.left_vertices - lanelet.right_vertices, axis=1)
        assert width.min() >= lane.width - PRECISION  # miter joins widen corners only
    ego = scene.states[scene.ego_index, now]
    assert problem.planning_problem_id == ids[scene.ego_index]
    np.testing.assert_allclose(problem.initial_state.position, ego[:2], atol=PRECISION)
    assert problem.initial_state.velocity == pytest.approx(ego[2], abs=PRECISION)
    obstacles = {obstacle.obstacle_id: obstacle for obstacle in document.dynamic_obstacles}
    others = [row for row in range(scene.num_agents) if row != scene.ego_index]
    assert sorted(obstacles) == sorted(ids[row] for row in others)
    for row in others:
        obstacle = obstacles[ids[row]]
        assert obstacle.obstacle_shape.length == pytest.approx(scene.length[row], abs=PRECISION)
        states = [obstacle.initial_state, *obstacle.prediction.trajectory.state_list]
        for state in states:
            expected = scene.states[row, now + state.time_step]
            np.testing.assert_allclose(state.position, expected[:2], atol=PRECISION)


def test_a_map_without_lanes_is_written_as_a_road_boundary(tmp_path):
    scene = shipped_bank("eval")[0]
    road = shapely.box(-50, -20, 3000, 20)
    plain = dataclasses.replace(scene, map=from_polygons(road, margin=5.0))
    (path,) = export_scenario(plain, tmp_path / "plain", "commonroad")
    document, _ = read(path)
    assert not document.lanelet_network.lanelets
    (boundary,) = document.static_obstacles
    assert boundary.obstacle_type.value == "roadBoundary"
    offroad = shapely.union_all(
        [shapely.Polygon(p.vertices) for p in boundary.obstacle_shape.shapes]
    )
    raster = shapely.box(*plain.map.bounds)
    assert offroad.intersection(road).area < 1e-6
    assert offroad.union(road).area == pytest.approx(raster.area)


def test_the_collision_checker_agrees_with_the_event_log(tmp_path):
    from commonroad.geometry.shape import Rectangle
    from commonroad_dc.collision.collision_detection.pycrcc_collision_dispatch import (
        create_collision_checker,
        create_collision_object,
    )

    # the ego at 5 m/s, a vehicle 20 m behind at 15 m/s: contact after 1.6 s
    scene = make_scenario([(0.0, 0.0, 5.0, 0.0), (-20.0, 0.0, 15.0, 0.0), (0.0, 6.0, 8.0, 0.0)])
    config = EnvConfig(max_agents=3, episode_steps=30)
    with ClosedLoop(
        ConstantVelocityPlanner(), ReplayPolicy(mode="open_loop"), config=config
    ) as loop:
        record = loop.run(scene, seed=0)
    logged = [
        e["step"] for e in record.events if e["event"] == "collision_start" and e["ego_involved"]
    ]
    assert logged, "the scene must crash"
    executed = record.to_scenario()
    (path,) = export_scenario(executed, tmp_path / "crash", "commonroad")
    document, _ = read(path)
    checker = create_collision_checker(document)
    now = executed.current_index
    length, width = float(executed.length[0]), float(executed.width[0])
    found = []
    for step in range(executed.states.shape[1] - now):
        if not executed.valid[0, now + step]:
            break
        x, y, _, heading = executed.states[0, now + step]
        ego = create_collision_object(Rectangle(length, width, np.array([x, y]), heading))
        if checker.time_slice(step).collide(ego):
            found.append(step)
    assert found and found[0] == logged[0] == 16
