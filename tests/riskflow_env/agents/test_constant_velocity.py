"""ConstantVelocityPolicy: zero actions, speeds and headings kept."""

from __future__ import annotations

import numpy as np

import riskflow_env
from riskflow_env.agents.constant_velocity import ConstantVelocityPolicy
from riskflow_env.view import ScenePolicy


def test_keeps_speed_and_heading():
    env = riskflow_env.parallel_env()
    env.reset(seed=0)
    policy = ConstantVelocityPolicy(controlled="all")
    assert isinstance(policy, ScenePolicy)
    policy.reset(env.view())
    start = env.scene.current.copy()
    for _ in range(5):
        actions = policy.act(env.view())
        assert set(actions) == set(env.agents)
        env.step(actions)
    live = env.scene.present
    np.testing.assert_allclose(env.scene.current[live, 2:], start[live, 2:])


def test_others_leaves_the_ego_out():
    env = riskflow_env.parallel_env()
    env.reset(seed=1)
    actions = ConstantVelocityPolicy().act(env.view())
    assert "ego" not in actions and set(actions) == set(env.agents) - {"ego"}
