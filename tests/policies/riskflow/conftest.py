"""Shared fixtures of the generator tests: tiny model configs and synthetic batches."""

from __future__ import annotations

import pytest
import torch

from policies.riskflow.config import ModelConfig
from policies.riskflow.data import ActionNormalizer
from policies.riskflow.generator import RiskFlowGenerator

TINY = ModelConfig(
    encoder_dim=16,
    head_dim=32,
    context_dim=32,
    edge_dim=8,
    num_heads=2,
    encoder_layers=1,
    head_layers=1,
    map_widths=(4, 8),
    time_frequencies=8,
)


@pytest.fixture
def tiny_config() -> ModelConfig:
    return TINY


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
        config: ModelConfig = TINY,
        seed: int = 0,
        dtype: torch.dtype = torch.float32,
        randomize: bool = True,
    ) -> RiskFlowGenerator:
        torch.manual_seed(seed)
        model = RiskFlowGenerator(config).to(dtype)
        return randomized(model, seed) if randomize else model

    return make
