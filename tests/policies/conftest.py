"""Fixtures of the policy tests: tiny random generators and a straight road.

``tiny_meanflow`` / ``tiny_denoiser`` are randomly initialised and perturbed (the
adaLN-Zero head starts as ``u = 0``), so plans depend on the noise and on the scene;
``road_view()`` is the first view of six cars at 12 m/s on a 12 m wide road;
``closed_loop(policy, n)`` runs it for ``n`` steps with the ego holding its speed;
``tiny_config``, ``normalizer`` and ``make_model`` serve the generator tests;
``scenarionet_toy`` is a 4-scene ScenarioNet dataset folder (the user cache redirected).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import riskflow_env
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from riskflow_env.config import EnvConfig
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import Scenario
from riskflow_env.user_cache import CACHE_ENV
from tests.riskflow_env.scenarios.scenarionet_datasets import toy_descriptions, write_dataset

TINY_MODEL = ModelConfig(
    encoder_dim=16, head_dim=32, context_dim=32, edge_dim=8, num_heads=2, encoder_layers=1,
    head_layers=1, map_widths=(4, 8), time_frequencies=8,
)  # fmt: skip
TINY_NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(0.5, 0.02))
ROAD_ENV = EnvConfig(
    max_agents=8, episode_steps=20, terminate_on_collision="all", terminate_on_offroad="none"
)
# (x [m], lane y [m]) at the current step, all at 12 m/s along +x; slot order = row order.
ROAD_START = [(0.0, 0.0), (18.0, 3.5), (-12.0, -3.5), (30.0, -3.5), (-25.0, 3.5), (45.0, 0.0)]


def _perturbed(seed: int) -> RiskFlowGenerator:
    torch.manual_seed(seed)
    network = RiskFlowGenerator(TINY_MODEL)
    noise = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in network.parameters():
            param.add_(0.2 * torch.randn(param.shape, generator=noise))
    return network.eval().requires_grad_(False)


@pytest.fixture(scope="session")
def tiny_meanflow() -> RiskFlowGenerator:
    """A tiny random MeanFlow generator (frozen, eval mode)."""
    return _perturbed(1)


@pytest.fixture(scope="session")
def tiny_denoiser():
    """A tiny random diffusion denoiser (``K = 100`` levels, v-prediction)."""
    from policies.baselines.diffusion.model import DiffusionDenoiser

    return DiffusionDenoiser(_perturbed(2))


@pytest.fixture(scope="session")
def tiny_normalizer() -> ActionNormalizer:
    return TINY_NORMALIZER


def make_road_scenario() -> Scenario:
    road = from_lanes([Lane(np.array([[-150.0, 0.0], [500.0, 0.0]]), 12.0, "road")])
    steps, num = 31 + 60, len(ROAD_START)
    time = 0.1 * (np.arange(steps) - 30)
    states = np.zeros((num, steps, 4))
    for row, (x, y) in enumerate(ROAD_START):
        states[row, :, 0], states[row, :, 1], states[row, :, 2] = x + 12.0 * time, y, 12.0
    valid = np.ones(states.shape[:2], dtype=bool)
    return Scenario(road, states, valid, np.full(num, 4.5), np.full(num, 2.0), name="road")


@pytest.fixture
def road_view():
    """``road_view()`` -> ``(env, view)`` at the first step of the road scenario."""

    def make():
        scenario = make_road_scenario()
        env = riskflow_env.parallel_env(config=ROAD_ENV, scenarios=scenario)
        env.reset(seed=0, options={"scenario": scenario})
        return env, env.view()

    return make


@pytest.fixture
def closed_loop():
    """``closed_loop(policy, steps)`` -> ``(env, emitted actions per step)``."""

    def run(policy, steps: int):
        scenario = make_road_scenario()
        env = riskflow_env.parallel_env(config=ROAD_ENV, scenarios=scenario)
        env.reset(seed=0, options={"scenario": scenario})
        policy.reset(env.view())
        emitted = []
        for _ in range(steps):
            if not env.agents:
                break
            actions = policy.act(env.view())
            emitted.append(actions)
            env.step({**actions, "ego": np.zeros(2)} if "ego" in env.agents else actions)
        return env, emitted

    return run


# Generator tests: tiny configs, rough action statistics, perturbed models.


@pytest.fixture
def tiny_config() -> ModelConfig:
    return TINY_MODEL


@pytest.fixture
def normalizer() -> ActionNormalizer:
    """Rough statistics of ``synthetic_batch`` actions (accel [m/s^2], yaw rate [rad/s])."""
    return ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.03))


def randomized(model: RiskFlowGenerator, seed: int, scale: float = 0.2) -> RiskFlowGenerator:
    """``model`` with noise added to every parameter.

    The adaLN-Zero head starts as ``u = 0``; derivative tests need a non-trivial ``u``.
    """
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in model.parameters():
            noise = torch.randn(param.shape, generator=gen, dtype=torch.float64)
            param.add_(scale * noise.to(param.dtype))
    return model


@pytest.fixture
def make_model():
    """``make_model(config, seed, dtype=..., randomize=True)`` -> a (perturbed) generator."""

    def make(
        config: ModelConfig = TINY_MODEL,
        seed: int = 0,
        dtype: torch.dtype = torch.float32,
        randomize: bool = True,
    ) -> RiskFlowGenerator:
        torch.manual_seed(seed)
        model = RiskFlowGenerator(config).to(dtype)
        return randomized(model, seed) if randomize else model

    return make


@pytest.fixture
def scenarionet_toy(tmp_path, monkeypatch):
    """``tmp_path/sd_toy``: 4 nuScenes-form scenes as ScenarioNet's converter writes them;
    the user cache (converted maps) in ``tmp_path/user-cache``."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    folder = tmp_path / "sd_toy"
    write_dataset(folder, toy_descriptions(4))
    return folder
