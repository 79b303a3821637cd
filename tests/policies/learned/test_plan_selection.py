"""Best of M joint plans: the score, the choice, and the policies that use it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.baselines.diffusion.sampling import OneCallSampler
from policies.baselines.nominal import NominalGenerator
from policies.learned.guidance_losses import ObjectiveConfig
from policies.learned.plan_selection import (
    overlap_gradient,
    overlap_scores,
    select_attack_plans,
    select_joint_plans,
)
from policies.learned.sampler import sample
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.riskflow.policy import RiskFlowAdversary
from tests.policies.straight_road import ROAD_ENV, TINY_NORMALIZER, road_env

CONFIG = dataclasses.replace(ROAD_ENV, max_agents=9, episode_steps=25)
LENGTH, WIDTH = 4.0, 2.0


def still(xy: list[tuple[float, float]], steps: int = 3) -> torch.Tensor:
    """(A, T, 4) agents standing at ``xy``, heading 0."""
    states = torch.tensor([[x, y, 0.0, 0.0] for x, y in xy], dtype=torch.float64)
    return states[:, None].expand(-1, steps, -1).clone()


def sizes(count: int) -> tuple[torch.Tensor, torch.Tensor]:
    full = torch.ones(1, count, dtype=torch.float64)
    return LENGTH * full, WIDTH * full


def test_overlap_score_tests_only_pairs_that_can_touch_and_equals_every_pair():
    """Skipping pairs whose centres stay farther apart than their half-diagonals changes
    neither the score nor its gradient: the dense sum over every pair, to float rounding."""
    from policies.learned.plan_penalties import pair_separation

    g = torch.Generator().manual_seed(3)
    num_scenes, samples, agents, steps = 2, 3, 14, 20
    start = torch.rand(num_scenes, 1, agents, 1, 2, generator=g, dtype=torch.float64)
    velocity = torch.randn(num_scenes, samples, agents, 1, 2, generator=g, dtype=torch.float64)
    plans = torch.zeros(num_scenes, samples, agents, steps, 4, dtype=torch.float64)
    time = 0.1 * torch.arange(steps, dtype=torch.float64)[:, None]
    plans[..., :2] = start * torch.tensor([50.0, 10.0], dtype=torch.float64) + 3 * velocity * time
    plans[..., 3] = 0.3 * torch.randn(num_scenes, samples, agents, 1, generator=g)
    length = 3.5 + 2 * torch.rand(num_scenes, agents, generator=g, dtype=torch.float64)
    width = 1.6 + 0.4 * torch.rand(num_scenes, agents, generator=g, dtype=torch.float64)
    mask = torch.rand(num_scenes, agents, generator=g) > 0.1
    now = plans[:, 0, :, 0]

    sparse = plans.clone().requires_grad_(True)
    dense = plans.clone().requires_grad_(True)
    scores = overlap_scores(sparse, length, width, mask, now)
    pairs = mask[:, :, None] & mask[:, None] & torch.ones(agents, agents, dtype=torch.bool).triu(1)
    pairs &= pair_separation(now[:, :, None], length, width)[..., 0] > 0.0
    depth = torch.relu(-pair_separation(dense, length[:, None], width[:, None]))
    expected = (depth**2 * pairs[:, None, :, :, None]).sum(dim=(-3, -2, -1))
    assert int((expected > 0).sum()) >= 3  # joint plans with overlaps to score
    torch.testing.assert_close(scores, expected, rtol=1e-12, atol=1e-12)
    scores.sum().backward()
    expected.sum().backward()
    torch.testing.assert_close(sparse.grad, dense.grad, rtol=1e-12, atol=1e-12)


def test_the_closed_form_overlap_gradient_is_autograds():
    """``overlap_gradient`` (no autograd graph) against autograd through
    ``overlap_scores``, on joint plans with many overlaps; ``closest`` is the smallest
    separation among the pairs tested, and a slack tests more pairs."""
    from policies.learned.plan_penalties import pair_separation

    g = torch.Generator().manual_seed(5)
    num_scenes, samples, agents, steps = 2, 2, 9, 12
    plans = torch.zeros(num_scenes, samples, agents, steps, 4, dtype=torch.float64)
    plans[..., :2] = 6 * torch.rand(num_scenes, samples, agents, 1, 2, generator=g)
    plans[..., :2] += torch.cumsum(0.3 * torch.randn(*plans.shape[:-1], 2, generator=g), dim=3)
    plans[..., 3] = 3 * torch.randn(*plans.shape[:-1], generator=g)
    length = 3.5 + 2 * torch.rand(num_scenes, agents, generator=g, dtype=torch.float64)
    width = 1.6 + 0.4 * torch.rand(num_scenes, agents, generator=g, dtype=torch.float64)
    mask = torch.rand(num_scenes, agents, generator=g) > 0.1
    pairs = mask[:, :, None] & mask[:, None] & torch.ones(agents, agents, dtype=torch.bool).triu(1)
    now = plans[:, 0, :, 0]

    variable = plans.clone().requires_grad_(True)
    overlap_scores(variable, length, width, mask, now, pairs).sum().backward()
    gradient, closest = overlap_gradient(plans, length, width, pairs)
    assert int((variable.grad != 0).sum()) > 100
    torch.testing.assert_close(gradient, variable.grad, rtol=1e-10, atol=1e-10)
    assert not gradient[..., 2].any()  # speed
    gaps = pair_separation(plans, length[:, None], width[:, None])  # (B, M, A, A, T)
    gaps = gaps.masked_fill(~pairs[:, None, :, :, None], float("inf")).flatten(2).amin(dim=2)
    assert bool((gaps < 0).all())  # every joint plan overlaps: its closest pair is tested
    torch.testing.assert_close(closest, gaps, rtol=0, atol=0)
    far = torch.zeros(1, 1, 2, 3, 4, dtype=torch.float64)
    far[0, 0, 1, :, 0] = 10.0  # 10 m apart, 4 m boxes: 6 m between them
    two = torch.ones(1, 2, dtype=torch.float64)
    pair = torch.tensor([[[False, True], [False, False]]])
    for slack, expected in ((0.0, float("inf")), (7.0, 6.0)):
        gradient, closest = overlap_gradient(far, 4 * two, 2 * two, pair, slack)
        assert not gradient.any() and float(closest[0, 0]) == pytest.approx(expected)


def test_overlap_score_is_the_squared_penetration_of_pairs_apart_now():
    now = torch.tensor([[[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0], [20.0, 0.0, 0.0, 0.0]]])
    apart = still([(0.0, 0.0), (10.0, 0.0), (20.0, 0.0)])
    touching = still([(0.0, 0.0), (3.0, 0.0), (20.0, 0.0)])  # 1 m into each other, 3 steps
    plans = torch.stack([apart, touching])[None]  # (1, 2, A, T, 4)
    length, width = sizes(3)
    mask = torch.ones(1, 3, dtype=torch.bool)
    scores = overlap_scores(plans, length, width, mask, now.double())
    np.testing.assert_allclose(scores.numpy(), [[0.0, 3 * 1.0**2]])
    # an absent agent counts for nothing, nor does a pair that overlaps already now
    absent = torch.tensor([[True, False, True]])
    assert overlap_scores(plans, length, width, absent, now.double())[0, 1] == 0
    now_touching = touching[None, :, 0]
    assert overlap_scores(plans, length, width, mask, now_touching)[0, 1] == 0


def test_the_lowest_score_wins_with_the_map_term_added():
    now = still([(0.0, 0.0), (10.0, 0.0)])[None, :, 0]
    apart, touching = still([(0.0, 0.0), (10.0, 0.0)]), still([(0.0, 0.0), (3.0, 0.0)])
    plans = torch.stack([touching, apart, apart])[None]  # (1, 3, A, T, 4)
    length, width = sizes(2)
    mask = torch.ones(1, 2, dtype=torch.bool)
    best, scores = select_joint_plans(plans, length, width, mask, now, None)
    assert best.tolist() == [1] and scores.shape == (1, 3)

    def off_road_beyond_5m(rows: torch.Tensor) -> torch.Tensor:  # (C, T, 4) -> (C,)
        return 100.0 * (rows[:, :, 0] > 5.0).double().sum(dim=1)

    # "road" up to x = 5 m: samples 1 and 2 leave it (300 m^2 each), sample 0 overlaps (3)
    best, scores = select_joint_plans(plans, length, width, mask, now, off_road_beyond_5m)
    assert best.tolist() == [0]
    np.testing.assert_allclose(scores.numpy(), [[3.0, 300.0, 300.0]])
    plans[0, 2, 1, :, 0] = 4.5  # sample 2: on the road and 0.5 m clear of the first car
    best, _ = select_joint_plans(plans, length, width, mask, now, off_road_beyond_5m)
    assert best.tolist() == [2]


def test_attack_selection_keeps_each_guided_vehicles_sample_nearest_its_targets():
    """Per vehicle of ``A_c``: the sample with the lowest ``lambda_adv * L_adv + lambda_map
    * L_map`` against the targets' plans; 0 for every other vehicle."""
    # agents: 0 the ego at (0, 0), 1 guided, 2 guided, 3 a bystander at (0, 20)
    samples = [
        still([(0.0, 0.0), (30.0, 0.0), (30.0, 20.0), (0.0, 20.0)]),
        still([(0.0, 0.0), (10.0, 0.0), (12.0, 35.0), (0.0, 40.0)]),
        still([(0.0, 0.0), (20.0, 0.0), (20.0, 5.0), (0.0, 0.0)]),
    ]
    plans = torch.stack(samples)[None]  # (1, 3, 4, T, 4)
    controllable = torch.tensor([[False, True, True, False]])
    targets = torch.tensor([[True, False, False, True]])
    target_xy = plans[:, 0, ..., :2]  # the targets follow sample 0: ego (0, 0), (0, 20)
    objective = ObjectiveConfig()
    pick = select_attack_plans(plans, target_xy, controllable, targets, objective, None)
    # 1: 30 / 10 / 20 m from the ego; 2: 30 / 19.2 / 20.6 m from its nearest target
    assert pick.tolist() == [[0, 1, 1, 0]]
    ego_only = torch.tensor([[True, False, False, False]])
    pick = select_attack_plans(plans, target_xy, controllable, ego_only, objective, None)
    assert pick.tolist() == [[0, 1, 2, 0]]  # 2: 36.1 / 37.0 / 20.6 m from the ego

    def off_road_below_x_15(rows: torch.Tensor) -> torch.Tensor:  # (M * C, T, 4) -> (M * C,)
        return 10.0 * (rows[:, :, 0] < 15.0).double().sum(dim=1)

    # "road" from x = 15 m: sample 1 leaves it (20 * 30 m^2 outweighs 50 * 10 m) for both
    pick = select_attack_plans(
        plans, target_xy, controllable, targets, objective, off_road_below_x_15
    )
    assert pick.tolist() == [[0, 2, 2, 0]]
    nobody = torch.zeros_like(controllable)
    assert select_attack_plans(plans, target_xy, nobody, targets, objective, None).sum() == 0


