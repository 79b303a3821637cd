"""PettingZoo API, seeding, determinism and input validation of ``riskflow_v0``."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.maps import FAMILIES
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from tests.pettingzoo_checks import pettingzoo_checks


def make_env(
    family: str = "highway", max_agents: int = 8, **config
) -> riskflow_env.RiskFlowParallelEnv:
    source = HighwayTrafficSource(TrafficConfig(families=(family,), num_vehicles=(4, max_agents)))
    return riskflow_env.parallel_env(
        config=EnvConfig(
            max_agents=max_agents, episode_steps=config.pop("episode_steps", 30), **config
        ),
        scenarios=source,
    )


@pytest.mark.parametrize("family", FAMILIES)
def test_pettingzoo_api_and_seed_tests(family):
    pettingzoo_checks(lambda: make_env(family))


def rollout(env, seed: int, steps: int = 30) -> list:
    observations, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    trace = [observations]
    for _ in range(steps):
        if not env.agents:
            break
        actions = {agent: rng.uniform([-3, -0.3], [2, 0.3]) for agent in env.agents}
        trace.append(env.step(actions))
    return trace + [env.scene.history.copy()]


@pytest.mark.reliability
def test_same_seed_same_rollout_bit_for_bit():
    first, second = rollout(make_env(), seed=7), rollout(make_env(), seed=7)
    assert len(first) == len(second)
    np.testing.assert_array_equal(first[-1], second[-1])
    for a, b in zip(first[1:-1], second[1:-1], strict=True):
        for dict_a, dict_b in zip(a, b, strict=True):
            assert dict_a.keys() == dict_b.keys()
            for key in dict_a:
                np.testing.assert_array_equal(
                    np.asarray(dict_a[key], dtype=object).astype(str),
                    np.asarray(dict_b[key], dtype=object).astype(str),
                )


def test_different_seeds_differ():
    assert not np.array_equal(rollout(make_env(), 1, 2)[-1], rollout(make_env(), 2, 2)[-1])


def test_spaces_identical_and_observations_inside():
    env = make_env()
    observations, infos = env.reset(seed=0)
    assert env.agents[0] == "ego"
    for agent in env.possible_agents:
        assert env.observation_space(agent) == env.observation_space("ego")
        assert env.action_space(agent) == env.action_space("ego")
    for agent, observation in observations.items():
        assert env.observation_space(agent).contains(observation)
        assert set(infos[agent]["reward_terms"]) == {
            "speed",
            "collision",
            "offroad",
            "risk",
            "comfort",
        }
    assert env.state().shape == env.state_space.shape


def test_reward_is_sum_of_terms():
    env = make_env()
    env.reset(seed=3)
    _, rewards, _, _, infos = env.step({a: np.zeros(2) for a in env.agents})
    for agent, reward in rewards.items():
        assert reward == pytest.approx(sum(infos[agent]["reward_terms"].values()))


def test_truncates_after_episode_steps():
    env = make_env(episode_steps=5)
    env.reset(seed=0)
    for _step in range(5):
        _, _, terminations, truncations, _ = env.step({a: np.zeros(2) for a in env.agents})
    assert all(truncations.values()) and not env.agents


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (np.array([np.nan, 0.0]), "finite"),
        (np.array([np.inf, 0.0]), "finite"),
        (np.zeros(3), "shape"),
        (np.zeros((1, 2)), "shape"),
    ],
)
def test_bad_actions_are_rejected(action, message):
    env = make_env()
    env.reset(seed=0)
    actions = {a: np.zeros(2) for a in env.agents}
    actions["ego"] = action
    with pytest.raises(ValueError, match=message):
        env.step(actions)


def test_unknown_and_missing_agents_are_rejected():
    env = make_env()
    env.reset(seed=0)
    actions = {a: np.zeros(2) for a in env.agents}
    with pytest.raises(ValueError, match="unknown agent id 'car_9'"):
        env.step({**actions, "car_9": np.zeros(2)})
    with pytest.raises(ValueError, match="missing"):
        env.step({"ego": np.zeros(2)})
    with pytest.raises(ValueError, match="unknown agent"):
        env.action_space("nobody")


def test_step_before_reset_and_after_end():
    env = make_env(episode_steps=1)
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    env.reset(seed=0)
    env.step({a: np.zeros(2) for a in env.agents})
    with pytest.raises(RuntimeError, match="episode ended"):
        env.step({"ego": np.zeros(2)})


def test_out_of_bounds_actions_clip_or_raise():
    env = make_env(clip_actions=False)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="out of bounds"):
        env.step({a: np.array([9.0, 0.0]) for a in env.agents})
    env = make_env()
    env.reset(seed=0)
    env.step({a: np.array([9.0, 5.0]) for a in env.agents})
    np.testing.assert_array_equal(env.scene.last_action[0], [5.0, 1.0])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_agents": 0}, "max_agents"),
        ({"episode_steps": 0}, "episode_steps"),
        ({"terminate_on_collision": "sometimes"}, "terminate_on_collision"),
        ({"terminate_on_offroad": ("ego", "agent_99")}, "unknown agents"),
    ],
)
def test_invalid_config_values(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EnvConfig(**kwargs)


def test_invalid_constructor_arguments():
    with pytest.raises(ValueError, match="render_mode"):
        riskflow_env.parallel_env(render_mode="vr")
    with pytest.raises(TypeError, match="config"):
        riskflow_env.parallel_env(config={"max_agents": 3})
    with pytest.raises(TypeError, match="scenarios"):
        riskflow_env.parallel_env(scenarios=42)
    env = make_env()
    with pytest.raises(TypeError, match="Scenario"):
        env.reset(options={"scenario": "highway"})


def test_ego_collision_terminates_and_vehicle_stays_as_obstacle():
    env = make_env(terminate_on_collision="all", end_with_ego=False)
    env.reset(seed=0)
    scene = env.scene
    # Teleport agent_1 onto the ego: both collide at the next step and terminate.
    history = scene.history.copy()
    history[1, -1, :2] = history[0, -1, :2]
    env._scene = scene.replace(history=history)
    _, _, terminations, _, infos = env.step({a: np.zeros(2) for a in env.agents})
    assert terminations["ego"] and terminations["agent_1"]
    assert "agent_1" in infos["ego"]["collided_with"]
    assert "ego" not in env.agents and env.scene.present[0] and not env.scene.active[0]
    position = env.scene.current[0].copy()
    env.step({a: np.zeros(2) for a in env.agents})
    np.testing.assert_array_equal(env.scene.current[0, :2], position[:2])


def test_aec_view_runs():
    aec = riskflow_env.env(config=EnvConfig(max_agents=4, episode_steps=3))
    aec.reset(seed=0)
    for _agent in aec.agent_iter(max_iter=20):
        _, _, termination, truncation, _ = aec.last()
        aec.step(None if termination or truncation else np.zeros(2, dtype=np.float32))
