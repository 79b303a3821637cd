"""``L_sep``: the guided boxes kept apart from each other and, with target ``"ego"``, from
the bystanders (present vehicles that keep their unguided plans), never from the ego."""

from __future__ import annotations

import dataclasses

import torch

from policies.learned.plan_overlap import pair_separation, separation_term
from policies.riskflow.guidance import PER_AGENT, GuidanceConfig, guided_rows
from tests.policies.riskflow.guidance_scenes import make_scene, mask_of

EGO_TARGET = GuidanceConfig(target="ego")
# The ego 30 m ahead; the attacker (row 1) drifts from the left lane toward it at 15 m/s
# through a car parked half across the lane line at 20 m (row 2); its plan also crosses
# the ego's (the target, which L_sep leaves to L_adv).
SCENE = make_scene([[30.0, 0.0, 10.0, 0.0], [0.0, 3.5, 15.0, -0.05], [20.0, 1.5, 0.0, 0.0]], seed=4)


def batched(scene):
    """One scene with a leading B = 1 axis, as :func:`guided_rows` takes it."""
    tensors = {name: getattr(scene, name)[None] for name in PER_AGENT}
    return dataclasses.replace(scene, frame=scene.frame[None], **tensors)


def depth_squared(trajectories: torch.Tensor, rows: list[int]) -> torch.Tensor:
    """Summed squared penetration depth [m^2] of the boxes ``rows`` (2) of SCENE."""
    gaps = pair_separation(
        trajectories[None, rows], SCENE.length[None, rows], SCENE.width[None, rows]
    )
    return torch.relu(-gaps[0, 0, 1]).square().sum()


def test_bystanders_are_the_vehicles_neither_guided_nor_targets():
    scene = batched(
        make_scene([[0.0, 0.0, 9.0, 0.0]] + [[10.0 * k, 3.5, 9.0, 0.0] for k in (1, 2, 3)])
    )
    ego = guided_rows(scene, mask_of(4, [2])[None], "ego")
    assert ego.bystanders.tolist() == [1, 3] and ego.scene_of_bystander.tolist() == [0, 0]
    others = guided_rows(scene, mask_of(4, [2])[None], "others")
    assert others.bystanders.numel() == 0 and others.scene_of_bystander.numel() == 0


def test_attacker_through_a_parked_car_is_pushed_away_from_it_and_not_from_the_ego():
    attacker = SCENE.base_trajectories[[1]]
    bystanders = guided_rows(batched(SCENE), mask_of(3, [1])[None], "ego").bystanders
    assert bystanders.tolist() == [2]  # the ego is the target, never a bystander
    term = separation_term(SCENE, torch.tensor([1]), EGO_TARGET, None, bystanders)
    gradient = term.gradient(attacker)
    # The closed form is autograd's gradient of the squared depth with the parked car.
    plans = SCENE.base_trajectories.clone().requires_grad_(True)
    depth_squared(plans, [1, 2]).backward()
    torch.testing.assert_close(gradient, plans.grad[[1]], rtol=1e-4, atol=1e-4)
    assert float(depth_squared(SCENE.base_trajectories, [1, 2])) > 1.0
    assert float(depth_squared(SCENE.base_trajectories, [1, 0])) > 0.1  # the ego: no push
    lateral = gradient[0, :, 1]  # descent moves y up, away from the parked car, never down
    assert bool((lateral <= 0).all()) and int((lateral < 0).sum()) >= 3
    # A descent step on the positions (d depth^2 / d y = -2 depth: half the depth off)
    # takes the attacker halfway out of the parked car.
    moved = SCENE.base_trajectories.clone()
    moved[1, :, :2] -= 0.25 * gradient[0, :, :2]
    assert depth_squared(moved, [1, 2]) < 0.5 * depth_squared(SCENE.base_trajectories, [1, 2])


def test_without_bystanders_the_term_is_the_guided_pairs_alone():
    rows, scene_of_row = torch.tensor([1, 2]), torch.zeros(2, dtype=torch.long)
    plans = SCENE.base_trajectories[[1, 2]]
    alone = separation_term(SCENE, rows, EGO_TARGET, scene_of_row).gradient(plans)
    empty = torch.zeros(0, dtype=torch.long)
    assert torch.equal(
        separation_term(SCENE, rows, EGO_TARGET, scene_of_row, empty, empty).gradient(plans), alone
    )
    assert alone.abs().sum() > 0
    assert separation_term(SCENE, rows, GuidanceConfig(lambda_sep=0.0), scene_of_row) is None
