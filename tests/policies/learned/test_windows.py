"""Training windows (docs/how-to/windows.md): shapes, scene frame, actions, selection, live view."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import riskflow_env
from policies.learned.window_types import FUTURE_FIELDS, Window
from policies.learned.windows import WindowConfig, window_from_scenario, window_from_view
from riskflow_env import dynamics
from riskflow_env.config import DynamicsConfig
from riskflow_env.risk import NUM_PAIR_FEATURES
from riskflow_env.scenarios import HighwayTrafficSource, Scenario, TrafficConfig

H, F, S = 31, 52, 48


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return HighwayTrafficSource().sample(np.random.default_rng(3))


def rolled_scenario(seed: int) -> Scenario:
    """A synthetic scene whose tracks follow the unicycle model exactly, with gaps."""
    base = HighwayTrafficSource(TrafficConfig(families=("highway",))).sample(
        np.random.default_rng(seed)
    )
    rng = np.random.default_rng(seed)
    num_agents, num_steps = base.states.shape[:2]
    actions = np.stack(
        [
            rng.uniform(-1.0, 1.0, (num_agents, num_steps - 1)),
            rng.uniform(-0.05, 0.05, (num_agents, num_steps - 1)),
        ],
        axis=-1,
    )
    start = base.states[:, 0]
    states = np.concatenate([start[:, None], dynamics.rollout(start, actions)], axis=1)
    valid = np.ones((num_agents, num_steps), dtype=bool)
    valid[1:, 60:63] = False  # a gap in the future of every non-ego agent
    valid[1:, :5] = False  # late appearance
    return dataclasses.replace(base, states=states, valid=valid)


EXPECTED = {
    "history": ((H, 4), np.float32),
    "history_valid": ((H,), np.bool_),
    "future": ((F, 4), np.float32),
    "future_valid": ((F,), np.bool_),
    "actions": ((F, 2), np.float32),
    "actions_valid": ((F,), np.bool_),
    "agent_mask": ((), np.bool_),
    "agent_index": ((), np.int64),
    "length": ((), np.float32),
    "width": ((), np.float32),
    "map_crops": ((2, S, S), np.float32),
}


def check_contract(window: Window, with_future: bool) -> int:
    num_agents = window.history.shape[0]
    expected = dict(EXPECTED)
    expected["pair_features"] = ((num_agents, NUM_PAIR_FEATURES), np.float32)
    expected["pair_mask"] = ((num_agents,), np.bool_)
    if not with_future:
        expected = {k: v for k, v in expected.items() if k not in FUTURE_FIELDS}
    assert isinstance(window, Window) and window.has_future == with_future
    assert {name for name, _ in window.arrays()} == set(expected)
    for key, (shape, dtype) in expected.items():
        assert getattr(window, key).shape == (num_agents, *shape), key
        assert getattr(window, key).dtype == dtype, key
    return num_agents


@pytest.mark.parametrize("current_index", [30, 55, 78])
def test_window_shapes_dtypes_and_scene_frame(scenario, current_index):
    window = window_from_scenario(scenario, current_index)
    num_agents = check_contract(window, with_future=True)
    now = scenario.states[:, current_index, :2]
    near = np.linalg.norm(now - now[scenario.ego_index], axis=-1) <= 150.0
    present = np.flatnonzero(scenario.valid[:, current_index] & near)
    assert num_agents == present.size and set(window.agent_index) == set(present)
    assert window.agent_index[0] == scenario.ego_index
    assert window.agent_mask.all() and window.history_valid[:, -1].all()

    ego_now = window.history[0, -1]
    np.testing.assert_allclose(ego_now[[0, 1, 3]], 0.0, atol=1e-5)  # origin, heading +x
    world = scenario.states[window.agent_index, current_index]
    np.testing.assert_allclose(ego_now[2], world[0, 2], rtol=1e-6)  # speeds unchanged
    # distances and relative headings are frame independent
    scene_xy = window.history[:, -1, :2]
    np.testing.assert_allclose(
        np.linalg.norm(scene_xy, axis=-1),
        np.linalg.norm(world[:, :2] - world[0, :2], axis=-1),
        atol=1e-4,
    )
    relative = dynamics.wrap_angle(world[:, 3] - world[0, 3])
    np.testing.assert_allclose(window.history[:, -1, 3], relative, atol=1e-5)
    # slots are ordered by distance to the ego
    assert np.all(np.diff(np.linalg.norm(scene_xy, axis=-1)) >= -1e-4)
    # map crops: the agent sits at the crop centre, on the road; SDF clipped to 10 m
    centre = window.map_crops[:, :, S // 2 - 1 : S // 2 + 1, S // 2 - 1 : S // 2 + 1]
    assert np.all(centre[:, 0] > 0.5) and np.all(centre[:, 1] < 0.5)
    assert np.abs(window.map_crops[:, 1]).max() <= 10.0
    np.testing.assert_array_equal(window.pair_mask.diagonal(), False)


def test_actions_reproduce_the_future_through_the_rollout():
    for seed in range(3):
        scenario = rolled_scenario(seed)
        for current_index in (30, 50):
            window = window_from_scenario(scenario, current_index)
            future, valid = window.future, window.future_valid
            actions, actions_valid = window.actions, window.actions_valid
            chain_valid = np.concatenate([window.agent_mask[:, None], valid], axis=1)
            np.testing.assert_array_equal(actions_valid, chain_valid[:, 1:] & chain_valid[:, :-1])
            assert np.all(actions[~actions_valid] == 0) and np.all(future[~valid] == 0)
            assert not actions_valid[1:].all()  # the gap is inside the window
            in_bounds = np.all(dynamics.clip_actions(actions) == actions, axis=-1)
            usable = np.cumprod(actions_valid & in_bounds, axis=1).astype(bool)  # valid prefix
            rolled = dynamics.rollout(
                window.history[:, -1].astype(np.float64), actions.astype(np.float64)
            )
            error = np.linalg.norm(rolled[..., :2] - future[..., :2], axis=-1)
            assert usable[0].all() and usable[:, :5].all()
            assert error[usable].max() < 1e-4


def test_history_and_future_beyond_the_track_are_invalid(scenario):
    window = window_from_scenario(scenario, 10)
    assert not window.history_valid[:, : H - 11].any()
    assert np.all(window.history[:, : H - 11] == 0)
    late = window_from_scenario(scenario, scenario.states.shape[1] - 11)
    assert not late.future_valid[:, 10:].any()
    assert not late.actions_valid[:, 10:].any()


def test_agent_selection_respects_max_agents_and_max_distance(scenario):
    near = window_from_scenario(scenario, config=WindowConfig(max_agents=3))
    assert near.history.shape[0] == 3
    full = window_from_scenario(scenario)
    np.testing.assert_array_equal(near.agent_index, full.agent_index[:3])
    distance = np.linalg.norm(full.history[:, -1, :2], axis=-1)
    radius = float(0.5 * (distance[3] + distance[4]))
    cut = window_from_scenario(scenario, config=WindowConfig(max_distance=radius))
    np.testing.assert_array_equal(cut.agent_index, full.agent_index[:4])


def test_bad_inputs_are_named(scenario):
    invalid = scenario.valid.copy()
    invalid[scenario.ego_index, 40] = False
    holed = dataclasses.replace(scenario, valid=invalid)
    with pytest.raises(ValueError, match="ego"):
        window_from_scenario(holed, 40)
    with pytest.raises(ValueError, match="current_index"):
        window_from_scenario(scenario, scenario.states.shape[1])
    for index in (1.5, "3", True):
        with pytest.raises(ValueError, match="current_index must be an int step index"):
            window_from_scenario(scenario, index)
    with pytest.raises(ValueError, match="dt"):
        window_from_scenario(scenario, config=WindowConfig(dynamics=DynamicsConfig(dt=0.2)))
    with pytest.raises(ValueError, match="max_agents"):
        WindowConfig(max_agents=0)
    with pytest.raises(
        TypeError, match=r"config must be a WindowConfig .*WindowConfig\(\*\*options"
    ):
        window_from_scenario(scenario, 30, {"max_agents": 4})
    with pytest.raises(TypeError, match="scenario must be a Scenario, got str"):
        window_from_scenario("scene-0061", 30)


@pytest.mark.parametrize("name", ["crop_resolution", "sdf_clip", "max_distance"])
def test_window_config_numbers(name):
    """A bool was taken as 1 m and np.float32 refused; now the other way round."""
    with pytest.raises(ValueError, match=f"WindowConfig.{name} must be a number, got True"):
        WindowConfig(**{name: True})
    value = getattr(WindowConfig(**{name: np.float32(0.5)}), name)
    assert type(value) is float and value == 0.5


def test_view_window_equals_scenario_window_at_the_episode_start(scenario):
    env = riskflow_env.parallel_env()
    env.reset(seed=0, options={"scenario": scenario})
    view = env.view()
    live = window_from_view(view)
    recorded = window_from_scenario(scenario)
    check_contract(live, with_future=False)
    for key, value in live.arrays():
        if key == "agent_index":  # env slots vs scenario rows
            np.testing.assert_array_equal(view.scenario_rows[value], recorded.agent_index)
        else:
            np.testing.assert_array_equal(value, getattr(recorded, key), err_msg=key)


def test_view_window_follows_the_live_scene(scenario):
    env = riskflow_env.parallel_env()
    env.reset(seed=0, options={"scenario": scenario})
    for _ in range(5):
        env.step({agent: np.array([0.5, 0.0]) for agent in env.agents})
    view = env.view()
    window = window_from_view(view)
    assert window.agent_index[0] == 0
    np.testing.assert_allclose(window.history[0, -1, [0, 1, 3]], 0.0, atol=1e-5)
    assert sorted(window.agent_index) == list(np.flatnonzero(view.present))
    speed = view.current[window.agent_index, 2]
    np.testing.assert_allclose(window.history[:, -1, 2], speed, rtol=1e-6)
