"""The PettingZoo-style module ``riskflow_env.riskflow_v0`` and its ``max_cycles`` option."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from pettingzoo.test import max_cycles_test

from riskflow_env import riskflow_v0
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig


def test_pettingzoo_max_cycles_test():
    """PettingZoo's check counts turns per *possible* agent and expects most of them live,
    so the scenes fill every slot here (the default bank's scenes fill 8-32 of 32)."""
    full = {
        # nobody terminates: PettingZoo's check resets unseeded and steps random actions
        "config": EnvConfig(
            max_agents=8, terminate_on_collision="none", terminate_on_offroad="none"
        ),
        "scenarios": HighwayTrafficSource(
            TrafficConfig(families=("highway",), num_vehicles=(8, 8))
        ),
    }
    module = SimpleNamespace(
        parallel_env=lambda max_cycles: riskflow_v0.parallel_env(max_cycles=max_cycles, **full),
        env=lambda max_cycles: riskflow_v0.env(max_cycles=max_cycles, **full),
    )
    max_cycles_test(module)


def test_max_cycles_sets_the_episode_length_and_keeps_the_rest_of_the_config():
    config = EnvConfig(max_agents=6, episode_steps=50)
    env = riskflow_v0.parallel_env(config=config, max_cycles=3)
    assert env.config.episode_steps == 3 and env.config.max_agents == 6
    env.reset(seed=0)
    steps = 0
    while env.agents:
        env.step({agent: env.action_space(agent).sample() for agent in env.agents})
        steps += 1
    assert steps <= 3
    assert riskflow_v0.parallel_env().config.episode_steps == EnvConfig().episode_steps


@pytest.mark.parametrize("bad", [0, -2, 2.5, True, "10"])
def test_bad_max_cycles_names_the_argument(bad):
    with pytest.raises(ValueError, match="max_cycles must be an int >= 1"):
        riskflow_v0.parallel_env(max_cycles=bad)
