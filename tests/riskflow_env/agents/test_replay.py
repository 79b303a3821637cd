"""ReplayPolicy: reproduces logged trajectories in the env; log ends; open-loop mode."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.agents.replay import ReplayPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import HighwayTrafficSource, Scenario
from riskflow_env.view import ScenePolicy
from tests.samples import SCENARIONET_DIR

CONFIG = EnvConfig(terminate_on_collision="none", terminate_on_offroad="none")
DATA_DIR = SCENARIONET_DIR
SAMPLE = DATA_DIR / "sd_nuscenes_v1.0-mini_scene-0061.pkl"


def replay_errors(env, policy, scenario=None, seed=0):
    """(steps, slots) position errors [m] against the reference, NaN where it is invalid."""
    env.reset(seed=seed, options={"scenario": scenario} if scenario is not None else None)
    policy.reset(env.view())
    scenario, rows = env.scenario, env.view().scenario_rows.copy()
    has = rows >= 0
    now = scenario.current_index
    errors = []
    while env.agents and now + len(errors) + 1 < scenario.states.shape[1]:
        env.step(policy.act(env.view()))
        step = now + len(errors) + 1
        reference = scenario.states[rows[has], step, :2]
        error = np.linalg.norm(env.scene.current[has, :2] - reference, axis=-1)
        errors.append(np.where(scenario.valid[rows[has], step], error, np.nan))
    return np.array(errors)


def test_protocol():
    assert isinstance(ReplayPolicy(), ScenePolicy)
    with pytest.raises(ValueError, match="mode"):
        ReplayPolicy(mode="closed")


def test_replay_reproduces_synthetic_traffic():
    env = riskflow_env.parallel_env(config=CONFIG, scenarios=HighwayTrafficSource())
    policy = ReplayPolicy(controlled="all")
    errors = [replay_errors(env, policy, seed=seed) for seed in range(7)]
    assert all(len(e) == 100 for e in errors)
    ade = np.nanmean(np.concatenate([e.ravel() for e in errors]))
    assert ade < 0.1, f"replay ADE {ade:.4f} m"


@pytest.mark.skipif(
    not SAMPLE.is_file(),
    reason=(
        f"ScenarioNet sample {SAMPLE.name} not in {DATA_DIR.resolve()}: the nuScenes samples"
        " are not shipped; set RISKFLOW_SCENARIONET_DIR to their folder (README, Real data)"
    ),
)
def test_replay_reproduces_a_scenarionet_sample():
    from riskflow_env.scenarios.scenarionet import load_scenarionet

    scenario = load_scenarionet(SAMPLE)
    env = riskflow_env.parallel_env(config=CONFIG, scenarios=scenario)
    errors = replay_errors(env, ReplayPolicy(controlled="all"), scenario)
    assert len(errors) == 100 and np.nanmean(errors) < 0.1, f"ADE {np.nanmean(errors):.4f} m"


def _straight_scene(valid_steps: int) -> Scenario:
    """Ego and one car at 10 m/s on a straight lane; the car's log ends early."""
    drivable_map = from_lanes([Lane(np.array([[-100.0, 0.0], [400.0, 0.0]]), 4.0, "lane")])
    steps = 131
    x = 10.0 * 0.1 * (np.arange(steps) - 30)
    states = np.zeros((2, steps, 4))
    states[0, :, 0], states[1, :, 0] = x, x + 30.0
    states[:, :, 2] = 10.0
    valid = np.ones((2, steps), dtype=bool)
    valid[1, valid_steps:] = False
    return Scenario(drivable_map, states, valid, np.full(2, 4.5), np.full(2, 2.0))


def test_log_end_holds_speed():
    scenario = _straight_scene(valid_steps=40)
    env = riskflow_env.parallel_env(config=CONFIG, scenarios=scenario)
    env.reset(options={"scenario": scenario})
    policy = ReplayPolicy(controlled="all")
    policy.reset(env.view())
    for _ in range(20):
        actions = policy.act(env.view())
        env.step(actions)
    np.testing.assert_allclose(actions["agent_1"], 0.0)
    assert env.scene.current[1, 2] == pytest.approx(10.0)


def test_open_loop_reproduces_speeds_and_headings():
    env = riskflow_env.parallel_env(config=CONFIG, scenarios=HighwayTrafficSource())
    env.reset(seed=3)
    policy = ReplayPolicy(controlled="all", mode="open_loop")
    policy.reset(env.view())
    scenario, rows = env.scenario, env.view().scenario_rows
    has = rows >= 0
    for step in range(1, 21):
        env.step(policy.act(env.view()))
        reference = scenario.states[rows[has], scenario.current_index + step]
        ok = scenario.valid[rows[has], scenario.current_index + step]
        np.testing.assert_allclose(env.scene.current[has][ok, 2:], reference[ok, 2:], atol=1e-9)
