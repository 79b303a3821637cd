"""The scenario bank shipped in ``riskflow_env/assets``: present, small, the env's default."""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.maps import FAMILIES
from riskflow_env.scenarios import ScenarioBank, load_scenario, shipped_bank
from riskflow_env.scenarios.io import ASSETS, list_scenarios

MAX_BANK_BYTES = 20 * 1024 * 1024


def test_bank_is_small_and_covers_the_families():
    size = sum(path.stat().st_size for path in ASSETS.parent.rglob("*") if path.is_file())
    assert size <= MAX_BANK_BYTES
    bank = shipped_bank("eval")
    assert isinstance(bank, ScenarioBank) and len(bank) >= 90
    assert {scene.family for scene in bank.scenarios} == set(FAMILIES)
    assert len(shipped_bank("train")) >= len(FAMILIES)
    eval_names = {scene.name for scene in bank.scenarios}
    assert not eval_names & {scene.name for scene in shipped_bank("train").scenarios}
    for scene in bank.scenarios:
        assert scene.history_steps == 31 and scene.future_steps >= 100
        assert scene.source == "highway-env-idm" and scene.valid[0].all()


def test_bank_is_cached_and_splits_are_checked():
    assert shipped_bank() is shipped_bank("eval")
    with pytest.raises(ValueError, match="split must be one of"):
        shipped_bank("test")


def test_parallel_env_defaults_to_the_eval_bank():
    env = riskflow_env.parallel_env(config=EnvConfig(max_agents=8))
    assert env.source is shipped_bank("eval")
    names = set()
    for seed in range(3):
        env.reset(seed=seed)
        names.add(env.scenario.name)
        assert any(env.scenario is scene for scene in shipped_bank("eval").scenarios)
    assert len(names) > 1
    env.close()


def test_env_runs_from_a_loaded_scenario():
    path = list_scenarios(ASSETS / "eval")[0]
    scenario = load_scenario(path)
    env = riskflow_env.parallel_env(config=EnvConfig(max_agents=8), scenarios=scenario)
    observations, _ = env.reset(seed=0)
    assert "ego" in observations and env.scenario is scenario
    now = scenario.current_index
    np.testing.assert_allclose(env.scene.current[0], scenario.states[0, now])
    for _ in range(5):
        if not env.agents:
            break
        env.step({agent: np.zeros(2) for agent in env.agents})
    env.close()


def test_shipped_tracks_follow_the_unicycle():
    """Logged actions rolled out from any logged state give back the logged positions
    (float32 storage: 1e-4 m over 5 s); the training targets are reachable."""
    from riskflow_env.dynamics import inverse, rollout

    for scene in shipped_bank("eval").scenarios[::7]:
        rows = scene.valid[:, 30:83].all(axis=1)
        states = scene.states[rows, 30:83]
        rolled = rollout(states[:, 0], inverse(states))
        np.testing.assert_allclose(rolled[..., :2], states[:, 1:, :2], atol=1e-3)
