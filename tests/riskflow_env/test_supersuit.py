"""SuperSuit vector envs over ``riskflow_v0`` (the ``rl`` extra).

What SuperSuit needs from the default env (docs/how-to/interop.md;
``FixedRosterEnv`` lifts the first two, tests/riskflow_env/wrappers/test_vector.py):

* identical observation and action spaces for every agent: they are;
* ``pettingzoo_env_to_vec_env_v1`` alone: an observation for every slot at every step,
  so every slot must be filled at reset (a scenario source that always places
  ``max_agents`` vehicles) and no agent may finish before the others
  (``terminate_on_collision="none"``, ``terminate_on_offroad="none"``): the episode then
  ends for all at once (truncation) and the vector env resets it;
* agents that finish early need ``supersuit.black_death_v3`` (zero observations and
  rewards for finished agents); it too needs every slot filled at reset. SuperSuit
  <= 3.11 has a bug there (Farama-Foundation/SuperSuit#254, fixed by #265): the wrapped
  env never reports the end of the episode, so the vector env cannot reset it.
"""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig

supersuit = pytest.importorskip(
    "supersuit", reason="supersuit is not installed (pip install -e '.[rl]')"
)

SLOTS = 6


def full_roster_env(**config) -> riskflow_env.RiskFlowParallelEnv:
    source = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(SLOTS, SLOTS)))
    return riskflow_env.parallel_env(
        config=EnvConfig(max_agents=SLOTS, episode_steps=10, **config), scenarios=source
    )


def random_actions(vec_env, rng: np.random.Generator) -> np.ndarray:
    low, high = vec_env.action_space.low, vec_env.action_space.high
    return rng.uniform(low, high, (vec_env.num_envs, *low.shape)).astype(np.float32)


def test_vec_env_steps_and_resets_episodes():
    vec_env = supersuit.pettingzoo_env_to_vec_env_v1(
        full_roster_env(terminate_on_collision="none", terminate_on_offroad="none")
    )
    assert vec_env.num_envs == SLOTS
    observations, infos = vec_env.reset(seed=0)
    assert observations.shape == (SLOTS, *vec_env.observation_space.shape)
    rng = np.random.default_rng(0)
    episode_ends = 0
    for _ in range(25):
        observations, rewards, terminations, truncations, infos = vec_env.step(
            random_actions(vec_env, rng)
        )
        assert observations.shape == (SLOTS, *vec_env.observation_space.shape)
        assert rewards.shape == (SLOTS,) and np.all(np.isfinite(rewards))
        if truncations.all():
            episode_ends += 1
            assert all("terminal_observation" in info for info in infos)
    assert episode_ends == 2  # 10-step episodes, reset by the vector env


def test_concat_vec_envs():
    vec_env = supersuit.pettingzoo_env_to_vec_env_v1(
        full_roster_env(terminate_on_collision="none", terminate_on_offroad="none")
    )
    vec_env = supersuit.concat_vec_envs_v1(vec_env, 2, num_cpus=0, base_class="gymnasium")
    observations, _ = vec_env.reset(seed=0)
    assert observations.shape[0] == 2 * SLOTS
    observations, rewards, *_ = vec_env.step(random_actions(vec_env, np.random.default_rng(1)))
    assert observations.shape[0] == rewards.shape[0] == 2 * SLOTS


def test_black_death_for_agents_that_finish_early():
    env = full_roster_env(
        terminate_on_collision="all", terminate_on_offroad="all", end_with_ego=False
    )
    vec_env = supersuit.pettingzoo_env_to_vec_env_v1(supersuit.black_death_v3(env))
    vec_env.reset(seed=0)
    rng = np.random.default_rng(0)
    finished = set()
    for _ in range(9):  # within the first (10-step) episode
        actions = random_actions(vec_env, rng)
        actions[:, 1] = np.sign(actions[:, 1])  # full yaw rate: cars leave the road
        observations, rewards, *_ = vec_env.step(actions)
        for index, agent in enumerate(env.possible_agents):
            if agent in finished:
                assert not observations[index].any() and rewards[index] == 0.0
        finished = set(env.possible_agents) - set(env.agents)
    assert finished  # some agents left the road and finished while others drive on
