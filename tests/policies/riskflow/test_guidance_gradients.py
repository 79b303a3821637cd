"""Guidance losses and gradients against closed forms, finite differences and autograd."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.learned.guidance_losses import MapTerm
from policies.learned.sampler import decode_plans
from policies.riskflow import guidance
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceScene,
    adversarial_loss,
    adversarial_value_and_gradient,
    guide,
    map_loss,
)
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout
from tests.policies.riskflow.guidance_scenes import (
    HIGHWAY,
    NORMALIZER,
    ROAD,
    STEPS,
    make_scene,
    mask_of,
)


def test_adversarial_loss_closed_form():
    time = torch.arange(10, dtype=torch.float32)
    xy = torch.stack([time, torch.zeros(10)], dim=-1)[None]  # (1, 10, 2) along y = 0
    targets = torch.stack(
        [
            torch.stack([time, torch.full((10,), 3.0)], dim=-1),  # 3 m to the left
            torch.stack([time + 4.0 - time, torch.zeros(10)], dim=-1),  # parked at x = 4
        ]
    )
    nearest = torch.minimum(torch.full((10,), 3.0), (time - 4.0).abs())
    assert torch.allclose(adversarial_loss(xy, targets), nearest.mean())
    assert torch.allclose(adversarial_loss(xy, targets, horizon=4), nearest[:4].mean())
    assert adversarial_loss(xy, targets[:0]) == 0.0


def test_map_loss_closed_form_and_frame():
    """A 4 x 2 m box centred 6 m left of the road axis: its left samples sit 1 m off."""
    states = torch.tensor([[[0.0, 6.0, 0.0, 0.0]]])  # (1, 1, 4)
    size = torch.tensor([4.0]), torch.tensor([2.0])
    loss = map_loss(states, *size, ROAD, torch.zeros(3), margin=0.0)
    # Samples at y = 7 (3), y = 6 (3, on the edge), y = 5 (3): depths 1, 0, 0.
    assert loss.item() == pytest.approx(3.0, abs=0.1)
    # The same box given in a frame rotated by 90 degrees and shifted.
    frame = torch.tensor([10.0, 0.0, np.pi / 2])
    rotated = torch.tensor([[[6.0, 10.0, 0.0, -np.pi / 2]]])  # world (10, 6), heading 0
    moved = map_loss(rotated, *size, ROAD, frame, margin=0.0)
    assert moved.item() == pytest.approx(loss.item(), abs=1e-3)


def test_adversarial_gradient_is_autograd_of_the_nearest_distance():
    """``adversarial_value_and_gradient`` (and autograd through ``adversarial_loss``) equal
    autograd of the plain formula: mean over T_g of the distance to the nearest target."""
    generator = torch.Generator().manual_seed(1)
    xy = torch.randn(3, 12, 2, generator=generator, dtype=torch.float64) * 5
    targets = torch.randn(4, 12, 2, generator=generator, dtype=torch.float64) * 5
    targets[0, 2] = xy[1, 2]  # an agent exactly on a target: gradient 0, not NaN
    for horizon in (None, 5):
        plain = xy.clone().requires_grad_(True)
        distance = (plain[:, None] - targets[None]).norm(dim=-1).amin(dim=1)[:, :horizon]
        (expected,) = torch.autograd.grad(distance.mean(dim=1).sum(), plain)
        value, gradient = adversarial_value_and_gradient(xy, targets, horizon)
        assert torch.allclose(value, distance.detach().mean(dim=1).sum())
        assert torch.allclose(gradient, torch.nan_to_num(expected))  # norm's NaN at 0
        assert (gradient[1, 2] == 0).all() and (horizon is None or (gradient[:, 5:] == 0).all())
        graph = xy.clone().requires_grad_(True)
        (through_loss,) = torch.autograd.grad(adversarial_loss(graph, targets, horizon), graph)
        assert torch.equal(through_loss, gradient)


def test_map_gradient_matches_finite_differences():
    """``MapTerm.value_and_gradient`` against central differences in (x, y, psi), in a
    rotated scene frame, with samples off the road; autograd through ``MapTerm`` agrees."""
    generator = torch.Generator().manual_seed(2)
    frame = torch.tensor([10.0, -1.0, 0.4], dtype=torch.float64)
    states = torch.zeros(2, 6, 4, dtype=torch.float64)
    states[..., 0] = torch.linspace(-5.0, 30.0, 6)
    states[..., 1] = torch.rand(2, 6, generator=generator, dtype=torch.float64) * 10 - 2.0
    states[..., 3] = torch.rand(2, 6, generator=generator, dtype=torch.float64) - 0.9
    length, width = torch.tensor([4.5, 5.0]).double(), torch.tensor([2.0, 2.2]).double()
    term = MapTerm(ROAD, frame, length, width, 6, margin=0.2, decay=0.9)
    value, gradient = term.value_and_gradient(states)
    assert value > 1.0  # some samples are off the road
    assert torch.equal(value, term(states)) and (gradient[..., 2] == 0).all()
    step = 1e-6
    for channel in (0, 1, 3):
        shift = torch.zeros_like(states)
        shift[..., channel] = step
        numeric = torch.stack(
            [
                (term(states + shift * e[..., None]) - term(states - shift * e[..., None]))
                / (2 * step)
                for e in torch.eye(12, dtype=torch.float64).reshape(12, 2, 6)
            ]
        ).reshape(2, 6)
        assert torch.allclose(gradient[..., channel], numeric, atol=1e-5), channel
    graph = states.clone().requires_grad_(True)
    (through_term,) = torch.autograd.grad(term(graph), graph)
    assert torch.equal(through_term, gradient)


def test_map_term_forgives_what_a_vehicle_is_off_the_road_now():
    """``MapTerm.forgive``: a vehicle 2 m beside the road (|y| < 6 m) is not penalised
    where it stands, only beyond; a vehicle on the road keeps the plain term."""
    frame = torch.zeros(3, dtype=torch.float64)
    length, width = torch.tensor([4.5, 4.5]).double(), torch.tensor([2.0, 2.0]).double()
    now = torch.tensor([[0.0, 8.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    plain = MapTerm(ROAD, frame, length, width, 3, margin=0.2, decay=1.0)
    term = MapTerm(ROAD, frame, length, width, 3, margin=0.2, decay=1.0)
    term.forgive(now)
    stay = now[:, None].expand(2, 3, 4).clone()
    assert float(plain.rows(stay)[0]) > 1.0 and float(term.rows(stay)[0]) == 0.0
    farther = stay.clone()
    farther[0, :, 1] += 0.5  # half a metre farther off the road
    assert 0.0 < float(term.rows(farther)[0]) < float(plain.rows(farther)[0])
    closer = stay.clone()
    closer[0, :, 1] -= 3.0  # back onto the road
    assert float(term.rows(closer)[0]) == 0.0
    onto = stay.clone()
    onto[1, :, 1] = torch.tensor([4.0, 5.5, 7.0], dtype=torch.float64)  # the on-road one leaves
    assert torch.equal(term.rows(onto)[1], plain.rows(onto)[1])


def test_map_term_scores_the_guidance_horizon_only():
    """``map_term`` scores the first ``T_g`` steps, as ``L_adv`` and ``L_sep`` do: with
    target ``"ego"`` (3 s) a plan off the road from step 30 on costs nothing, and the
    whole plan is scored with ``"others"``."""
    from types import SimpleNamespace

    from policies.learned.guidance_losses import ObjectiveConfig, map_term

    scene = SimpleNamespace(
        drivable_map=ROAD, frame=torch.zeros(3, dtype=torch.float64),
        length=torch.tensor([4.5]).double(), width=torch.tensor([2.0]).double(),
    )  # fmt: skip
    plan = torch.zeros(1, 50, 4, dtype=torch.float64)
    plan[0, 30:, 1] = 20.0  # off the road from 3 s on
    rows = torch.arange(1)
    ego = map_term(scene, rows, 50, ObjectiveConfig(target="ego"))
    others = map_term(scene, rows, 50, ObjectiveConfig(target="others"))
    assert float(ego.rows(plan)[0]) == 0.0 and float(others.rows(plan)[0]) > 1.0
    plan[0, 29, 1] = 20.0  # and at the horizon's last step
    assert float(ego.rows(plan)[0]) > 1.0
    _, gradient = ego.value_and_gradient(plan)
    assert (gradient[:, 30:] == 0).all() and (gradient[:, 29] != 0).any()


def _autograd_adversarial(xy, target_xy, horizon, target_valid):
    """Each row's ``L_adv`` by plain autograd ops (the reference of the closed form)."""
    targets = target_xy if target_xy.ndim == 4 else target_xy[None].expand(len(xy), -1, -1, -1)
    distance = torch.linalg.vector_norm(xy[:, None, :horizon] - targets[:, :, :horizon], dim=-1)
    if target_valid is not None:
        distance = distance.masked_fill(~target_valid[..., None], torch.inf)
    return distance.min(dim=1).values.mean(dim=1)


