"""RLlib PPO (new API stack) on ``ParallelPettingZooEnv(FixedRosterEnv(...))``: one shared
policy for every vehicle of scenes with padded slots (the ``rllib`` extra).

The local Ray instance (``tests/conftest.py``) gets 2 CPUs; the env runs in the driver
(``num_env_runners=0``).
"""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import FixedRosterEnv

pytestmark = pytest.mark.extras
REASON = "ray[rllib] is not installed (pip install -e '.[rllib]'; .ci/run installs it)"
pettingzoo_env = pytest.importorskip("ray.rllib.env.wrappers.pettingzoo_env", reason=REASON)
ppo = pytest.importorskip("ray.rllib.algorithms.ppo", reason=REASON)

SLOTS = 4
EPISODE_STEPS = 10


def make_env(config: dict | None = None):
    """The env creator RLlib calls (``config``: RLlib's ``EnvContext``, unused)."""
    source = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(2, SLOTS)))
    env = FixedRosterEnv(
        config=EnvConfig(max_agents=SLOTS, episode_steps=EPISODE_STEPS), scenarios=source
    )
    return pettingzoo_env.ParallelPettingZooEnv(env)


def test_episodes_close_for_rllib():
    """RLlib's wrapper ends an episode when all agents are terminated or all truncated."""
    env = make_env()
    observations, _ = env.reset(seed=0)
    assert set(observations) == set(env.possible_agents) == set(env.observation_space)
    for step in range(EPISODE_STEPS):
        actions = {agent: np.zeros(2, np.float32) for agent in observations}
        observations, _, terminateds, truncateds, _ = env.step(actions)
        ended = terminateds["__all__"] or truncateds["__all__"]
        assert ended == (step == EPISODE_STEPS - 1)


def test_ppo_new_api_stack_one_shared_policy(local_ray):
    from ray.tune.registry import register_env

    register_env("riskflow_fixed_roster_test", make_env)
    config = (
        ppo.PPOConfig()
        .environment("riskflow_fixed_roster_test")
        .env_runners(num_env_runners=0, rollout_fragment_length=40)
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *_, **__: "shared")
        .training(train_batch_size_per_learner=80, minibatch_size=40, num_epochs=1)
        .debugging(seed=0)
    )
    assert config.enable_rl_module_and_learner and config.enable_env_runner_and_connector_v2
    algorithm = config.build_algo()
    try:
        for _ in range(2):
            result = algorithm.train()
        runners = result["env_runners"]
        assert runners["num_env_steps_sampled_lifetime"] >= 160
        assert runners["num_episodes_lifetime"] >= 10  # 10-step episodes closed and restarted
        assert np.isfinite(runners["episode_return_mean"])
    finally:
        algorithm.stop()
