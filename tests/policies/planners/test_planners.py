"""Ego planners: the EgoPlanner signature, actions within bounds, braking behind a stopped car."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from policies.harness import ClosedLoop
from policies.planners import (
    PLANNERS,
    ConstantVelocityPlanner,
    EgoPlanner,
    IDMPlanner,
    as_action,
    reset_planner,
)
from riskflow_env.agents import ConstantVelocityPolicy, IDMPolicy
from riskflow_env.config import DynamicsConfig, EnvConfig
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import Scenario, shipped_bank

SPEED = 15.0  # [m/s] the ego's speed
STOPPED_AT = 40.0  # [m] where the stopped car stands, ahead of the ego at x = 0


def stopped_car_scene() -> Scenario:
    """A straight lane; the ego at 15 m/s, a car standing 40 m ahead in its lane."""
    road = from_lanes([Lane(np.array([[-100.0, 0.0], [400.0, 0.0]]), 3.5, "road")])
    steps = 31 + 100
    time = 0.1 * (np.arange(steps) - 30)
    states = np.zeros((2, steps, 4))
    states[0, :, 0], states[0, :, 2] = SPEED * time, SPEED
    states[1, :, 0] = STOPPED_AT
    return Scenario(road, states, np.ones((2, steps), bool), np.full(2, 4.5), np.full(2, 1.9))


def start(scenario: Scenario):
    env = riskflow_env.parallel_env(scenarios=scenario)
    observations, _ = env.reset(seed=0, options={"scenario": scenario})
    return env, observations


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_builtin_planners_are_ego_planners(name):
    assert isinstance(PLANNERS[name](), EgoPlanner)


def test_idm_planner_brakes_hard_behind_a_stopped_car():
    env, observations = start(stopped_car_scene())
    planner = IDMPlanner()
    reset_planner(planner, env.view())
    accel, yaw_rate = planner(observations["ego"], env.view())
    assert accel <= -4.0  # 35.5 m gap at 15 m/s: IDM wants ~90 m
    assert abs(yaw_rate) < 1e-6  # on the lane centre, heading along it


def test_idm_planner_stops_behind_a_stopped_car_in_closed_loop():
    with ClosedLoop(IDMPlanner(), ConstantVelocityPolicy(), scenarios=stopped_car_scene()) as loop:
        record = loop.run(stopped_car_scene())
    assert not record.metrics["ego_collided"]
    assert record.metrics["steps"] == 100
    assert record.states[0, -1, 2] < 0.5  # [m/s] standing
    assert 0.5 < record.metrics["min_distance_to_ego"] < 5.0  # [m] close behind, not touching


def test_constant_velocity_planner_holds_speed_into_the_stopped_car():
    planner = ConstantVelocityPlanner()
    assert np.array_equal(planner(np.zeros(142)), np.zeros(2))
    with ClosedLoop(planner, ConstantVelocityPolicy(), scenarios=stopped_car_scene()) as loop:
        record = loop.run(stopped_car_scene())
    assert record.metrics["ego_collided"]
    expected = (STOPPED_AT - 4.5) / SPEED  # [s] gap closed at 15 m/s
    assert record.metrics["time_to_first_ego_collision"] == pytest.approx(expected, abs=0.11)


def test_idm_planner_actions_within_bounds_on_shipped_scenes():
    bounds = DynamicsConfig()
    planner = IDMPlanner(dynamics=bounds)
    traffic = IDMPolicy(controlled="others")
    env = riskflow_env.parallel_env(config=EnvConfig(episode_steps=20))
    for index in (0, 2, 3):  # highway, roundabout, intersection
        observations, _ = env.reset(options={"scenario": shipped_bank("eval")[index]})
        reset_planner(planner, env.view())
        traffic.reset(env.view())
        while "ego" in env.agents:
            action = as_action(planner(observations["ego"], env.view()))
            assert np.all(np.isfinite(action))
            assert bounds.accel_min <= action[0] <= bounds.accel_max
            assert abs(action[1]) <= bounds.yaw_rate_max
            observations, *_ = env.step({**traffic.act(env.view()), "ego": action})


def test_a_plain_function_is_a_planner_and_bad_actions_are_named():
    def planner(observation, view):
        return [1.0, 0.0]

    assert isinstance(planner, EgoPlanner)
    reset_planner(planner, None)  # no reset method: nothing happens
    assert as_action(planner(None, None)).shape == (2,)
    with pytest.raises(ValueError, match=r"shape \(2,\).*got shape \(3,\)"):
        as_action([1.0, 0.0, 0.0], "my planner")


def test_an_action_that_is_not_two_numbers_names_the_planner():
    from policies.planners.base import as_action

    np.testing.assert_array_equal(as_action([1, 0.5]), [1.0, 0.5])
    with pytest.raises(ValueError, match="my planner must return an action of two numbers"):
        as_action("fast", "my planner")
    with pytest.raises(ValueError, match=r"of shape \(2,\)"):
        as_action([1.0, 2.0, 3.0])