@pytest.fixture
def model(make_model, tiny_config):
    return make_model(tiny_config, seed=1).eval()


def nominal(model, **kwargs) -> NominalGenerator:
    return NominalGenerator(generator=model, normalizer=TINY_NORMALIZER, seed=5, **kwargs)


def test_best_of_m_keeps_one_of_the_generator_samples_deterministically(model):
    env = road_env(CONFIG)
    plans = []
    for _ in range(2):
        policy = nominal(model, base_samples=4)
        policy.reset(env.view())
        plans.append(policy.plan(env.view()).copy())
    np.testing.assert_array_equal(plans[0], plans[1])  # same seed, same choice, bit for bit
    # the kept plan is the generator's own sample of the kept noise (no output edited)
    window = window_from_view(env.view(), policy.window_config)
    actions, _ = sample(model, collate_windows([window]), policy.noise[None], TINY_NORMALIZER)
    slots = window.agent_index
    np.testing.assert_allclose(policy.plan_actions[slots], actions[0].numpy(), rtol=0, atol=1e-5)


def test_one_sample_is_the_single_draw_bit_for_bit(model):
    env = road_env(CONFIG)
    default, one = nominal(model), nominal(model, base_samples=1)
    for policy in (default, one):
        policy.reset(env.view())
    np.testing.assert_array_equal(default.plan(env.view()), one.plan(env.view()))


