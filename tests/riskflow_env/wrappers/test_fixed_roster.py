"""``FixedRosterEnv``: PettingZoo's checks over its configurations, padded and masked slots,
flat infos, one episode end for the whole roster, ignored actions, the scene policy."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from pettingzoo.test import max_cycles_test
from pettingzoo.utils.conversions import parallel_to_aec

from riskflow_env.agents import ConstantVelocityPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.rewards import REWARD_TERMS
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import FixedRosterEnv
from tests.pettingzoo_checks import pettingzoo_checks

SLOTS = 5
# Scenes with 2-4 vehicles in 5 slots: at least one slot is always padded.
FEW = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(2, 4)))

CONFIGS = {
    "all-slots": {},
    "adversaries": {"roster": [f"agent_{i}" for i in range(1, SLOTS)]},
    "ego-only": {"roster": ["ego"]},
    "individual-ends": {
        "config": {"terminate_on_collision": "all", "terminate_on_offroad": "all"},
        "ignore_inactive_actions": True,
    },
}


def make_env(name: str = "all-slots", episode_steps: int = 12, **overrides) -> FixedRosterEnv:
    options = {**CONFIGS[name], **overrides}
    config = EnvConfig(max_agents=SLOTS, episode_steps=episode_steps, **options.pop("config", {}))
    return FixedRosterEnv(config=config, scenarios=FEW, **options)


def sample_actions(env: FixedRosterEnv) -> dict[str, np.ndarray]:
    return {agent: env.action_space(agent).sample() for agent in env.agents}


def zero_actions(env: FixedRosterEnv) -> dict[str, np.ndarray]:
    """Keep speed and heading: nobody crashes in a short episode."""
    return {agent: np.zeros(2, np.float32) for agent in env.agents}


def run_episode(env: FixedRosterEnv, seed: int, actions=sample_actions) -> list[tuple]:
    observations, infos = env.reset(seed=seed)
    for agent in env.possible_agents:
        env.action_space(agent).seed(seed)
    steps = [(observations, infos)]
    while env.agents:
        steps.append(env.step(actions(env)))
    return steps


@pytest.mark.parametrize("name", CONFIGS)
def test_pettingzoo_api_and_seed_tests(name):
    pettingzoo_checks(lambda: make_env(name))


@pytest.mark.parametrize("name", ["all-slots", "adversaries", "ego-only"])
def test_max_cycles(name):
    """PettingZoo's check resets unseeded and steps random actions: nobody terminates here
    (an early crash would end the episode before ``max_cycles``). Padded slots count as
    live, so scenes need not fill every slot (the default env needs full scenes)."""
    quiet = {"terminate_on_collision": "none", "terminate_on_offroad": "none"}

    def parallel_env(max_cycles: int) -> FixedRosterEnv:
        return make_env(name, episode_steps=max_cycles, config=quiet)

    module = SimpleNamespace(
        parallel_env=parallel_env,
        env=lambda max_cycles: parallel_to_aec(parallel_env(max_cycles)),
    )
    max_cycles_test(module)


def test_every_roster_agent_is_live_until_the_episode_ends_together():
    env = make_env(episode_steps=7)
    steps = run_episode(env, seed=3, actions=zero_actions)
    assert len(steps) == 8  # reset + 7 steps
    for _, _, terminations, truncations, _ in steps[1:-1]:
        assert not any(terminations.values()) and not any(truncations.values())
    _, _, terminations, truncations, _ = steps[-1]
    assert all(truncations.values()) and not any(terminations.values())  # the time limit
    assert env.agents == []
    with pytest.raises(RuntimeError, match="after the episode ended"):
        env.step({})


def test_padded_slots_observe_zeros_and_are_masked():
    env = make_env()
    observations, infos = env.reset(seed=0)
    live = np.array([infos[agent]["live"] for agent in env.possible_agents])
    assert live[0] and not live.all()  # the ego, and at least one empty slot
    np.testing.assert_array_equal(live, env.live_mask())
    observations, rewards, _, _, infos = env.step(sample_actions(env))
    for agent in env.possible_agents:
        info = infos[agent]
        assert set(info) == {
            "live",
            "collided",
            "collided_with",
            "offroad_fraction",
            "sdf_depth",
            "reward_terms",
        }
        assert info["collided_with"].shape == (SLOTS,) and info["reward_terms"].shape == (5,)
        assert observations[agent].shape == env.observation_space(agent).shape
        if not info["live"]:
            assert not observations[agent].any() and rewards[agent] == 0.0
            assert not info["reward_terms"].any()
        else:
            assert observations[agent].any()
            # the flat reward terms are the env's terms, and sum to the reward
            assert np.isclose(info["reward_terms"].sum(), rewards[agent], atol=1e-5)


def test_flat_infos_match_the_parallel_env():
    """Same seed, same actions: the flat infos carry the parallel env's values."""
    wrapped = make_env()
    bare = make_env().env
    observations, _ = wrapped.reset(seed=4)
    bare.reset(seed=4)
    actions = {agent: np.array([1.0, 0.3]) for agent in bare.agents}
    wrapped_out = wrapped.step(actions)
    bare_out = bare.step(actions)
    for agent, info in bare_out[4].items():
        flat = wrapped_out[4][agent]
        assert flat["live"] and flat["collided"] == info["collided"]
        assert flat["offroad_fraction"] == info["offroad_fraction"]
        assert flat["sdf_depth"] == info["sdf_depth"]
        expected = [info["reward_terms"][name] for name in REWARD_TERMS]
        np.testing.assert_allclose(flat["reward_terms"], expected, rtol=1e-6)
        partners = [bare.possible_agents[i] for i in np.flatnonzero(flat["collided_with"])]
        assert partners == info["collided_with"]
        np.testing.assert_array_equal(wrapped_out[0][agent], bare_out[0][agent])


