"""RiskFlowAdversary ablations: the diffusion generator as base plans, and the loss weights."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from policies.baselines.diffusion.sampling import OneCallSampler
from policies.learned.checkpoint import build_checkpoint, load_checkpoint, save_checkpoint
from policies.learned.sampler import sample
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.pipeline import stages
from policies.riskflow.base_generator import checkpoint_kind, load_base_generator
from policies.riskflow.policy import RiskFlowAdversary


def planned(policy, road_view):
    _, view = road_view()
    policy.reset(view)
    policy.plan(view)
    return policy, view


def test_diffusion_base_plans_are_the_ddim_chain_and_guidance_moves_only_a_c(
    tiny_denoiser, tiny_normalizer, road_view
):
    sampler = OneCallSampler(tiny_denoiser, 3)
    # threads=None: the policy plans with the thread count of the reference call below
    # (matrix products round differently with another count); blending first passes the
    # base plans through the action normalisation and back (equal to float rounding), so
    # the bit-for-bit comparison blends after planning.
    kwargs = {"generator": sampler, "normalizer": tiny_normalizer, "seed": 2, "threads": None}

    def after(**options):  # blending after planning: the cycle without its stitch stage
        policy = RiskFlowAdversary(**kwargs, **options)
        policy.stages = tuple(stage for stage in policy.stages if stage is not stages.stitch)
        return policy

    unguided, view = planned(after(k=0), road_view)
    assert unguided.generator_kind == "diffusion"
    window = window_from_view(view, unguided.window_config)
    batch = collate_windows([window])
    actions, _ = sample(sampler, batch, unguided.noise[None], tiny_normalizer)
    np.testing.assert_array_equal(unguided.plan_actions[window.agent_index], actions[0].numpy())
    first, _ = planned(RiskFlowAdversary(k=0, **kwargs), road_view)
    np.testing.assert_allclose(
        first.plan_actions[window.agent_index], actions[0].numpy(), rtol=0, atol=1e-5
    )

    guided, _ = planned(after(k=2, guidance_steps=6), road_view)
    np.testing.assert_array_equal(guided.base_plans, unguided.plans)
    same = guided.plan_mask & ~guided.controllable
    np.testing.assert_array_equal(guided.plans[same], unguided.plans[same])
    assert not np.allclose(guided.plans[guided.controllable], unguided.plans[guided.controllable])
    assert guided.guidance_losses[-1, 0] < guided.guidance_losses[0, 0]


@pytest.mark.parametrize(("lambda_adv", "lambda_map"), [(0.0, 0.0), (0.0, 1.0), (50.0, 0.0)])
def test_loss_weight_ablations(tiny_meanflow, tiny_normalizer, road_view, lambda_adv, lambda_map):
    policy, _ = planned(
        RiskFlowAdversary(
            k=2, guidance_steps=6, lambda_adv=lambda_adv, lambda_map=lambda_map, seed=2,
            generator=tiny_meanflow, normalizer=tiny_normalizer,
        ),
        road_view,
    )  # fmt: skip
    losses, moved = policy.guidance_losses, policy.controllable
    if lambda_map == 0.0:
        np.testing.assert_array_equal(losses[:, 1], 0.0)  # the term is not even evaluated
    if lambda_adv == 0.0:
        # No adversarial pull: L_map alone (0 on this wide road) leaves the plans as they
        # are, up to the projection of the actions into the bounds.
        np.testing.assert_allclose(policy.plans[moved], policy.base_plans[moved], atol=1e-4)
    else:
        assert losses[-1, 0] < losses[0, 0]


@pytest.fixture
def diffusion_file(tmp_path, tiny_denoiser, tiny_normalizer):
    options = tiny_denoiser.checkpoint_options()
    checkpoint = build_checkpoint(
        tiny_denoiser.network, tiny_normalizer, step=0, train_config=options, metrics={}
    )
    return save_checkpoint(checkpoint, tmp_path / "diffusion.pt")


def test_checkpoint_kind_is_read_from_the_file(diffusion_file, road_view):
    assert checkpoint_kind(load_checkpoint(diffusion_file)) == "diffusion"
    assert checkpoint_kind({"train_config": {}}) == "meanflow"
    policy, _ = planned(
        RiskFlowAdversary(k=1, guidance_steps=2, checkpoint=diffusion_file, sampling_steps=2),
        road_view,
    )
    assert policy.generator_kind == "diffusion" and len(policy.model.levels) == 2
    with pytest.raises(ValueError, match="is a diffusion model"):
        RiskFlowAdversary(generator="meanflow", checkpoint=diffusion_file)


def test_bad_generator_options(tiny_meanflow, tiny_normalizer, diffusion_file):
    with pytest.raises(ValueError, match="generator must be one of"):
        load_base_generator("gan")
    with pytest.raises(ValueError, match="sampling_steps applies to a diffusion"):
        RiskFlowAdversary(generator="meanflow", sampling_steps=5)
    with pytest.raises(ValueError, match="not with a model object"):
        RiskFlowAdversary(
            generator=tiny_meanflow, normalizer=tiny_normalizer, checkpoint=diffusion_file
        )
    with pytest.raises(ValueError, match="normalizer given without"):
        RiskFlowAdversary(generator="diffusion", normalizer=tiny_normalizer)
    with pytest.raises(FileNotFoundError):
        RiskFlowAdversary(checkpoint=diffusion_file.parent / "missing.pt")


def test_shipped_diffusion_generator():
    if not resources.files("policies").joinpath("checkpoints", "diffusion_default.pt").is_file():
        pytest.skip("no shipped diffusion checkpoint")
    policy = RiskFlowAdversary(generator="diffusion")
    assert policy.generator_kind == "diffusion" and len(policy.model.levels) == 10
