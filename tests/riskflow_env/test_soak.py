"""Random-action soak of the env: no crash, no NaN, nothing outside its bounds (issue 19).

Random actions drawn from 1.5 x the action bounds (the env clips them: the default
``clip_actions=True``), random scenes from the shipped bank, episodes ended the default
way (the ego's collision or off-road, or truncation), then a reset. After every reset
and every step:

* every observation, reward, ``info`` number and ``env.state()`` entry is finite,
  observations have the space's shape and dtype;
* every present vehicle's state (x, y, v, psi) is finite, its speed within the dynamics
  bounds, its heading within +-1e4 rad;
* every live vehicle is inside the map's raster, or flagged off-road
  (``info["offroad_fraction"] > 0``), or beyond it on a road that leaves the map (the map
  continues its border pixels outward: the border point the vehicle faces is drivable).

10,000 steps run in ``python -m pytest -m reliability``; 100,000 steps are a ``slow`` test
only (``python -m pytest -m slow``), so that the reliability suite does not take minutes.
"""

from __future__ import annotations

import numpy as np
import pytest

import riskflow_env
from riskflow_env.config import EnvConfig

HEADING_LIMIT = 1e4  # [rad] Scenario's bound on headings


def soak(steps: int, seed: int = 0) -> dict[str, int]:
    """Run ``steps`` random-action steps; assert the checks of the module docstring.
    Returns counts (steps, resets, off-road flags, vehicles outside the raster)."""
    config = EnvConfig(max_agents=16)
    env = riskflow_env.parallel_env(config=config)
    rng = np.random.default_rng(seed)
    low, high = env.action_space("ego").low, env.action_space("ego").high
    centre, half = (low + high) / 2, (high - low) / 2
    shape, dtype = env.observation_space("ego").shape, env.observation_space("ego").dtype
    bounds = config.dynamics
    counts = {"steps": 0, "resets": 0, "offroad": 0, "outside_raster": 0}
    observations, infos = env.reset(seed=seed)
    rewards: dict[str, float] = {}
    counts["resets"] += 1
    while True:
        _check(env, observations, rewards, infos, shape, dtype, bounds, counts)
        if counts["steps"] == steps:
            return counts
        if not env.agents:
            observations, infos = env.reset()
            rewards = {}
            counts["resets"] += 1
            continue
        noise = rng.uniform(-1.5, 1.5, size=(len(env.agents), 2))
        actions = dict(zip(env.agents, centre + half * noise, strict=True))
        observations, rewards, _, _, infos = env.step(actions)
        counts["steps"] += 1


def _check(env, observations, rewards, infos, shape, dtype, bounds, counts) -> None:
    where = f"after {counts['steps']} steps, {counts['resets']} resets ({env.scenario.name})"
    for agent, observation in observations.items():
        assert observation.shape == shape and observation.dtype == dtype, (agent, where)
        assert np.isfinite(observation).all(), f"non-finite observation of {agent} {where}"
    assert np.isfinite(list(rewards.values())).all(), f"non-finite reward {where}"
    numbers = [value for info in infos.values() for value in _numbers(info)]
    assert np.isfinite(numbers).all(), f"non-finite info {where}"
    assert np.isfinite(env.state()).all(), f"non-finite env.state() {where}"
    scene = env.scene
    current = scene.history[scene.present, -1]  # (N, 4) x, y, v, psi
    assert np.isfinite(current).all(), f"non-finite vehicle state {where}"
    speed = current[:, 2]
    assert np.all((speed >= bounds.speed_min) & (speed <= bounds.speed_max)), where
    assert np.all(np.abs(current[:, 3]) <= HEADING_LIMIT), f"heading out of range {where}"
    x0, y0, x1, y1 = env.scenario.map.bounds
    for agent, info in infos.items():
        x, y = scene.history[env.possible_agents.index(agent), -1, :2]
        flagged = info["offroad_fraction"] > 0
        counts["offroad"] += flagged
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            counts["outside_raster"] += 1
            border = np.clip([x, y], [x0, y0], [x1, y1])
            on_road = env.scenario.map.is_drivable(border)
            assert flagged or on_road, f"{agent} at ({x:.1f}, {y:.1f}) off the map's roads {where}"


def _numbers(info: dict) -> list[float]:
    values = []
    for value in info.values():
        if isinstance(value, dict):
            values.extend(_numbers(value))
        elif isinstance(value, (bool, int, float, np.number)):
            values.append(float(value))
    return values


@pytest.mark.reliability
def test_soak_10k_random_steps():
    counts = soak(10_000, seed=0)
    assert counts["steps"] == 10_000 and counts["resets"] > 1
    assert counts["offroad"] > 0  # random driving leaves the road: the checks saw it


@pytest.mark.slow  # not `reliability`: `-m reliability` replaces the default `-m 'not slow'`
def test_soak_100k_random_steps():
    counts = soak(100_000, seed=1)
    assert counts["steps"] == 100_000 and counts["resets"] > 10
