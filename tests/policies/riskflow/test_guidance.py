"""Output-space guidance: masked to A_c, lowers L_adv with a bounded L_map, bounds, signs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.learned.data import ActionNormalizer
from policies.learned.guidance_losses import MapTerm
from policies.learned.sampler import base_velocity, sample
from policies.learned.synthetic import synthetic_batch
from policies.riskflow import guidance
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceScene,
    adversarial_loss,
    adversarial_value_and_gradient,
    guide,
    map_loss,
    plans_from_velocity,
)
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout
from riskflow_env.maps import Lane, MapStack, from_lanes

NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.1))
ROAD = from_lanes([Lane(np.array([[-100.0, 0.0], [300.0, 0.0]]), 12.0, "road")])  # |y| < 6 m
STEPS = 52


def make_scene(state: list[list[float]], frame=(0.0, 0.0, 0.0), seed: int = 0) -> GuidanceScene:
    """Vehicles (4.5 m x 2 m) whose base plans keep their speed and heading."""
    state = torch.tensor(state, dtype=torch.float32)
    num = state.shape[0]
    eps = torch.randn(num, STEPS, 2, generator=torch.Generator().manual_seed(seed))
    u0 = NORMALIZER.normalize(torch.zeros(num, STEPS, 2)) - eps  # keep speed and heading
    mask = torch.ones(num, dtype=torch.bool)
    actions, trajectories = plans_from_velocity(eps, u0, state, mask, NORMALIZER)
    return GuidanceScene(
        eps=eps,
        u0=u0,
        state=state,
        length=torch.full((num,), 4.5),
        width=torch.full((num,), 2.0),
        agent_mask=mask,
        base_actions=actions,
        base_trajectories=trajectories,
        drivable_map=ROAD,
        frame=torch.tensor(frame),
    )


# Ego in the middle lane; others ahead and behind in the outer lanes, all at 15 m/s.
HIGHWAY = [
    [0.0, 0.0, 15.0, 0.0],
    [20.0, 3.5, 15.0, 0.0],
    [-15.0, -3.5, 15.0, 0.0],
    [35.0, -3.5, 15.0, 0.0],
    [-30.0, 3.5, 15.0, 0.0],
    [50.0, 0.0, 15.0, 0.0],
]


def mask_of(num: int, rows: list[int]) -> torch.Tensor:
    mask = torch.zeros(num, dtype=torch.bool)
    mask[rows] = True
    return mask


def test_only_controllable_rows_change():
    scene = make_scene(HIGHWAY)
    result = guide(scene, mask_of(6, [1, 3]), NORMALIZER)
    fixed = [0, 2, 4, 5]
    assert torch.equal(result.u[fixed], scene.u0[fixed])
    assert torch.equal(result.actions[fixed], scene.base_actions[fixed])
    assert torch.equal(result.trajectories[fixed], scene.base_trajectories[fixed])
    for row in (1, 3):
        assert not torch.equal(result.actions[row], scene.base_actions[row])


def test_ego_and_absent_agents_are_never_guided():
    scene = dataclasses.replace(make_scene(HIGHWAY), agent_mask=mask_of(6, [0, 1, 2, 3, 4]))
    result = guide(scene, torch.ones(6, dtype=torch.bool), NORMALIZER)
    for row in (0, 5):
        assert torch.equal(result.actions[row], scene.base_actions[row])


@pytest.mark.parametrize("target", ["others", "ego"])
@pytest.mark.parametrize("optimizer", ["gradient", "adam"])
def test_lowers_adversarial_loss_and_keeps_map_loss_bounded(target, optimizer):
    scene = make_scene(HIGHWAY)
    step_size = 0.1 if optimizer == "adam" else 5e-3
    config = GuidanceConfig(target=target, optimizer=optimizer, step_size=step_size)
    result = guide(scene, mask_of(6, [1, 2, 3]), NORMALIZER, config)
    (adv_before, map_before), (adv_after, map_after) = result.losses[0], result.losses[-1]
    assert result.losses.shape == (config.steps + 1, 2)
    assert adv_after < 0.8 * adv_before
    assert map_before < 1e-6 and map_after < 0.5  # [m^2]: stays on the 12 m road
    # The reported losses are those of the returned plans.
    rows = [1, 2, 3]
    targets = [0] if target == "ego" else [0, 4, 5]
    xy, target_xy = result.trajectories[rows, :, :2], scene.base_trajectories[targets, :, :2]
    assert torch.allclose(adversarial_loss(xy, target_xy), adv_after)


def test_sign_convention_negative_weight_pushes_apart():
    scene = make_scene(HIGHWAY)
    push = guide(scene, mask_of(6, [1]), NORMALIZER, GuidanceConfig(lambda_adv=-50.0))
    assert push.losses[-1, 0] > push.losses[0, 0]


def test_map_term_pulls_a_vehicle_back_onto_the_road():
    # Heading 0.15 rad toward the edge at 15 m/s: the base plan leaves the road.
    scene = make_scene([[0.0, 0.0, 15.0, 0.0], [10.0, 3.0, 15.0, 0.15]])
    config = GuidanceConfig(lambda_adv=0.0)
    result = guide(scene, mask_of(2, [1]), NORMALIZER, config)
    assert result.losses[0, 1] > 50.0
    assert result.losses[-1, 1] < 0.05 * result.losses[0, 1]


def test_actions_stay_in_bounds_and_trajectories_follow_them():
    scene = make_scene(HIGHWAY)
    config = GuidanceConfig(optimizer="gradient", step_size=10.0)  # every step hits a bound
    result = guide(scene, mask_of(6, [1, 2]), NORMALIZER, config)
    accel, yaw_rate = result.actions[..., 0], result.actions[..., 1]
    assert accel.min() >= DEFAULT_CONFIG.accel_min and accel.max() <= DEFAULT_CONFIG.accel_max
    assert yaw_rate.abs().max() <= DEFAULT_CONFIG.yaw_rate_max
    assert (accel[[1, 2]] == DEFAULT_CONFIG.accel_min).any()  # the bounds are reached
    expected = rollout(scene.state[[1, 2]], result.actions[[1, 2]])
    assert torch.allclose(result.trajectories[[1, 2]], expected, atol=1e-4)


def test_no_controllable_agent_gives_the_base_plans():
    scene = make_scene(HIGHWAY)
    result = guide(scene, torch.zeros(6, dtype=torch.bool), NORMALIZER)
    assert torch.equal(result.actions, scene.base_actions)
    assert torch.equal(result.trajectories, scene.base_trajectories)


def test_base_plans_are_the_samplers(make_model, tiny_config):
    model = make_model(tiny_config).eval()
    batch = synthetic_batch(1, 6, seed=3, map_size=tiny_config.map_size)
    eps = torch.randn(1, 6, tiny_config.future_steps, 2, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        scene = model.encode(batch)
        u0 = base_velocity(model, eps, scene)
        actions, trajectories = plans_from_velocity(
            eps, u0, scene.state, scene.agent_mask, NORMALIZER
        )
        expected_actions, expected_trajectories = sample(model, scene, eps, NORMALIZER)
    assert torch.equal(actions, expected_actions)
    assert torch.equal(trajectories, expected_trajectories)


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


def test_config_validation():
    for bad in (
        {"steps": -1},
        {"steps": False},
        {"step_size": 0.0},
        {"lambda_map": -1.0},
        {"lambda_adv": float("nan")},
        {"horizon": 0},
        {"target": "all"},
        {"optimizer": "sgd"},
        {"map_decay": 1.5},
    ):
        with pytest.raises(ValueError, match="GuidanceConfig: "):
            GuidanceConfig(**bad)


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


def _autograd_adversarial(xy, target_xy, horizon, target_valid):
    """Each row's ``L_adv`` by plain autograd ops (the reference of the closed form)."""
    targets = target_xy if target_xy.ndim == 4 else target_xy[None].expand(len(xy), -1, -1, -1)
    distance = torch.linalg.vector_norm(xy[:, None, :horizon] - targets[:, :, :horizon], dim=-1)
    if target_valid is not None:
        distance = distance.masked_fill(~target_valid[..., None], torch.inf)
    return distance.min(dim=1).values.mean(dim=1)