def _autograd_gradient(objective, u_c, lambda_adv, lambda_map):
    """The autograd path the closed form replaces: through the rollout and the losses
    Returns the gradient and each row's ``L_adv`` and ``L_map`` (as
    ``gradient`` does)."""
    with torch.inference_mode(False), torch.enable_grad():  # guide's loop runs in inference
        u_c = u_c.clone().requires_grad_(True)
        trajectories = rollout(objective.state, objective.actions(u_c), objective.dynamics)
        adv = _autograd_adversarial(
            trajectories[..., :2], objective.target_xy, objective.horizon, objective.target_valid
        )
        off_road = objective.map_term(trajectories)
        loss = lambda_adv * adv.sum() + lambda_map * off_road
        (grad,) = torch.autograd.grad(loss, u_c)
    return grad, adv.detach(), objective.map_term.rows(trajectories.detach())


def _stopping_scene() -> GuidanceScene:
    """HIGHWAY with vehicle 3 braking to a stop (speed bound active) and vehicle 1 on the
    road edge (map term active)."""
    state = [row[:] for row in HIGHWAY]
    state[1][1], state[3][2] = 5.0, 1.0
    scene = make_scene(state)
    accel = torch.zeros(len(state), STEPS, 2)
    accel[3, :30, 0] = -2.0
    u0 = NORMALIZER.normalize(accel) - scene.eps
    actions, trajectories = decode_plans(scene.eps + u0, scene.state, scene.agent_mask, NORMALIZER)
    assert bool((trajectories[3, :, 2] == 0).any())
    return dataclasses.replace(scene, u0=u0, base_actions=actions, base_trajectories=trajectories)


