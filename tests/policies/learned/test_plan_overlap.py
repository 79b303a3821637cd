"""The overlap score of planned boxes and its closed-form gradient."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.learned.plan_overlap import overlap_gradient, overlap_scores
from tests.policies.straight_road import ROAD_ENV

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
    from policies.learned.plan_overlap import pair_separation

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
    from policies.learned.plan_overlap import pair_separation

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
