"""Pure reset / step functions and the observation layout."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import box

from riskflow_env import dynamics, simulator
from riskflow_env.config import DynamicsConfig, ObservationConfig
from riskflow_env.maps import from_polygons
from riskflow_env.observations import observation_size, observe
from riskflow_env.risk import pairwise_features
from riskflow_env.scenarios import Scenario
from riskflow_env.state import HISTORY_STEPS


def straight_scenario(num_agents: int = 3, steps: int = 40) -> Scenario:
    road = from_polygons([box(-50, -6, 400, 6)], resolution=0.5)
    t = np.arange(steps) * 0.1
    x0 = np.array([0.0, 30.0, -30.0, 60.0, 90.0])[:num_agents]
    speed = np.array([10.0, 8.0, 12.0, 9.0, 7.0])[:num_agents]
    states = np.zeros((num_agents, steps, 4))
    states[..., 0] = x0[:, None] + speed[:, None] * t
    states[..., 2] = speed[:, None]
    return Scenario(
        map=road,
        states=states,
        valid=np.ones((num_agents, steps), bool),
        length=np.full(num_agents, 4.5),
        width=np.full(num_agents, 2.0),
    )


def test_reset_orders_agents_by_distance_and_fills_slots():
    scenario = straight_scenario(5)
    state = simulator.reset(scenario, max_agents=4)
    assert state.present.tolist() == [True, True, True, True]
    # at t = 3 s: ego at 30 m; others at 54, 6 (both 24 m away, stable order), 87, 111 (dropped)
    np.testing.assert_array_equal(state.current[:, 0], [30.0, 54.0, 6.0, 87.0])
    assert state.history.shape == (4, HISTORY_STEPS, 4)


def test_reset_pads_empty_slots():
    state = simulator.reset(straight_scenario(2), max_agents=5)
    assert state.present.tolist() == [True, True, False, False, False]
    assert not state.history_valid[2:].any()


def test_step_matches_dynamics_and_rolls_history():
    state = simulator.reset(straight_scenario(3), max_agents=3)
    actions = np.array([[1.0, 0.1], [-2.0, 0.0], [0.0, -0.2]])
    config = DynamicsConfig()
    new = simulator.step(state, actions, config)
    np.testing.assert_array_equal(new.current, dynamics.step(state.current, actions, config))
    np.testing.assert_array_equal(new.history[:, :-1], state.history[:, 1:])
    assert new.step == 1 and state.step == 0  # the input state is untouched


def test_inactive_vehicles_stand_still():
    state = simulator.reset(straight_scenario(3), max_agents=3)
    state = state.replace(active=np.array([True, False, True]))
    new = simulator.step(state, np.ones((3, 2)), DynamicsConfig())
    np.testing.assert_array_equal(new.current[1, :2], state.current[1, :2])
    assert new.current[1, 2] == 0.0 and new.last_action[1].tolist() == [0.0, 0.0]


def test_scene_state_checks_shapes():
    state = simulator.reset(straight_scenario(2), max_agents=2)
    with pytest.raises(ValueError, match="length"):
        state.replace(length=np.ones(3))


def test_observation_layout_nearest_first():
    scenario = straight_scenario(4)
    state = simulator.reset(scenario, max_agents=6)
    config = ObservationConfig(num_neighbors=3, ray_directions=4, ray_distances=(1.0, 5.0))
    features, mask = pairwise_features(state.current, state.length, state.width, state.present)
    obs = observe(state, features, mask, scenario.map, config)
    assert obs.shape == (6, observation_size(config)) and obs.dtype == np.float32
    assert not obs[4:].any()  # empty slots
    ego_neighbors = obs[0, 6 : 6 + 3 * 11].reshape(3, 11)
    # 24 m ahead and behind are observed; the third vehicle (57 m) is beyond 50 m: absent
    np.testing.assert_allclose(ego_neighbors[:, 0], [24.0, -24.0, 0.0])
    np.testing.assert_array_equal(ego_neighbors[:, -1], [1.0, 1.0, 0.0])
    assert not ego_neighbors[2].any()
    assert obs[0, 5] < 0  # the ego's centre is on the road
