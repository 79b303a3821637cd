"""Agents leave the scene when their logged reference ends (EnvConfig.leave_when_log_ends)."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env import simulator
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios.scenarionet import scenario_from_description
from tests.riskflow_env.scenarios.scenarionet_sources import description


@pytest.fixture(scope="module")
def scenario():
    return scenario_from_description(description("nuscenes"))  # "car": log ends at 6 s


def _car_slot(scenario, max_agents):
    rows = simulator.select_agents(scenario, max_agents)
    return list(rows).index(scenario.agent_ids.index("car"))


def test_log_end_steps(scenario):
    rows = simulator.select_agents(scenario, 4)
    ends = simulator.log_end_steps(scenario, rows, 4)
    slot = _car_slot(scenario, 4)
    assert ends[slot] == 60 - scenario.current_index  # last valid recorded step 60
    assert ends[0] == np.iinfo(np.int64).max  # the ego never leaves
    assert ends[3] == np.iinfo(np.int64).max  # empty slot


@pytest.mark.parametrize("leave", [True, False])
def test_agent_leaves_after_its_log(scenario, leave):
    config = EnvConfig(max_agents=4, episode_steps=40, leave_when_log_ends=leave)
    env = riskflow_env.parallel_env(config=config, scenarios=scenario)
    env.reset(seed=0, options={"scenario": scenario})
    name = env.possible_agents[_car_slot(scenario, 4)]
    last = 60 - scenario.current_index
    for step in range(1, 40):
        assert name in env.agents
        _, _, terminations, truncations, _ = env.step({a: np.zeros(2) for a in env.agents})
        assert not terminations[name]
        assert truncations[name] == (leave and step == last + 1)
        if leave and step > last:
            break
    slot = env.possible_agents.index(name)
    assert (name in env.agents) != leave
    assert bool(env.scene.present[slot]) != leave


def test_config_checks_the_flag():
    with pytest.raises(ValueError, match="leave_when_log_ends"):
        EnvConfig(leave_when_log_ends=1)