def test_a_crash_ends_the_episode_as_a_termination_for_everyone():
    env = make_env(episode_steps=60)
    env.reset(seed=1)
    steps = 0
    while env.agents:  # full throttle, hard left: the ego leaves the road and terminates
        _, _, terminations, truncations, _ = env.step(
            {agent: np.array([5.0, 1.0]) for agent in env.agents}
        )
        steps += 1
    assert steps < 60
    assert all(terminations.values()) and not any(truncations.values())


def test_vehicles_done_early_become_padded_slots():
    env = make_env("individual-ends", episode_steps=40, config={"end_with_ego": False})
    env.reset(seed=2)
    rng = np.random.default_rng(0)
    seen_padded_after_live = False
    was_live = env.live_mask()
    while env.agents:
        actions = {agent: np.array([5.0, rng.choice([-1.0, 1.0])]) for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        live = np.array([infos[agent]["live"] for agent in env.possible_agents])
        if env.agents:
            assert not any(terminations.values()) and not any(truncations.values())
        if (was_live & ~live).any():
            seen_padded_after_live = True
        was_live = live
    assert seen_padded_after_live


def test_actions_of_padded_agents_are_ignored_or_rejected():
    env = make_env()
    env.reset(seed=0)
    padded = [
        agent for agent, live in zip(env.possible_agents, env.live_mask(), strict=True) if not live
    ]
    live = [agent for agent in env.possible_agents if agent not in padded]
    reference = make_env()
    reference.reset(seed=0)
    with_padded = env.step({agent: np.array([0.5, 0.0]) for agent in env.possible_agents})
    without = reference.step({agent: np.array([0.5, 0.0]) for agent in live})
    for agent in env.possible_agents:
        np.testing.assert_array_equal(with_padded[0][agent], without[0][agent])

    strict = make_env(ignore_inactive_actions=False)
    strict.reset(seed=0)
    with pytest.raises(ValueError, match="not live"):
        strict.step({agent: np.array([0.5, 0.0]) for agent in strict.possible_agents})
    with pytest.raises(ValueError, match="missing for live agents"):
        env.step({})


def test_same_seed_same_rollout_bit_for_bit_with_a_scene_policy():
    first = run_episode(make_env("adversaries"), seed=5, actions=sample_actions)
    second = run_episode(make_env("adversaries"), seed=5, actions=sample_actions)
    assert len(first) == len(second)
    for a, b in zip(first, second, strict=True):
        for agent in a[0]:
            np.testing.assert_array_equal(a[0][agent], b[0][agent])


def test_the_scene_policy_drives_the_slots_outside_the_roster():
    env = make_env("ego-only", policy=ConstantVelocityPolicy(controlled="others"))
    observations, _ = env.reset(seed=0)
    assert list(observations) == ["ego"] and env.possible_agents == ["ego"]
    before = env.env.view().current.copy()
    env.step({"ego": np.zeros(2)})
    after = env.env.view().current
    moving = env.env.scene.present[1:]
    assert np.all(after[1:][moving, 0] != before[1:][moving, 0])  # the others drove on


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"roster": ["agent_99"]}, ValueError, "roster has unknown agents"),
        ({"roster": "ego"}, TypeError, "roster must be a sequence"),
        ({"roster": []}, ValueError, "at least one agent"),
        ({"roster": ["ego", "ego"]}, ValueError, "each once"),
        ({"ignore_inactive_actions": "yes"}, TypeError, "ignore_inactive_actions must be a bool"),
        ({"roster": ["ego"], "policy": object()}, TypeError, "policy must be a ScenePolicy"),
    ],
)
def test_bad_arguments_name_the_argument(kwargs, error, message):
    with pytest.raises(error, match=message):
        FixedRosterEnv(config=EnvConfig(max_agents=SLOTS), scenarios=FEW, **kwargs)


def test_bad_actions_name_the_agent():
    env = make_env("adversaries")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="outside the roster"):
        env.step({"ego": np.zeros(2)})
    with pytest.raises(TypeError, match="actions must be a dict"):
        env.step([np.zeros(2)])
    with pytest.raises(ValueError, match="unknown agent"):
        env.observation_space("ego")
