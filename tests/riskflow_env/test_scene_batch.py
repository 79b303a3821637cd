"""SceneBatch: N scenes on their own maps, reset on their own, stepped in one transition,
follow the parallel env scene by scene."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.maps import from_highway_env
from riskflow_env.scenarios import place_traffic
from riskflow_env.scene_batch import SceneBatch

SLOTS = 8
CONFIG = EnvConfig(max_agents=SLOTS, episode_steps=12, end_with_ego=False)


@pytest.fixture(scope="module")
def scenarios():
    rng = np.random.default_rng(0)
    return [place_traffic(from_highway_env(family), SLOTS - k, rng) for k, family in
            enumerate(("merge", "roundabout", "highway"))]  # fmt: skip


def test_scenes_follow_the_env_through_a_lone_reset(scenarios):
    """Three scenes on three maps (one SDF lookup through a MapStack); scene 1 restarts at
    step 5, so the scenes end at different steps: each is the parallel env with its seed."""
    batch = SceneBatch(3, CONFIG, scenarios)
    envs = [riskflow_env.parallel_env(config=CONFIG, scenarios=scenarios) for _ in range(3)]
    observations, _ = batch.reset([4, 5, 6])
    for b, env in enumerate(envs):
        expected, _ = env.reset(seed=4 + b)
        for agent, row in expected.items():
            np.testing.assert_array_equal(observations[b][agent], row)
    assert len({id(view.map) for view in batch.views()}) > 1
    rng = np.random.default_rng(1)
    for step in range(16):
        if step == 5:
            fresh, _ = batch.reset_scenes([1], [None])
            expected, _ = envs[1].reset()
            np.testing.assert_array_equal(fresh[0]["ego"], expected["ego"])
        actions = rng.uniform([-8.0, -1.0], [5.0, 1.0], (3, SLOTS, 2))
        transition = batch.step(actions)
        for b, env in enumerate(envs):
            if not env.agents:
                assert not transition.terminated[b].any() and not transition.truncated[b].any()
                continue
            slots = [env.possible_agents.index(agent) for agent in env.agents]
            got = env.step(
                {agent: actions[b, s] for agent, s in zip(env.agents, slots, strict=True)}
            )
            rows, rewards, terminations, truncations, _ = got
            for agent, s in zip(rows, slots, strict=True):
                np.testing.assert_allclose(rows[agent], transition.observations[b, s], atol=1e-6)
                np.testing.assert_allclose(rewards[agent], transition.rewards[b, s], atol=1e-9)
                assert terminations[agent] == transition.terminated[b, s]
                assert truncations[agent] == transition.truncated[b, s]
            view = batch.views()[b]
            np.testing.assert_allclose(view.history, env.view().history, atol=1e-12)
            assert view.step == env.view().step
    assert batch.state.step[:, 0].tolist() == [16, 11, 16]


def test_bad_arguments(scenarios):
    with pytest.raises(ValueError, match="num_scenes"):
        SceneBatch(0, CONFIG, scenarios)
    batch = SceneBatch(2, CONFIG, scenarios)
    with pytest.raises(RuntimeError, match="reset"):
        batch.step(np.zeros((2, SLOTS, 2)))
    batch.reset([0, 1])
    with pytest.raises(ValueError, match=r"actions must have shape \(N, A, 2\)"):
        batch.step(np.zeros((3, SLOTS, 2)))
    with pytest.raises(ValueError, match="seeds"):
        batch.reset_scenes([0], [1, 2])
    with pytest.raises(ValueError, match="options must be one mapping or a list"):
        batch.reset([0, 1], [{"scenario": scenarios[0]}])


def test_each_scene_its_own_reset_options(scenarios):
    """A list of options: scene b starts from its own scenario (riskflow-eval's batches)."""
    batch = SceneBatch(3, CONFIG, scenarios)
    order = [scenarios[2], scenarios[0], scenarios[1]]
    batch.reset([0, 0, 0], [{"scenario": scenario} for scenario in order])
    assert [view.scenario for view in batch.views()] == order
