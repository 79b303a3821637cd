"""The Gymnasium ego view ``RiskFlowEgo-v0``: env checker, registration, rollouts, seeding."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import riskflow_env  # noqa: F401 - registers RiskFlowEgo-v0
from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import EgoEnv


class ConstantPolicy:
    """Every other vehicle holds its speed and heading."""

    def reset(self, view) -> None:
        pass

    def act(self, view) -> dict[str, np.ndarray]:
        mask = controlled_mask(view, "others")
        return actions_dict(view, mask, np.zeros((view.num_agents, 2)))


class EgoOnlyMissingPolicy(ConstantPolicy):
    def act(self, view) -> dict[str, np.ndarray]:
        return {}


def small_kwargs(family: str = "highway", **config) -> dict:
    return {
        "config": EnvConfig(max_agents=6, episode_steps=config.pop("episode_steps", 20), **config),
        "scenarios": HighwayTrafficSource(TrafficConfig(families=(family,), num_vehicles=(3, 6))),
    }


def rollout(env: gymnasium.Env, seed: int) -> list:
    observation, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    trace = [observation]
    while True:
        observation, reward, terminated, truncated, info = env.step(env.action_space.sample())
        trace.append((observation, reward, terminated, truncated, info["reward_terms"]))
        if terminated or truncated:
            return trace


def test_check_env():
    check_env(EgoEnv(**small_kwargs()), skip_render_check=True)


def test_make_registered_id():
    env = gymnasium.make("RiskFlowEgo-v0", **small_kwargs())
    assert env.spec.id == "RiskFlowEgo-v0"
    assert env.observation_space == env.unwrapped.parallel_env.observation_space("ego")
    assert env.action_space == env.unwrapped.parallel_env.action_space("ego")
    observation, info = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    assert set(info["reward_terms"]) == {"speed", "collision", "offroad", "risk", "comfort"}
    env.close()


@pytest.mark.parametrize("family", ["highway", "roundabout", "intersection"])
def test_random_rollout_reward_is_sum_of_terms(family):
    env = EgoEnv(**small_kwargs(family))
    trace = rollout(env, seed=3)
    assert 1 <= len(trace) - 1 <= 20
    for observation, reward, _, _, terms in trace[1:]:
        assert env.observation_space.contains(observation)
        assert isinstance(reward, float)
        assert reward == pytest.approx(sum(terms.values()))
    assert trace[-1][2] or trace[-1][3]


@pytest.mark.reliability
def test_same_seed_same_rollout_bit_for_bit():
    first = rollout(EgoEnv(**small_kwargs()), seed=5)
    second = rollout(EgoEnv(**small_kwargs()), seed=5)
    assert len(first) == len(second)
    np.testing.assert_array_equal(first[0], second[0])
    for a, b in zip(first[1:], second[1:], strict=True):
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:] == b[1:]
    other = rollout(EgoEnv(**small_kwargs()), seed=6)
    assert not np.array_equal(first[0], other[0])


def test_default_policy_drives_others_and_custom_policy_is_used():
    env = EgoEnv(**small_kwargs())
    env.reset(seed=1)
    start = env.parallel_env.scene.current.copy()
    env.step(np.zeros(2, dtype=np.float32))
    assert np.any(env.parallel_env.scene.last_action[1:] != 0.0)  # IDM acts on the others
    env = EgoEnv(policy=ConstantPolicy(), **small_kwargs())
    env.reset(seed=1)
    env.step(np.zeros(2, dtype=np.float32))
    np.testing.assert_array_equal(env.parallel_env.scene.last_action, 0.0)
    assert start.shape == env.parallel_env.scene.current.shape


def test_errors():
    with pytest.raises(ValueError, match="missing"):
        env = EgoEnv(policy=EgoOnlyMissingPolicy(), **small_kwargs())
        env.reset(seed=0)
        env.step(np.zeros(2, dtype=np.float32))
    with pytest.raises(TypeError, match="ScenePolicy"):
        EgoEnv(policy=object(), **small_kwargs())
    with pytest.raises(ValueError, match="not both"):
        EgoEnv(env=riskflow_env.parallel_env(), config=EnvConfig())
    env = EgoEnv(policy=ConstantPolicy(), **small_kwargs(episode_steps=1))
    env.reset(seed=0)
    *_, truncated, _ = env.step(np.zeros(2, dtype=np.float32))
    assert truncated
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2, dtype=np.float32))
