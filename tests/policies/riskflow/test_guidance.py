"""Output-space guidance: masked to A_c, lowers L_adv with a bounded L_map, bounds, signs
(closed forms and gradients: ``test_guidance_gradients.py``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import policies.learned.guidance_losses as guidance_losses
from policies.learned.guidance_losses import HORIZONS, HUMAN_ACCEL, HUMAN_YAW_RATE, KEEP_MOVING
from policies.learned.plan_overlap import pair_separation
from policies.learned.sampler import base_velocity, decode_plans, sample
from policies.learned.synthetic import synthetic_batch
from policies.riskflow.guidance import (
    GuidanceConfig,
    GuidanceScene,
    adversarial_loss,
    guide,
)
from policies.stress.failures import HUMAN_BOUNDS
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout
from riskflow_env.maps import Lane, MapStack, from_lanes
from tests.policies.riskflow.guidance_scenes import (
    HIGHWAY,
    NORMALIZER,
    STEPS,
    make_scene,
    mask_of,
)


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


@pytest.mark.parametrize("lambda_sep", [0.0, GuidanceConfig.lambda_sep])
@pytest.mark.parametrize("target", ["others", "ego"])
@pytest.mark.parametrize("optimizer", ["gradient", "adam"])
def test_lowers_adversarial_loss_and_keeps_map_loss_bounded(target, optimizer, lambda_sep):
    scene = make_scene(HIGHWAY)
    step_size = 5e-3 if optimizer == "gradient" else 0.1
    # over the whole plan (the default with "ego" is 3 s: test_horizon_defaults_per_target)
    config = GuidanceConfig(
        target=target, optimizer=optimizer, step_size=step_size, lambda_sep=lambda_sep,
        horizon=STEPS,
    )  # fmt: skip
    result = guide(scene, mask_of(6, [1, 2, 3]), NORMALIZER, config)
    (adv_before, map_before), (adv_after, map_after) = result.losses[0], result.losses[-1]
    assert result.losses.shape == (config.steps + 1, 2)
    assert adv_after < 0.8 * adv_before
    # [m^2]: stays on the 12 m road. With the separation term (the default) three cars
    # closing on one ego spread across it and may graze its edge.
    assert map_before < 1e-6 and map_after < (0.5 if lambda_sep == 0 else 1.0)
    # The reported losses are those of the returned plans.
    rows = [1, 2, 3]
    targets = [0] if target == "ego" else [0, 4, 5]
    xy, target_xy = result.trajectories[rows, :, :2], scene.base_trajectories[targets, :, :2]
    assert torch.allclose(adversarial_loss(xy, target_xy), adv_after)


def test_separation_term_keeps_the_guided_vehicles_apart():
    """Two guided cars in the outer lanes closing on the ego ahead: without ``L_sep`` their
    guided boxes overlap each other near the ego; with it they do not, and they still
    close on the ego (a little less)."""
    scene = make_scene(
        [[30.0, 0.0, 8.0, 0.0], [0.0, 3.5, 14.0, 0.0], [0.0, -3.5, 14.0, 0.0], [-40, 3.5, 10, 0]]
    )
    rows = [1, 2]
    penetration, adversarial = [], []
    for weight in (0.0, 20.0):
        config = GuidanceConfig(target="ego", lambda_sep=weight, horizon=STEPS)
        result = guide(scene, mask_of(4, rows), NORMALIZER, config)
        gaps = pair_separation(
            result.trajectories[None, rows], scene.length[None, rows], scene.width[None, rows]
        )[0, 0, 1]
        penetration.append(float(torch.relu(-gaps).square().sum()))
        adversarial.append(float(result.losses[-1, 0]))
    assert penetration[0] > 1.0 and penetration[1] == 0.0
    assert adversarial[0] < adversarial[1] < 0.9 * float(result.losses[0, 0])


def test_attacker_of_the_ego_drives_around_a_parked_car_not_through_it():
    """Target ``"ego"``: the attacker's way to the ego crosses a car parked half across
    the lane line, which keeps its plan (a bystander). Without ``L_sep`` the guided plan
    runs into the parked car; with it the plan clears it and still closes on the ego."""
    scene = make_scene([[30.0, 0.0, 10.0, 0.0], [0.0, 3.5, 15.0, -0.05], [20.0, 1.5, 0.0, 0.0]])
    penetration, adversarial = [], []
    for weight in (0.0, GuidanceConfig.lambda_sep):
        result = guide(
            scene, mask_of(3, [1]), NORMALIZER, GuidanceConfig(target="ego", lambda_sep=weight)
        )
        assert torch.equal(result.trajectories[2], scene.base_trajectories[2])
        gaps = pair_separation(
            result.trajectories[None, [1, 2]], scene.length[None, [1, 2]], scene.width[None, [1, 2]]
        )[0, 0, 1]
        penetration.append(float(torch.relu(-gaps).square().sum()))
        adversarial.append(float(result.losses[-1, 0]))
    assert penetration[0] > 1.0 and penetration[1] == 0.0
    assert adversarial[1] < 0.85 * float(result.losses[0, 0])


def test_horizon_defaults_per_target():
    """``T_g``: the whole plan with "others", 3 s with "ego" (``HORIZONS``); a given
    horizon wins; a copy with another target (a curriculum's) takes that target's."""
    assert GuidanceConfig().resolved_horizon is None
    assert GuidanceConfig(target="ego").resolved_horizon == HORIZONS["ego"] == 30
    assert GuidanceConfig(target="ego", horizon=12).resolved_horizon == 12
    assert dataclasses.replace(GuidanceConfig(), target="ego").resolved_horizon == 30
    # the objective scores L_adv over the resolved horizon only (a car catching up: its
    # distance to the ego changes over the plan)
    scene = make_scene([[0.0, 0.0, 15.0, 0.0], [-20.0, 3.5, 20.0, 0.0]])
    result = guide(scene, mask_of(2, [1]), NORMALIZER, GuidanceConfig(target="ego", steps=0))
    xy, ego_xy = scene.base_trajectories[[1], :, :2], scene.base_trajectories[[0], :, :2]
    assert torch.allclose(result.losses[0, 0], adversarial_loss(xy, ego_xy, horizon=30))
    assert not torch.allclose(result.losses[0, 0], adversarial_loss(xy, ego_xy))


def test_attacker_of_the_ego_brakes_within_the_human_bound():
    """A car ahead of a slower ego closes on it by braking: attacking the ego it brakes at
    ``HUMAN_ACCEL`` at most (the failure analysis's human bound); with the paper's
    target the dynamics' bound (8 m/s^2) is the limit."""
    assert HUMAN_ACCEL == HUMAN_BOUNDS.accel
    scene = make_scene([[0.0, 0.0, 8.0, 0.0], [25.0, 0.0, 20.0, 0.0]])
    braking = {}
    for target in ("ego", "others"):
        config = GuidanceConfig(target=target, step_size=0.3, steps=60)
        result = guide(scene, mask_of(2, [1]), NORMALIZER, config)
        assert result.losses[-1, 0] < 0.9 * result.losses[0, 0]
        braking[target] = -float(result.actions[1, :, 0].min())
    assert braking["ego"] == pytest.approx(HUMAN_ACCEL)
    assert braking["others"] == pytest.approx(-DEFAULT_CONFIG.accel_min)


def test_attacker_of_the_ego_turns_within_the_human_bound():
    """A car driving away beside a slow ego turns back toward it: attacking the ego its yaw
    rate stays within ``HUMAN_YAW_RATE`` (the failure analysis's human bound); with the
    paper's target the dynamics' bound (1 rad/s) is the limit."""
    assert HUMAN_YAW_RATE == HUMAN_BOUNDS.yaw_rate < DEFAULT_CONFIG.yaw_rate_max
    scene = make_scene([[0.0, 0.0, 6.0, 0.0], [0.0, 6.0, 6.0, 1.5]])
    turning = {}
    for target in ("ego", "others"):
        config = GuidanceConfig(target=target, step_size=0.3, steps=60, lambda_map=0.0)
        result = guide(scene, mask_of(2, [1]), NORMALIZER, config)
        assert result.losses[-1, 0] < 0.9 * result.losses[0, 0]
        turning[target] = float(result.actions[1, :, 1].abs().max())
    assert turning["ego"] == pytest.approx(HUMAN_YAW_RATE)
    assert turning["others"] == pytest.approx(DEFAULT_CONFIG.yaw_rate_max)


def test_attacker_of_the_ego_keeps_moving(monkeypatch):
    """A car ahead of a slow ego closes on it by braking: attacking the ego it keeps
    moving near ``KEEP_MOVING`` over the guidance horizon (a soft floor), where without
    the floor it brakes to a standstill in the lane."""
    scene = make_scene([[0.0, 0.0, 3.0, 0.0], [12.0, 0.0, 10.0, 0.0]])
    config = GuidanceConfig(target="ego", step_size=0.3, steps=60)
    horizon = config.resolved_horizon

    def slowest() -> float:
        result = guide(scene, mask_of(2, [1]), NORMALIZER, config)
        assert result.losses[-1, 0] < 0.8 * result.losses[0, 0]  # it still attacks
        return float(result.trajectories[1, :horizon, 2].min())

    assert slowest() > 0.75 * KEEP_MOVING  # a soft floor: 1.8 m/s here
    monkeypatch.setattr(guidance_losses, "LAMBDA_KEEP_MOVING", 0.0)
    assert slowest() < 0.1


def test_keep_moving_gradient_is_the_penalty_slope():
    """``keep_moving_gradient`` is the derivative of ``LAMBDA_KEEP_MOVING * sum_t
    relu(floor - v_t)^2`` over the horizon (autograd), 0 above the floor and beyond it."""
    speed = torch.tensor([[5.0, 3.0, 1.0, 0.0], [2.0, 2.5, 6.0, 1.0]], requires_grad=True)
    floor = torch.tensor([4.0, 2.0])
    horizon = 3
    penalty = torch.relu(floor[:, None] - speed)[:, :horizon].square().sum()
    (expected,) = torch.autograd.grad(guidance_losses.LAMBDA_KEEP_MOVING * penalty, speed)
    got = guidance_losses.keep_moving_gradient(speed.detach(), floor, horizon)
    assert torch.allclose(got, expected)
    assert got[0, 0] == 0 and got[0, 3] == 0 and got[1, :3].eq(0).all()


def test_sign_convention_negative_weight_pushes_apart():
    scene = make_scene(HIGHWAY)
    push = guide(scene, mask_of(6, [1]), NORMALIZER, GuidanceConfig(lambda_adv=-50.0))
    assert push.losses[-1, 0] > push.losses[0, 0]


def test_map_term_pulls_a_vehicle_back_onto_the_road():
    # Heading 0.15 rad toward the edge at 15 m/s: the base plan leaves the road.
    scene = make_scene([[0.0, 0.0, 15.0, 0.0], [10.0, 3.0, 15.0, 0.15]])
    # At the step 0.03: the default with the paper's target (0.01) moves a plan a third as
    # far in the 30 steps of one cycle, and closed loop takes several cycles for it.
    config = GuidanceConfig(lambda_adv=0.0, step_size=0.03)
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
        actions, trajectories = decode_plans(eps + u0, scene.state, scene.agent_mask, NORMALIZER)
        expected_actions, expected_trajectories = sample(model, scene, eps, NORMALIZER)
    assert torch.equal(actions, expected_actions)
    assert torch.equal(trajectories, expected_trajectories)


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
        {"optimizer": "adam-plan"},
        {"lambda_sep": -1.0},
        {"lambda_sep": float("nan")},
    ):
        with pytest.raises(ValueError, match="GuidanceConfig: "):
            GuidanceConfig(**bad)


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


@pytest.mark.parametrize(("target", "lambda_sep"), [("others", 0.0), ("ego", 0.0), ("ego", 50.0)])
def test_batched_scenes_guide_as_each_scene_alone(target, lambda_sep):
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
    config = GuidanceConfig(steps=8, target=target, lambda_sep=lambda_sep)
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