def _autograd_gradient(objective, u_c, lambda_adv, lambda_map):
    """The autograd path the closed form replaces: through the rollout and both losses.
    Returns the gradient and each row's ``L_adv`` and ``L_map`` (as ``gradient`` does)."""
    with torch.inference_mode(False), torch.enable_grad():  # guide's loop runs in inference
        u_c = u_c.clone().requires_grad_(True)
        trajectories = rollout(objective.state, objective.actions(u_c), objective.dynamics)
        adv = _autograd_adversarial(
            trajectories[..., :2], objective.target_xy, objective.horizon, objective.target_valid
        )
        off_road = objective.map_term(trajectories)
        (grad,) = torch.autograd.grad(lambda_adv * adv.sum() + lambda_map * off_road, u_c)
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
    actions, trajectories = plans_from_velocity(
        scene.eps, u0, scene.state, scene.agent_mask, NORMALIZER
    )
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


def test_target_rows_others_ego_and_bad_target():
    from policies.learned.guidance_losses import target_rows

    present = torch.tensor([True, True, True, False, True])
    controllable = torch.tensor([False, True, False, False, False])
    others = target_rows(present, controllable, ego=0, target="others")
    assert others.tolist() == [True, False, True, False, True]  # absent and A_c excluded
    assert target_rows(present, controllable, ego=0, target="ego").tolist() == [
        True,
        False,
        False,
        False,
        False,
    ]
    with pytest.raises(ValueError, match="target"):
        target_rows(present, controllable, ego=0, target="everyone")