def test_closed_form_gradient_and_plans_equal_the_autograd_path(monkeypatch):
    scene = _stopping_scene()
    controllable = mask_of(6, [1, 3, 5])
    config = GuidanceConfig()
    rows = torch.tensor([1, 3, 5])
    targets = scene.base_trajectories[[0, 2, 4], :, :2]
    objective = guidance._Objective(scene, rows, targets, NORMALIZER, config, DEFAULT_CONFIG)
    guided = guide(scene, controllable, NORMALIZER, config)
    for u_c in (scene.u0[rows], guided.u[rows]):
        closed = objective.gradient(u_c, config.lambda_adv, config.lambda_map)
        reference = _autograd_gradient(objective, u_c, config.lambda_adv, config.lambda_map)
        scale = float(reference[0].abs().max())
        torch.testing.assert_close(closed[0], reference[0], rtol=0, atol=1e-5 * scale)
        torch.testing.assert_close(closed[1:], reference[1:])
    monkeypatch.setattr(guidance._Objective, "gradient", _autograd_gradient)
    previous = guide(scene, controllable, NORMALIZER, config)
    # Plans (trajectories) to float rounding; actions that move nothing (braking while
    # stopped) may differ: autograd leaves rounding residues there that Adam amplifies.
    torch.testing.assert_close(guided.trajectories, previous.trajectories, rtol=0, atol=1e-4)
    torch.testing.assert_close(guided.losses, previous.losses, rtol=1e-5, atol=1e-5)
