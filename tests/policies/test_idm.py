"""IDMPolicy: protocol, shapes, car following, lane keeping, closed loop on highway scenes."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from policies.base import ScenePolicy
from policies.baselines.idm import IDMParams, IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig


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
