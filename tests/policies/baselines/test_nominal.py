"""NominalGenerator: RiskFlowAdversary(k=0) under its own name, bit for bit."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from policies.baselines.diffusion.sampling import OneCallSampler
from policies.baselines.nominal import NominalGenerator
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.view import ScenePolicy


def test_is_riskflow_k0_bit_for_bit_in_closed_loop(tiny_meanflow, tiny_normalizer, closed_loop):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    nominal = NominalGenerator(planning_interval=0.3, seed=4, **models)
    assert isinstance(nominal, ScenePolicy) and nominal.k == 0
    env, emitted = closed_loop(nominal, 8)
    assert nominal.cycles == 3 and not nominal.controllable.any()
    np.testing.assert_array_equal(nominal.plans, nominal.base_plans)
    reference_env, reference = closed_loop(
        RiskFlowAdversary(k=0, planning_interval=0.3, seed=4, **models), 8
    )
    np.testing.assert_array_equal(env.scene.history, reference_env.scene.history)
    for ours, theirs in zip(emitted, reference, strict=True):
        assert ours.keys() == theirs.keys()
        assert all(np.array_equal(ours[name], theirs[name]) for name in ours)


def test_diffusion_generator(tiny_denoiser, tiny_normalizer, closed_loop):
    nominal = NominalGenerator(
        generator=OneCallSampler(tiny_denoiser, 3), normalizer=tiny_normalizer, seed=1
    )
    closed_loop(nominal, 2)
    assert nominal.generator_kind == "diffusion"
    np.testing.assert_array_equal(nominal.plans, nominal.base_plans)


def test_shipped_checkpoint_with_the_harness_keywords():
    if not resources.files("policies").joinpath("checkpoints", "riskflow_default.pt").is_file():
        pytest.skip("no shipped checkpoint")
    nominal = NominalGenerator(planning_interval=0.5, seed=0, device="cpu")
    assert nominal.generator_kind == "meanflow" and nominal.overlay_prefix == "nominal"


def test_bad_options(tiny_meanflow, tiny_normalizer):
    with pytest.raises(ValueError, match="planning_interval"):
        NominalGenerator(
            planning_interval=-1.0, generator=tiny_meanflow, normalizer=tiny_normalizer
        )
    with pytest.raises(ValueError, match="normalizer"):
        NominalGenerator(generator=tiny_meanflow)
    with pytest.raises(ValueError, match="generator must be one of"):
        NominalGenerator(generator="gan")


def test_exported_from_the_packages():
    import policies
    import policies.baselines

    assert policies.NominalGenerator is policies.baselines.NominalGenerator is NominalGenerator
    assert policies.StriveAdversary is policies.baselines.StriveAdversary
    assert "StriveAdversary" in dir(policies)
    with pytest.raises(AttributeError, match="no attribute"):
        policies.NoSuchPolicy  # noqa: B018
