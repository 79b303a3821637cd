"""``sb3_vec_env``: SuperSuit ``pettingzoo_env_to_vec_env_v1`` + ``concat_vec_envs_v1`` over
``FixedRosterEnv``, trained with Stable-Baselines3 PPO with a seed (the ``rl`` extra)."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import FixedRosterEnv, sb3_vec_env

pytest.importorskip("supersuit", reason="supersuit is not installed (pip install -e '.[rl]')")
stable_baselines3 = pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)

SLOTS = 4
FEW = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(2, SLOTS)))


def make_env() -> FixedRosterEnv:
    return FixedRosterEnv(config=EnvConfig(max_agents=SLOTS, episode_steps=8), scenarios=FEW)


def train(seed: int) -> np.ndarray:
    """64 PPO steps on 2 scenes x 4 slots; the policy's parameters, flattened."""
    vec_env = sb3_vec_env(make_env(), num_envs=2)
    model = stable_baselines3.PPO(
        "MlpPolicy", vec_env, n_steps=8, batch_size=32, n_epochs=1, seed=seed, device="cpu"
    )
    model.learn(total_timesteps=64)
    vec_env.close()
    return np.concatenate([p.detach().numpy().ravel() for p in model.policy.parameters()])


def test_ppo_with_a_seed_trains_and_repeats_bit_for_bit():
    first, second = train(seed=0), train(seed=0)
    assert np.all(np.isfinite(first))
    np.testing.assert_array_equal(first, second)


def test_rows_are_scenes_times_roster_and_episodes_reset():
    vec_env = sb3_vec_env(make_env(), num_envs=2)
    assert vec_env.num_envs == 2 * SLOTS
    vec_env.seed(3)
    observations = vec_env.reset()
    again = sb3_vec_env(make_env(), num_envs=2).reset(seed=3)
    np.testing.assert_array_equal(observations, again)
    assert observations.shape == (2 * SLOTS, *vec_env.observation_space.shape)
    ends = 0
    for _ in range(10):  # 8-step episodes: every row is done at step 8, then reset
        observations, rewards, dones, infos = vec_env.step(
            np.zeros((vec_env.num_envs, 2), np.float32)
        )
        assert rewards.shape == (2 * SLOTS,) and np.all(np.isfinite(rewards))
        if dones.all():
            ends += 1
            assert all("terminal_observation" in info for info in infos)
    assert ends == 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_envs": 0}, "num_envs must be an int >= 1"),
        ({"num_envs": 1.5}, "num_envs must be an int >= 1"),
        ({"num_cpus": -1}, "num_cpus must be an int >= 0"),
    ],
)
def test_bad_arguments_name_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        sb3_vec_env(make_env(), **kwargs)


def test_a_gymnasium_env_is_refused():
    with pytest.raises(TypeError, match="env must be a PettingZoo ParallelEnv"):
        sb3_vec_env(object())