@pytest.mark.parametrize("name", ["base_samples", "attack_samples"])
def test_bad_sample_counts_name_the_argument(model, name, tiny_denoiser, tiny_normalizer):
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match=f"{name} must be an int >= 1"):
            RiskFlowAdversary(generator=model, normalizer=TINY_NORMALIZER, **{name: bad})
    sampler = OneCallSampler(tiny_denoiser, 2)
    with pytest.raises(ValueError, match=f"{name} > 1 needs the MeanFlow generator"):
        RiskFlowAdversary(generator=sampler, normalizer=tiny_normalizer, **{name: 2})


def test_attack_samples_guide_from_a_generator_sample_deterministically(model):
    """With ``attack_samples`` each guided vehicle starts from another of its sampled plans
    (the same ones for the same seed, bit for bit); the other vehicles keep the first joint
    sample, drawn with the single draw's noise (guidance, avoidance and blending off here;
    the generator's batched pass of 4 samples may round differently from a pass of one)."""
    env = road_env(CONFIG)
    plans = {}
    for samples in (4, 4, 1):
        policy = RiskFlowAdversary(
            generator=model, normalizer=TINY_NORMALIZER, seed=5, k=2, attack_samples=samples,
            guidance_steps=0, avoid_steps=0, stitch_first=False, hold_distance=0.0,
        )  # fmt: skip
        policy.reset(env.view())
        policy.plan(env.view())
        if samples in plans:
            np.testing.assert_array_equal(policy.plan_actions, plans[samples])
        plans[samples] = policy.plan_actions.copy()
    slots = window_from_view(env.view(), policy.window_config).agent_index
    guided = np.zeros(len(policy.plan_actions), dtype=bool)
    guided[slots] = policy.ranking.controllable[: len(slots)]
    assert guided.any()
    np.testing.assert_allclose(plans[4][~guided], plans[1][~guided], rtol=0, atol=1e-5)
    assert not np.allclose(plans[4][guided], plans[1][guided], atol=1e-3)
