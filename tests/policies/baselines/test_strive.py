"""StriveAdversary: latent optimisation of A_c only, L_adv down, K=0 unguided, seeding, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.baselines.diffusion.sampling import OneCallSampler
from policies.baselines.strive import StriveAdversary
from policies.riskflow.policy import PHASES, RiskFlowAdversary
from riskflow_env.view import ScenePolicy


@pytest.fixture
def strive(tiny_meanflow, tiny_normalizer):
    def make(**kwargs) -> StriveAdversary:
        kwargs = {"k": 2, "guidance_steps": 8, "seed": 3, **kwargs}
        return StriveAdversary(generator=tiny_meanflow, normalizer=tiny_normalizer, **kwargs)

    return make


def planned(policy, road_view):
    _, view = road_view()
    policy.reset(view)
    policy.plan(view)
    return policy


def test_optimises_only_the_latent_of_a_c_and_lowers_l_adv(strive, road_view):
    policy = planned(strive(target="ego", lambda_map=0.0), road_view)
    assert isinstance(policy, ScenePolicy)
    assert set(policy.timings) == {*PHASES, "total"}
    moved = policy.controllable
    assert moved.sum() == 1 and not moved[0]  # target "ego": one attacker
    same = policy.plan_mask & ~moved
    np.testing.assert_array_equal(policy.plans[same], policy.base_plans[same])
    assert not np.allclose(policy.plans[moved], policy.base_plans[moved])
    # Only the A_c rows of the latent moved (window row order = env slots here).
    rows = policy.ranking.controllable
    changed = (policy.latent != policy.noise).any(dim=(1, 2)).numpy()
    np.testing.assert_array_equal(changed, rows)
    losses = policy.guidance_losses
    assert losses.shape == (9, 2) and policy.prior_losses.shape == (9,)
    assert losses[-1, 0] < losses[0, 0]
    np.testing.assert_allclose(policy.prior_losses[0], 0.5 * (policy.noise[rows] ** 2).sum())


def test_k0_is_exactly_the_unguided_generator(strive, road_view, tiny_meanflow, tiny_normalizer):
    policy = planned(strive(k=0), road_view)
    reference = RiskFlowAdversary(k=0, seed=3, generator=tiny_meanflow, normalizer=tiny_normalizer)
    planned(reference, road_view)
    assert not policy.controllable.any()
    np.testing.assert_array_equal(policy.plans, policy.base_plans)
    np.testing.assert_array_equal(policy.plans, reference.plans)
    np.testing.assert_array_equal(policy.plan_actions, reference.plan_actions)


def test_same_base_plans_and_a_c_as_riskflow(strive, road_view, tiny_meanflow, tiny_normalizer):
    policy = planned(strive(), road_view)
    riskflow = RiskFlowAdversary(
        k=2, guidance_steps=8, seed=3, generator=tiny_meanflow, normalizer=tiny_normalizer
    )
    planned(riskflow, road_view)
    np.testing.assert_array_equal(policy.base_plans, riskflow.base_plans)
    np.testing.assert_array_equal(policy.controllable, riskflow.controllable)
    torch.testing.assert_close(policy.noise, riskflow.noise, rtol=0, atol=0)


def test_prior_term_pulls_the_latent_toward_zero(strive, road_view):
    policy = planned(strive(lambda_adv=0.0, lambda_map=0.0, lambda_prior=1.0), road_view)
    assert policy.prior_losses[-1] < 0.5 * policy.prior_losses[0]
    free = planned(strive(lambda_prior=0.0), road_view)
    assert free.prior_losses[-1] != free.prior_losses[0]


def test_same_seed_same_closed_loop_rollout(strive, closed_loop):
    histories = []
    for seed in (5, 5, 6):
        env, _ = closed_loop(strive(seed=seed, guidance_steps=3), 7)
        histories.append(env.scene.history.copy())
    np.testing.assert_array_equal(histories[0], histories[1])
    assert not np.array_equal(histories[0], histories[2])


def test_adam_steps_move_every_latent_coordinate_by_the_step_size(strive, road_view):
    """Adam's first step is ``lr * sign(g)``: every coordinate of the guided latent rows
    moves by ``step_size``; more steps lower ``L_adv``."""
    policy = planned(strive(guidance_steps=8), road_view)
    assert policy.guidance_losses[-1, 0] < policy.guidance_losses[0, 0]
    policy = planned(strive(guidance_steps=1), road_view)
    rows = (policy.latent != policy.noise).any(dim=(1, 2))
    step = (policy.latent - policy.noise)[rows].abs()
    assert rows.sum() == 2
    torch.testing.assert_close(step, torch.full_like(step, 0.1), rtol=1e-3, atol=0.0)


def test_gradient_steps_and_draw(strive, road_view):
    policy = planned(strive(optimizer="gradient", step_size=1e-3), road_view)
    assert policy.guidance_losses[-1, 0] <= policy.guidance_losses[0, 0]
    overlays = {}

    class Renderer:
        def set_overlay(self, name, *args, **kwargs):
            overlays[name] = args

    policy.draw(Renderer())
    assert set(overlays) == {"strive_base", "strive_guided"}


def test_bad_options(strive, tiny_denoiser, tiny_normalizer, tiny_meanflow):
    for kwargs, match in (
        ({"lambda_prior": -1.0}, "lambda_prior"),
        ({"lambda_prior": float("nan")}, "lambda_prior"),
        ({"lambda_prior": True}, "lambda_prior"),
        ({"k": -1}, "k must be"),
        ({"planning_interval": 0.0}, "planning_interval"),
        ({"target": "everyone"}, "target must be one of"),
        ({"guidance_steps": -1}, "GuidanceConfig: steps"),
        ({"optimizer": "adam-plan"}, "optimizer must be one of"),
    ):
        with pytest.raises(ValueError, match=match):
            strive(**kwargs)
    assert strive(guidance_horizon=7).guidance.horizon == 7  # the shared objective
    assert strive(lambda_prior=np.float32(0.1)).lambda_prior == 0.1
    with pytest.raises(ValueError, match="diffusion"):
        StriveAdversary(generator="diffusion")
    with pytest.raises(ValueError, match="diffusion"):
        StriveAdversary(generator=OneCallSampler(tiny_denoiser, 2), normalizer=tiny_normalizer)
    with pytest.raises(ValueError, match="normalizer"):
        StriveAdversary(generator=tiny_meanflow)


def _guided_penetration(policy, view) -> float:
    """Summed squared penetration depth [m^2] of the pairs of guided plans (world frame):
    the avoidance steps' score (``overlap_scores``) on every pair of guided vehicles."""
    from policies.learned.plan_overlap import overlap_scores

    guided = policy.controllable
    plans = torch.as_tensor(policy.plans[guided])[None]  # (1, C, T, 4)
    length = torch.as_tensor(view.length[guided], dtype=plans.dtype)[None]
    width = torch.as_tensor(view.width[guided], dtype=plans.dtype)[None]
    count = plans.shape[1]
    pairs = torch.ones(1, count, count, dtype=torch.bool).triu(diagonal=1)
    present = torch.ones(1, count, dtype=torch.bool)
    return float(overlap_scores(plans[:, None], length, width, present, plans[:, :, 0], pairs))


