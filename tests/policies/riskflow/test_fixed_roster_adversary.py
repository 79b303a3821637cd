"""An ego trained against the RiskFlow adversary through ``FixedRosterEnv(roster=["ego"],
policy=RiskFlowAdversary(...))``: PettingZoo's seed test (a seeded reset reseeds the
adversary) and RLlib PPO on it (the ``rllib`` extra)."""

from __future__ import annotations

import numpy as np
import pytest

from policies.riskflow import RiskFlowAdversary
from riskflow_env.config import EnvConfig
from riskflow_env.wrappers import FixedRosterEnv
from tests.pettingzoo_checks import pettingzoo_checks
from tests.policies.straight_road import make_road_scenario


@pytest.fixture
def make_env(tiny_meanflow, tiny_normalizer):
    def make(context: object = None) -> FixedRosterEnv:
        adversary = RiskFlowAdversary(
            k=2, planning_interval=0.3, seed=0, generator=tiny_meanflow, normalizer=tiny_normalizer
        )
        config = EnvConfig(max_agents=8, episode_steps=8)
        return FixedRosterEnv(
            config=config, scenarios=[make_road_scenario()], policy=adversary, roster=["ego"]
        )

    return make


def test_pettingzoo_api_and_seed_tests(make_env):
    pettingzoo_checks(make_env, num_cycles=10)


def test_seeded_reset_repeats_the_adversary_bit_for_bit(make_env):
    env = make_env()

    def others(seed: int) -> np.ndarray:
        env.reset(seed=seed)
        for _ in range(6):
            env.step({"ego": np.zeros(2, np.float32)})
        return env.env.scene.current[1:].copy()

    first = others(5)
    others(9)
    np.testing.assert_array_equal(others(5), first)


@pytest.mark.extras
def test_rllib_ppo_ego_against_the_riskflow_adversary(make_env, local_ray):
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    register_env("riskflow_ego_vs_adversary_test", lambda c: ParallelPettingZooEnv(make_env(c)))
    config = (
        PPOConfig()
        .environment("riskflow_ego_vs_adversary_test")
        .env_runners(num_env_runners=0, rollout_fragment_length=16)
        .multi_agent(policies={"ego"}, policy_mapping_fn=lambda agent_id, *_, **__: "ego")
        .training(train_batch_size_per_learner=32, minibatch_size=16, num_epochs=1)
        .debugging(seed=0)
    )
    algorithm = config.build_algo()
    try:
        result = algorithm.train()
        assert result["env_runners"]["num_env_steps_sampled_lifetime"] >= 32
        assert np.isfinite(result["env_runners"]["episode_return_mean"])
    finally:
        algorithm.stop()
