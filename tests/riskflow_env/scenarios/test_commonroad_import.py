"""CommonRoad XML as a scenario source: the four NGSIM scenarios of shared/data/commonroad
load, their recorded vehicles drive on the map, and closed loops run on them."""

from __future__ import annotations

import numpy as np
import pytest

from tests.riskflow_env.scenarios.interop import require

require("commonroad.common.file_reader")

from policies.harness import ClosedLoop  # noqa: E402
from policies.planners import IDMPlanner  # noqa: E402
from riskflow_env.agents.idm import IDMPolicy  # noqa: E402
from riskflow_env.config import EnvConfig  # noqa: E402
from riskflow_env.scenarios.commonroad_import import load_commonroad  # noqa: E402
from riskflow_env.scenarios.exchange import read_scene  # noqa: E402
from riskflow_env.scenarios.folders import open_scenes  # noqa: E402
from tests.samples import COMMONROAD, COMMONROAD_DIR, require_commonroad  # noqa: E402

ON_MAP = 0.95  # share of the recorded vehicles' logged positions on the drivable map


@pytest.fixture(scope="module")
def scenes():
    return {path.stem: load_commonroad(path) for path in require_commonroad()}


def test_the_four_ngsim_scenarios_load(scenes):
    assert len(scenes) == 4
    for name, scene in scenes.items():
        assert scene.name == f"commonroad/{name}"
        assert scene.ego_index == 0 and scene.valid[0, scene.current_index]
        assert not scene.valid[0, scene.current_index + 1 :].any()  # a goal, not a track
        assert scene.num_agents > 1 and set(scene.kinds) == {"car"}
        assert scene.future_steps >= 100 and scene.dt == 0.1
        assert scene.map.lanes and scene.map.is_drivable(scene.states[0, scene.current_index, :2])
        known = {lane.lane_id for lane in scene.map.lanes}
        assert all(set(lane.successors) <= known for lane in scene.map.lanes)


def test_recorded_vehicles_are_on_the_map(scenes):
    for name, scene in scenes.items():
        valid = scene.valid[1:]
        on_map = scene.map.is_drivable(scene.states[1:][valid][:, :2])
        assert on_map.mean() >= ON_MAP, f"{name}: {on_map.mean():.3f}"  # measured 1.000


def test_recorded_tracks_follow_the_file(scenes):
    from commonroad.common.file_reader import CommonRoadFileReader

    path = COMMONROAD[0]
    scenario, _ = CommonRoadFileReader(str(path)).open()
    scene = scenes[path.stem]
    obstacle = scenario.dynamic_obstacles[0]
    row = scene.agent_ids.index(str(obstacle.obstacle_id))
    for state in obstacle.prediction.trajectory.state_list:
        step = scene.current_index + state.time_step
        assert scene.valid[row, step]
        np.testing.assert_allclose(scene.states[row, step, :2], state.position)
        assert scene.states[row, step, 2] == pytest.approx(state.velocity)
    assert scene.length[row] == pytest.approx(obstacle.obstacle_shape.length)


def test_a_folder_of_commonroad_files_is_a_scene_source(scenes):
    bank = open_scenes(COMMONROAD_DIR)
    assert sorted(bank.names) == sorted(scene.name for scene in scenes.values())
    assert read_scene(COMMONROAD[0]).name == f"commonroad/{COMMONROAD[0].stem}"


def test_a_closed_loop_runs_on_a_commonroad_scene(scenes):
    scene = scenes["USA_US101-3_3_T-1"]
    with ClosedLoop(IDMPlanner(), IDMPolicy(), config=EnvConfig(episode_steps=20)) as loop:
        record = loop.run(scene, seed=0)
    assert record.metrics["steps"] == 20
    assert record.present.sum() == scene.num_agents


def test_bad_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_commonroad(tmp_path / "none.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<commonRoad><nonsense/></commonRoad>")
    with pytest.raises(ValueError, match="bad.xml"):
        load_commonroad(bad)


def test_time_steps_beyond_a_recorded_scene_are_refused_before_any_array(tmp_path):
    """A state at time step 10**9 (or a time step of 1 ms) would allocate gigabytes of
    tracks: refused naming the file and the limit."""
    source = next(path for path in require_commonroad() if "Peach" in path.name)
    text = source.read_text()
    far = tmp_path / "far.xml"
    far.write_text(text.replace("<exact>2</exact>", "<exact>1000000000</exact>", 1))
    with pytest.raises(ValueError, match="MAX_STEPS") as error:
        load_commonroad(far)
    assert str(far) in str(error.value)
    fine = tmp_path / "fine.xml"
    fine.write_text(text.replace('timeStepSize="0.1"', 'timeStepSize="0.001"', 1))
    with pytest.raises(ValueError, match="time step dt"):
        load_commonroad(fine)


@pytest.mark.parametrize("value", ["nan", "inf", "1e12"])
def test_lanelet_vertices_out_of_range_are_named(tmp_path, value):
    """A lanelet point that is NaN, inf or far beyond any map is refused naming the file and
    the lanelet, before shapely or the rasteriser sees it."""
    source = next(path for path in require_commonroad() if "Peach" in path.name)
    text = source.read_text()
    start = text.index("<x>") + len("<x>")
    bad = tmp_path / "bad.xml"
    bad.write_text(text[:start] + value + text[text.index("</x>", start) :])
    with pytest.raises(ValueError, match=r"bad.xml: lanelet \d+ polygon has vertices that are"):
        load_commonroad(bad)