@pytest.mark.parametrize("kind", ["strive", "riskflow"])
def test_separation_term_keeps_the_guided_vehicles_apart(
    kind, strive, road_view, tiny_meanflow, tiny_normalizer
):
    """STRIVE-style takes RiskFlow's L_sep: three adversaries pulled hard onto the others
    overlap each other without it (``lambda_sep=0``, the paper's objective), much less
    with it; the default is a weight of 100."""
    options = {"k": 3, "target": "others", "guidance_steps": 30, "step_size": 0.5}
    if kind == "riskflow":
        models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer, "seed": 3}
        make = lambda **kw: RiskFlowAdversary(**models, **kw)  # noqa: E731
    else:
        make = strive
    _, view = road_view()
    without = planned(make(lambda_sep=0.0, **options), road_view)
    with_term = planned(make(lambda_sep=1000.0, **options), road_view)
    default = planned(make(**options), road_view)
    hundred = planned(make(lambda_sep=100.0, **options), road_view)
    assert _guided_penetration(without, view) > 0.1
    assert _guided_penetration(with_term, view) < 0.5 * _guided_penetration(without, view)
    np.testing.assert_array_equal(default.plans, hundred.plans)


def test_with_target_ego_the_separation_term_takes_the_bystanders(strive, road_view, monkeypatch):
    """As RiskFlow's: with target ``ego`` the attacker keeps clear of the vehicles that keep
    their unguided plans (never the ego); with ``others`` there are none."""
    from policies.baselines import strive as module

    calls = []
    real = module.separation_term

    def spy(scene, rows, config, scene_of_row=None, bystanders=None, scene_of_bystander=None):
        calls.append((rows.clone(), None if bystanders is None else bystanders.clone()))
        return real(scene, rows, config, scene_of_row, bystanders, scene_of_bystander)

    monkeypatch.setattr(module, "separation_term", spy)
    planned(strive(target="ego"), road_view)
    rows, bystanders = calls[-1]
    assert rows.numel() == 1 and bystanders is not None and bystanders.numel() > 0
    assert not set(bystanders.tolist()) & set(rows.tolist())
    planned(strive(target="others"), road_view)
    assert calls[-1][1] is None or calls[-1][1].numel() == 0
