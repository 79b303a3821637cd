"""Batched stepping: the same numbers as the env, scene by scene, in numpy and torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import riskflow_env
from riskflow_env import batched, simulator
from riskflow_env.config import EnvConfig
from riskflow_env.maps import from_highway_env
from riskflow_env.scenarios import place_traffic
from riskflow_env.state import SceneState

SLOTS = 10
CONFIG = EnvConfig(
    max_agents=SLOTS,
    episode_steps=25,
    terminate_on_collision="all",
    terminate_on_offroad="all",
    end_with_ego=False,
)


def scenes(family: str = "merge", count: int = 3, seed: int = 0):
    drivable_map = from_highway_env(family)
    rng = np.random.default_rng(seed)
    return [place_traffic(drivable_map, SLOTS - 2 * (k % 2), rng) for k in range(count)]


def test_batch_matches_env_scene_by_scene():
    scenarios = scenes()
    drivable_map = scenarios[0].map
    state = batched.reset_batch(scenarios, SLOTS)
    envs = [riskflow_env.parallel_env(config=CONFIG, scenarios=s) for s in scenarios]
    for env, scenario in zip(envs, scenarios, strict=True):
        env.reset(seed=0, options={"scenario": scenario})
    rng = np.random.default_rng(1)
    for _ in range(CONFIG.episode_steps):
        actions = rng.uniform([-8.0, -1.2], [6.0, 1.2], (len(scenarios), SLOTS, 2))
        state, report = batched.step_batch(state, actions, drivable_map, CONFIG)
        for b, env in enumerate(envs):
            if not env.agents:
                continue
            step = env.step({agent: actions[b, env._slot[agent]] for agent in env.agents})
            observations, rewards, terminations, truncations, infos = step
            for agent in observations:
                slot = env._slot[agent]
                np.testing.assert_array_equal(observations[agent], report.observations[b, slot])
                assert rewards[agent] == report.rewards[b, slot]
                assert terminations[agent] == report.terminated[b, slot]
                assert truncations[agent] == report.truncated[b, slot]
                assert infos[agent]["reward_terms"]["risk"] == report.reward_terms["risk"][b, slot]
            np.testing.assert_array_equal(env.scene.current, state.current[b])
            np.testing.assert_array_equal(env.scene.active, state.active[b])
    assert not state.active.any()  # every agent was truncated at the end


def test_torch_matches_numpy_and_observations_optional():
    scenarios = scenes("highway", count=2)
    drivable_map = scenarios[0].map
    state = batched.reset_batch(scenarios, SLOTS)
    tensors = state.convert(torch.as_tensor)
    rng = np.random.default_rng(2)
    for _ in range(5):
        actions = rng.uniform([-3.0, -0.3], [2.0, 0.3], (2, SLOTS, 2))
        state, report = batched.step_batch(state, actions, drivable_map, CONFIG)
        tensors, torch_report = batched.step_batch(
            tensors, torch.as_tensor(actions), drivable_map, CONFIG
        )
        # numpy and torch kernels round differently (a few ulps of float64 per op, compounded
        # over 5 steps): values of at most a few hundred m stay within 1e-9 of each other.
        close = {"rtol": 1e-12, "atol": 1e-9}
        np.testing.assert_allclose(torch_report.observations.numpy(), report.observations, **close)
        np.testing.assert_allclose(torch_report.rewards.numpy(), report.rewards, **close)
        np.testing.assert_allclose(tensors.current.numpy(), state.current, **close)
    _, full = batched.step_batch(state, actions, drivable_map, CONFIG)
    _, bare = batched.step_batch(state, actions, drivable_map, CONFIG, observations=False)
    assert bare.observations is None and bare.evaluation.pair_features is None
    # without observations only the risk channel is computed: the same numbers
    np.testing.assert_array_equal(bare.rewards, full.rewards)
    np.testing.assert_array_equal(bare.reward_terms["risk"], full.reward_terms["risk"])


def test_float32_batch_stays_float32_near_float64():
    scenarios = scenes("highway", count=2)
    drivable_map = scenarios[0].map
    state = batched.reset_batch(scenarios, SLOTS)

    def single(array):
        return array.astype(np.float32) if array.dtype == np.float64 else array

    narrow = state.convert(single)
    rng = np.random.default_rng(3)
    for _ in range(10):
        actions = rng.uniform([-3.0, -0.3], [2.0, 0.3], (2, SLOTS, 2))
        state, report = batched.step_batch(state, actions, drivable_map, CONFIG)
        narrow, narrow_report = batched.step_batch(
            narrow, actions.astype(np.float32), drivable_map, CONFIG
        )
    assert narrow.current.dtype == np.float32
    assert narrow_report.observations.dtype == np.float32
    # float32 rounding (~1e-7 relative) on positions of a few hundred m, over 10 steps
    np.testing.assert_allclose(narrow.current, state.current, rtol=0, atol=1e-2)
    np.testing.assert_array_equal(narrow.active, state.active)


def test_errors():
    scenarios = scenes("highway", count=1) + scenes("merge", count=1)
    with pytest.raises(ValueError, match="share one DrivableMap"):
        batched.reset_batch(scenarios, SLOTS)
    state = batched.reset_batch(scenarios[:1], SLOTS)
    with pytest.raises(ValueError, match=r"\(B, A, 2\)"):
        batched.step_batch(state, np.zeros((1, SLOTS)), scenarios[0].map, CONFIG)
    with pytest.raises(ValueError, match="actions must hold real numbers, got dtype bool"):
        batched.step_batch(state, np.zeros((1, SLOTS, 2), bool), scenarios[0].map, CONFIG)
    with pytest.raises(ValueError, match="must be a batch"):
        batched.step_batch(env_state(scenarios[0]), np.zeros((SLOTS, 2)), scenarios[0].map, CONFIG)
    with pytest.raises(ValueError, match="history must have shape"):
        SceneState(
            history=np.zeros((SLOTS, 4)),
            history_valid=np.ones((SLOTS, 1), bool),
            last_action=np.zeros((SLOTS, 2)),
            length=np.ones(SLOTS),
            width=np.ones(SLOTS),
            present=np.ones(SLOTS, bool),
            active=np.ones(SLOTS, bool),
        )
    with pytest.raises(ValueError, match="at least one"):
        batched.reset_batch([], SLOTS)


def env_state(scenario):
    return simulator.reset(scenario, SLOTS)


def test_a_batch_of_one_is_the_env_transition_with_its_history():
    """The env's state (31-step history) and a stacked batch of it step alike."""
    scenario = scenes(count=1)[0]
    single = env_state(scenario)
    batch = SceneState.stack([single])
    actions = np.random.default_rng(3).uniform(-1.0, 1.0, (SLOTS, 2))
    single, report = simulator.transition(single, actions, scenario.map, CONFIG)
    batch, batch_report = simulator.transition(batch, actions[None], scenario.map, CONFIG)
    np.testing.assert_array_equal(batch.history[0], single.history)
    np.testing.assert_array_equal(batch.history_valid[0], single.history_valid)
    np.testing.assert_array_equal(batch_report.observations[0], report.observations)
    np.testing.assert_array_equal(batch_report.terminated[0], report.terminated)
    assert batch.batch_shape == (1,) and single.batch_shape == ()
