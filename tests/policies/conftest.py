"""Fixtures of the policy tests: tiny random generators and a straight road.

``tiny_meanflow`` / ``tiny_denoiser`` are randomly initialised and perturbed (the
adaLN-Zero head starts as ``u = 0``), so plans depend on the noise and on the scene;
``road_view()`` is the first view of six cars at 12 m/s on a 12 m wide road;
``closed_loop(policy, n)`` runs it for ``n`` steps with the ego holding its speed;
``tiny_config``, ``normalizer`` and ``make_model`` serve the generator tests;
``scenarionet_toy`` is a 4-scene ScenarioNet dataset folder (the user cache redirected).
"""

from __future__ import annotations

import contextlib
import re

import pytest
import torch

from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from riskflow_env.user_cache import CACHE_ENV
from tests.policies.straight_road import (
    TINY_MODEL,
    TINY_NORMALIZER,
    perturbed_generator,
    road_env,
    run_closed_loop,
)
from tests.riskflow_env.scenarios.scenarionet_datasets import toy_descriptions, write_dataset


@pytest.fixture(scope="session")
def tiny_meanflow() -> RiskFlowGenerator:
    """A tiny random MeanFlow generator (frozen, eval mode)."""
    return perturbed_generator(1)


@pytest.fixture(scope="session")
def tiny_denoiser():
    """A tiny random diffusion denoiser (``K = 100`` levels, v-prediction)."""
    from policies.baselines.diffusion.model import DiffusionDenoiser

    return DiffusionDenoiser(perturbed_generator(2))


@pytest.fixture(scope="session")
def tiny_normalizer() -> ActionNormalizer:
    return TINY_NORMALIZER


@pytest.fixture
def road_view():
    """``road_view()`` -> ``(env, view)`` at the first step of the road scenario."""

    def make():
        env = road_env(seed=0)
        return env, env.view()

    return make


@pytest.fixture
def closed_loop():
    """``closed_loop(policy, steps)`` -> ``(env, emitted actions per step)``."""

    return run_closed_loop


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


@pytest.fixture
def refused(capsys):
    """``with refused(pattern): main(...)``: the command exits with status 2 and its one
    error line on stderr matches ``pattern`` (a regular expression)."""

    @contextlib.contextmanager
    def check(pattern: str):
        with pytest.raises(SystemExit) as exit_info:
            yield
        assert exit_info.value.code == 2
        error = capsys.readouterr().err
        assert re.search(pattern, error), error

    return check