def test_map_term_is_none_without_map_or_weight():
    from types import SimpleNamespace

    from policies.learned.guidance_losses import map_term

    size = torch.ones(2)
    scene = SimpleNamespace(drivable_map=None, frame=torch.zeros(3), length=size, width=size)
    assert map_term(scene, torch.arange(2), 5, GuidanceConfig()) is None


def _padded(scene: GuidanceScene, agents: int) -> GuidanceScene:
    """``scene`` with absent agents appended up to ``agents`` (zeros, masked)."""
    extra = agents - scene.eps.shape[0]
    names = ("eps", "u0", "state", "length", "width", "agent_mask", "base_actions")
    tensors = {name: getattr(scene, name) for name in (*names, "base_trajectories")}
    return dataclasses.replace(
        scene,
        **{
            name: torch.cat([value, value.new_zeros(extra, *value.shape[1:])])
            for name, value in tensors.items()
        },
    )


@pytest.mark.parametrize("target", ["others", "ego"])
def test_batched_scenes_guide_as_each_scene_alone(target):
    """Three scenes (4, 6 and 3 agents, padded to 6) with their own maps and frames, guided
    in one loop: each scene's plans and losses are those of guiding it alone."""
    narrow = from_lanes([Lane(np.array([[-50.0, 10.0], [250.0, 40.0]]), 7.0, "narrow")])
    scenes = [
        make_scene(HIGHWAY[:4], frame=(3.0, -1.0, 0.2), seed=1),
        make_scene(HIGHWAY, seed=2),
        dataclasses.replace(
            make_scene([[0.0, 0.0, 12.0, 0.0], [12.0, 2.5, 12.0, 0.1], [-9.0, -2.0, 14.0, 0.0]],
                       frame=(-50.0, 10.0, 0.0997), seed=3),
            drivable_map=narrow,
        ),
    ]  # fmt: skip
    controllable = [mask_of(4, [1, 3]), mask_of(6, [2, 4, 5]), mask_of(3, [1, 2])]
    config = GuidanceConfig(steps=8, target=target)
    alone = [guide(s, c, NORMALIZER, config) for s, c in zip(scenes, controllable, strict=True)]
    padded = [_padded(s, 6) for s in scenes]
    batch = GuidanceScene(
        **{
            name: torch.stack([getattr(s, name) for s in padded])
            for name in ("eps", "u0", "state", "length", "width", "agent_mask", "base_actions",
                         "base_trajectories", "frame")
        },
        drivable_map=MapStack([s.drivable_map for s in scenes]),
    )  # fmt: skip
    masks = torch.stack([torch.cat([c, c.new_zeros(6 - len(c))]) for c in controllable])
    result = guide(batch, masks, NORMALIZER, config)
    assert result.losses.shape == (9, 3, 2)
    for b, single in enumerate(alone):
        count = single.actions.shape[0]
        torch.testing.assert_close(result.actions[b, :count], single.actions, rtol=0, atol=1e-5)
        torch.testing.assert_close(
            result.trajectories[b, :count], single.trajectories, rtol=0, atol=1e-4
        )
        torch.testing.assert_close(result.losses[:, b], single.losses, rtol=1e-5, atol=1e-5)
        assert torch.equal(result.trajectories[b, count:], batch.base_trajectories[b, count:])
    assert (result.losses[0, :, 1] > 0).any()  # the map term is active somewhere


def test_guide_names_bad_shapes():
    scene = make_scene(HIGHWAY)
    with pytest.raises(ValueError, match="controllable"):
        guide(scene, mask_of(5, [1]), NORMALIZER)
    with pytest.raises(ValueError, match="scene.eps"):
        guide(dataclasses.replace(scene, eps=scene.eps[0]), mask_of(6, [1]), NORMALIZER)
