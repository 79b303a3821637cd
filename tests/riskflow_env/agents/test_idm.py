"""IDMPolicy: protocol, shapes, car following, lane keeping, closed loop on highway scenes."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.agents.idm import IDMParams, IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import HighwayTrafficSource, Scenario, TrafficConfig
from riskflow_env.view import ScenePolicy


def _env(family: str) -> riskflow_env.env.RiskFlowParallelEnv:
    config = EnvConfig(terminate_on_collision="none", terminate_on_offroad="none")
    source = HighwayTrafficSource(TrafficConfig(families=(family,)))
    return riskflow_env.parallel_env(config=config, scenarios=source)


def test_protocol_and_default_constructor():
    policy = IDMPolicy(controlled="others")
    assert isinstance(policy, ScenePolicy)
    env = _env("highway")
    env.reset(seed=0)
    policy.reset(env.view())
    actions = policy.act(env.view())
    assert set(actions) == set(env.agents) - {"ego"}
    for action in actions.values():
        assert action.shape == (2,) and np.all(np.isfinite(action))


def test_params_validation():
    with pytest.raises(ValueError, match="time_headway"):
        IDMParams(time_headway=0.0)
    with pytest.raises(ValueError, match="desired_speed"):
        IDMParams(desired_speed=-1.0)


def test_closed_loop_runs_on_every_family():
    policy = IDMPolicy(controlled="all")
    for family in ("highway", "roundabout", "intersection"):
        env = _env(family)
        env.reset(seed=1)
        policy.reset(env.view())
        while env.agents:
            env.step(policy.act(env.view()))
        assert env.scene.step == 100


@pytest.mark.parametrize("controlled", ["all", ("ego",)])
def test_steer_is_the_yaw_rate_of_act(controlled):
    """steer() computes only the lane keeping; its yaw rates are act()'s, bit for bit."""
    for family in ("highway", "roundabout", "intersection"):
        env = _env(family)
        env.reset(seed=2)
        policy, traffic = IDMPolicy(controlled=controlled), IDMPolicy(controlled="all")
        for _ in range(30):
            view = env.view()
            actions, yaw_rates = policy.act(view), policy.steer(view)
            assert set(yaw_rates) == set(actions) and yaw_rates
            for agent, action in actions.items():
                assert yaw_rates[agent] == action[1]
            env.step(traffic.act(view))


def _queue_scene() -> Scenario:
    """A stopped ego 60 m ahead of a car at 15 m/s on a straight 400 m lane."""
    drivable_map = from_lanes([Lane(np.array([[0.0, 0.0], [400.0, 0.0]]), 4.0, "lane")])
    states = np.zeros((2, 131, 4))
    states[0, :, 0] = 100.0
    states[1, :, 0] = 40.0 + 15.0 * 0.1 * (np.arange(131) - 30)
    states[1, :, 2] = 15.0
    valid = np.ones((2, 131), dtype=bool)
    return Scenario(drivable_map, states, valid, np.full(2, 4.5), np.full(2, 2.0))


def test_follower_stops_behind_a_standing_vehicle():
    scenario = _queue_scene()
    env = riskflow_env.parallel_env(
        config=EnvConfig(terminate_on_collision="none"), scenarios=scenario
    )
    env.reset(options={"scenario": scenario})
    policy = IDMPolicy(params=IDMParams(desired_speed=15.0))
    gaps = []
    while env.agents:
        env.step({**policy.act(env.view()), "ego": np.zeros(2)})
        gaps.append(env.scene.current[0, 0] - env.scene.current[1, 0] - 4.5)
    assert min(gaps) > 1.0 and env.scene.current[1, 2] < 0.5  # creeping up to s0 = 2 m


def test_closed_loop_has_no_collisions_and_stays_on_the_road():
    steps = offroad = 0
    policy = IDMPolicy(controlled="all")
    for family, seed in (
        ("intersection", 0),
        ("intersection", 1),
        ("racetrack", 0),
        ("roundabout", 2),
    ):
        env = _env(family)
        env.reset(seed=seed)
        policy.reset(env.view())
        while env.agents:
            env.step(policy.act(env.view()))
            events, present = env.last_events, env.scene.present
            assert not events.collided.any(), f"{family} seed {seed} step {env.scene.step}"
            steps += present.sum()
            offroad += (events.centroid_offroad & present).sum()
    assert offroad / steps < 0.02
