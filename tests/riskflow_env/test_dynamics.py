"""Unicycle dynamics against closed-form motions, step-by-step integration and torch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from riskflow_env import dynamics
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import (
    ACCEL,
    SPEED,
    YAW,
    YAW_RATE,
    X,
    Y,
    check_actions,
    clip_actions,
    inverse,
    rollout,
    step,
    wrap_angle,
)

CONFIG = DynamicsConfig()
DT = CONFIG.dt


def _step_loop(state, actions, config=CONFIG):
    """Repeated ``step`` calls: the env's way of integrating."""
    states = []
    for t in range(actions.shape[-2]):
        state = step(state, actions[..., t, :], config)
        states.append(state)
    return np.stack(states, axis=-2) if isinstance(state, np.ndarray) else torch.stack(states, -2)


def _reference(state, actions, config=CONFIG):
    """Independent sequential integration of docs/explanation/architecture.md, clamping every
    step."""
    x, y, v, psi = np.asarray(state).tolist()
    out = []
    for a, omega in np.asarray(actions).tolist():
        a = min(max(a, config.accel_min), config.accel_max)
        omega = min(max(omega, -config.yaw_rate_max), config.yaw_rate_max)
        v_next = min(max(v + a * config.dt, config.speed_min), config.speed_max)
        if config.turn_radius_min:
            reach = (v + v_next) / (2 * config.turn_radius_min)
            omega = min(max(omega, -reach), reach)
        a_eff = (v_next - v) / config.dt
        x += math.cos(psi) * (v + 0.5 * a_eff * config.dt) * config.dt
        y += math.sin(psi) * (v + 0.5 * a_eff * config.dt) * config.dt
        v, psi = v_next, psi + omega * config.dt
        out.append((x, y, v, psi))
    return np.array(out)


def _random_actions(rng, shape, accel=(-2.0, 2.0), yaw_rate=(-0.8, 0.8)):
    return np.stack([rng.uniform(*accel, shape), rng.uniform(*yaw_rate, shape)], axis=-1)


# ----------------------------------------------------------------------- closed form


def test_one_step_matches_design_formula():
    state = np.array([1.0, -2.0, 10.0, 0.3])
    a, omega = 2.0, -0.5
    out = step(state, np.array([a, omega]))
    expected_advance = (10.0 + 0.5 * a * DT) * DT
    np.testing.assert_allclose(
        out,
        [
            1.0 + math.cos(0.3) * expected_advance,
            -2.0 + math.sin(0.3) * expected_advance,
            10.0 + a * DT,
            0.3 + omega * DT,
        ],
        atol=1e-12,
    )


def test_straight_line_at_constant_speed():
    state = np.array([5.0, -3.0, 12.0, 0.7])
    states = rollout(state, np.zeros((50, 2)))
    t = DT * np.arange(1, 51)
    np.testing.assert_allclose(states[:, X], 5.0 + 12.0 * math.cos(0.7) * t, atol=1e-9)
    np.testing.assert_allclose(states[:, Y], -3.0 + 12.0 * math.sin(0.7) * t, atol=1e-9)
    np.testing.assert_allclose(states[:, SPEED], 12.0, atol=1e-12)
    np.testing.assert_allclose(states[:, YAW], 0.7, atol=1e-12)


def test_constant_acceleration_is_exact():
    v0, a = 3.0, 1.5
    states = rollout(np.array([0.0, 0.0, v0, 0.0]), np.tile([a, 0.0], (52, 1)))
    t = DT * np.arange(1, 53)
    np.testing.assert_allclose(states[:, X], v0 * t + 0.5 * a * t**2, atol=1e-9)
    np.testing.assert_allclose(states[:, SPEED], v0 + a * t, atol=1e-9)
    np.testing.assert_allclose(states[:, Y], 0.0, atol=1e-12)


def test_braking_to_a_stop_covers_the_stopping_distance_and_stays():
    v0, a = 10.0, -4.0  # stops after exactly 2.5 s = 25 steps
    states = rollout(np.array([0.0, 0.0, v0, 0.0]), np.tile([a, 0.0], (60, 1)))
    np.testing.assert_allclose(states[24:, SPEED], 0.0, atol=1e-9)
    np.testing.assert_allclose(states[24:, X], v0**2 / (2 * -a), atol=1e-9)
    assert np.all(states[:, SPEED] >= 0.0)


def test_circle_matches_exact_discrete_solution():
    x0, y0, v, psi0, omega, steps = 1.0, 2.0, 10.0, 0.4, 0.5, 100
    states = rollout(np.array([x0, y0, v, psi0]), np.tile([0.0, omega], (steps, 1)))
    n = np.arange(1, steps + 1)
    d = omega * DT
    # sum_{k<n} cos(psi0 + k d) = sin(n d / 2) / sin(d / 2) * cos(psi0 + (n - 1) d / 2)
    gain = np.sin(n * d / 2) / np.sin(d / 2)
    np.testing.assert_allclose(
        states[:, X], x0 + v * DT * gain * np.cos(psi0 + (n - 1) * d / 2), atol=1e-9
    )
    np.testing.assert_allclose(
        states[:, Y], y0 + v * DT * gain * np.sin(psi0 + (n - 1) * d / 2), atol=1e-9
    )
    np.testing.assert_allclose(states[:, YAW], psi0 + n * d, atol=1e-12)


def _circle_error(dt, v=10.0, omega=0.5, duration=10.0):
    """Largest distance [m] to the continuous circle of radius v / omega over ``duration``."""
    steps = round(duration / dt)
    actions = np.tile([0.0, omega], (steps, 1))
    states = rollout(np.array([0.0, 0.0, v, 0.0]), actions, DynamicsConfig(dt=dt))
    radius, t = v / omega, dt * np.arange(1, steps + 1)
    exact = np.stack([radius * np.sin(omega * t), radius - radius * np.cos(omega * t)], -1)
    return np.linalg.norm(states[:, :2] - exact, axis=-1).max()


def test_circle_approaches_continuous_circle_first_order_in_dt():
    v = 10.0
    errors = [_circle_error(dt, v=v) for dt in (0.1, 0.05, 0.025)]
    # Each step moves along the heading at its start, which lags the chord by omega*dt/2:
    # the discrete circle's centre is off by about v*dt/2, so points are off by <= v*dt.
    assert errors[0] <= 1.01 * v * 0.1
    assert errors[1] / errors[0] == pytest.approx(0.5, abs=0.01)
    assert errors[2] / errors[1] == pytest.approx(0.5, abs=0.01)


# ------------------------------------------------------------- rollout versus step


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("steps", [52, 100])
def test_rollout_matches_step_loop_in_bounds(backend, steps):
    rng = np.random.default_rng(steps)
    state = np.stack(
        [
            rng.normal(0, 50, 8),
            rng.normal(0, 50, 8),
            rng.uniform(10, 25, 8),
            rng.uniform(-np.pi, np.pi, 8),
        ],
        axis=-1,
    )
    actions = _random_actions(rng, (8, steps))
    if backend == "torch":
        state, actions = torch.from_numpy(state), torch.from_numpy(actions)
    vectorised, looped = rollout(state, actions), _step_loop(state, actions)
    vectorised, looped = np.asarray(vectorised), np.asarray(looped)
    assert 0 < vectorised[..., SPEED].min() and vectorised[..., SPEED].max() < 40  # no bound hit
    np.testing.assert_allclose(vectorised[..., :2], looped[..., :2], rtol=0, atol=1e-5)
    np.testing.assert_allclose(vectorised, looped, rtol=0, atol=1e-9)
    np.testing.assert_allclose(vectorised[0], _reference(state[0], actions[0]), atol=1e-9)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_rollout_exact_when_braking_to_a_stop_and_starting_again(backend):
    # Brake hard (stops after ~1.7 s, keeps braking), then accelerate, brake, accelerate.
    accel = np.concatenate(
        [np.full(30, -6.0), np.full(22, 3.0), np.full(25, -8.0), np.full(23, 2.0)]
    )
    actions = np.stack([accel, np.full(100, 0.3)], axis=-1)
    state = np.array([0.0, 0.0, 10.0, 0.2])
    if backend == "torch":
        state, actions = torch.from_numpy(state), torch.from_numpy(actions)
    vectorised = np.asarray(rollout(state, actions))
    np.testing.assert_allclose(vectorised, np.asarray(_step_loop(state, actions)), atol=1e-9)
    np.testing.assert_allclose(vectorised, _reference(state, actions), atol=1e-9)
    assert vectorised[:, SPEED].min() == 0.0


def test_rollout_exact_at_lower_bound_for_random_stop_and_go():
    rng = np.random.default_rng(0)
    state = np.stack([np.zeros(16), np.zeros(16), rng.uniform(0, 3, 16), np.zeros(16)], -1)
    actions = _random_actions(rng, (16, 100), accel=(-8.0, 5.0))
    vectorised = rollout(state, actions)
    assert (vectorised[..., SPEED] == 0).any() and vectorised[..., SPEED].max() < 40
    np.testing.assert_allclose(vectorised, _step_loop(state, actions), atol=1e-9)


def test_rollout_exact_at_upper_bound():
    accel = np.concatenate([np.full(30, 5.0), np.full(22, -3.0)])
    actions = np.stack([accel, np.zeros(52)], axis=-1)
    state = np.array([0.0, 0.0, 37.0, 0.0])
    vectorised = rollout(state, actions)
    np.testing.assert_allclose(vectorised, _reference(state, actions), atol=1e-9)
    assert vectorised[:, SPEED].max() == 40.0


def test_both_speed_bounds_in_one_horizon_stay_bounded_and_consistent():
    # Documented approximation: speeds stay in bounds, a_eff has the sign of a and |a_eff| <= |a|.
    config = DynamicsConfig(speed_min=0.0, speed_max=5.0)
    rng = np.random.default_rng(1)
    actions = _random_actions(rng, (32, 100), accel=(-8.0, 5.0))
    state = np.stack([np.zeros(32), np.zeros(32), rng.uniform(0, 5, 32), np.zeros(32)], -1)
    states = rollout(state, actions, config)
    speed = np.concatenate([state[:, None, SPEED], states[..., SPEED]], axis=-1)
    assert speed.min() >= 0.0 and speed.max() <= 5.0
    a_eff = np.diff(speed, axis=-1) / config.dt
    assert np.all(a_eff * actions[..., ACCEL] >= -1e-9)
    assert np.all(np.abs(a_eff) <= np.abs(actions[..., ACCEL]) + 1e-9)


# -------------------------------------------------------------------------- inverse


def test_inverse_recovers_actions_with_heading_wrapped_across_pi():
    rng = np.random.default_rng(2)
    state = np.array([[0.0, 0.0, 15.0, math.pi - 0.05], [3.0, 1.0, 20.0, -math.pi + 0.05]])
    actions = _random_actions(rng, (2, 52))
    actions[0, :, YAW_RATE] = 0.9  # turns left across +pi
    actions[1, :, YAW_RATE] = -0.9  # turns right across -pi
    states = np.concatenate([state[:, None], rollout(state, actions)], axis=1)
    states[..., YAW] = wrap_angle(states[..., YAW])
    assert np.abs(np.diff(states[..., YAW], axis=-1)).max() > math.pi  # a wrap happened
    np.testing.assert_allclose(inverse(states), actions, atol=1e-9)


def test_inverse_does_not_clip_unless_asked():
    states = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.5]])
    np.testing.assert_allclose(inverse(states), [[20.0, 5.0]])
    np.testing.assert_allclose(inverse(states, clip=True), [[CONFIG.accel_max, 1.0]])


def test_wrap_angle_range():
    angles = np.array([0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 4.0, -4.0, 7.5])
    wrapped = wrap_angle(angles)
    assert np.all(wrapped > -math.pi) and np.all(wrapped <= math.pi)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-12)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(angles), atol=1e-12)
    np.testing.assert_allclose(wrapped[1:3], math.pi)
    assert float(wrap_angle(-math.pi)) == pytest.approx(math.pi)
    torch.testing.assert_close(wrap_angle(torch.from_numpy(angles)), torch.from_numpy(wrapped))


# ---------------------------------------------------------------------------- torch


def test_gradients_flow_through_rollout():
    state = torch.tensor([[1.0, 2.0, 8.0, 0.3], [0.0, -1.0, 12.0, -1.0]], dtype=torch.float64)
    actions = torch.tensor(_random_actions(np.random.default_rng(3), (2, 5)))
    state.requires_grad_(True)
    actions.requires_grad_(True)
    assert torch.autograd.gradcheck(rollout, (state, actions))


def test_torch_and_numpy_agree_with_batch_dims():
    rng = np.random.default_rng(4)
    batch, agents, steps = 3, 5, 52
    state = np.stack(
        [
            rng.normal(0, 20, (batch, agents)),
            rng.normal(0, 20, (batch, agents)),
            rng.uniform(0, 30, (batch, agents)),
            rng.uniform(-3, 3, (batch, agents)),
        ],
        axis=-1,
    )
    actions = _random_actions(rng, (batch, agents, steps), accel=(-9.0, 6.0), yaw_rate=(-1.2, 1.2))
    expected = rollout(state, actions)
    assert expected.shape == (batch, agents, steps, 4)
    got = rollout(torch.from_numpy(state), torch.from_numpy(actions))
    assert isinstance(got, torch.Tensor) and got.shape == (batch, agents, steps, 4)
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-12)
    one = step(torch.from_numpy(state), torch.from_numpy(actions[..., 0, :]))
    np.testing.assert_allclose(one.numpy(), expected[..., 0, :], atol=1e-12)


def test_leading_dims_broadcast_and_dtype_is_kept():
    state = np.array([0.0, 0.0, 10.0, 0.0], dtype=np.float32)
    actions = np.zeros((6, 52, 2), dtype=np.float32)
    states = rollout(state, actions)
    assert states.shape == (6, 52, 4) and states.dtype == np.float32
    assert step(state, actions[:, 0]).shape == (6, 4)
    torch_states = rollout(torch.from_numpy(state), torch.from_numpy(actions))
    assert torch_states.dtype == torch.float32
    assert rollout(state, np.zeros((0, 2), dtype=np.float32)).shape == (0, 4)


# --------------------------------------------------------------------- bounds, errors


def test_action_bounds_are_applied():
    config = DynamicsConfig(accel_min=-3.0, accel_max=2.0, yaw_rate_max=0.5)
    clipped = clip_actions(np.array([[-10.0, -2.0], [10.0, 2.0], [1.0, 0.1]]), config)
    np.testing.assert_allclose(clipped, [[-3.0, -0.5], [2.0, 0.5], [1.0, 0.1]])
    state = np.array([0.0, 0.0, 10.0, 0.0])
    wild = np.tile([100.0, 7.0], (10, 1))
    np.testing.assert_allclose(
        rollout(state, wild, config), rollout(state, np.tile([2.0, 0.5], (10, 1)), config)
    )


def test_speed_bounds_are_applied():
    config = DynamicsConfig(speed_min=1.0, speed_max=12.0)
    states = rollout(np.array([0.0, 0.0, 10.0, 0.0]), np.tile([5.0, 0.0], (20, 1)), config)
    np.testing.assert_allclose(states[4:, SPEED], 12.0)
    states = rollout(np.array([0.0, 0.0, 10.0, 0.0]), np.tile([-8.0, 0.0], (20, 1)), config)
    np.testing.assert_allclose(states[11:, SPEED], 1.0)
    np.testing.assert_allclose(np.diff(states[11:, X]), 1.0 * config.dt)


@pytest.mark.parametrize("backend", [np.asarray, torch.from_numpy])
def test_a_standing_vehicle_does_not_turn(backend):
    """A car turns only while it rolls: at rest a commanded yaw rate leaves the heading."""
    start, actions = np.array([3.0, -1.0, 0.0, 0.3]), np.tile([0.0, 1.0], (20, 1))
    states = rollout(backend(start), backend(actions))
    np.testing.assert_array_equal(np.asarray(states)[:, YAW], 0.3)
    np.testing.assert_array_equal(np.asarray(states)[:, :2], [[3.0, -1.0]] * 20)


def test_turns_no_tighter_than_the_turning_radius():
    """At 2 m/s a full yaw rate (1 rad/s, a 2 m circle) turns on the 5 m circle; at 10
    m/s (a 10 m circle) the bound is not reached."""
    for speed, expected in ((2.0, 2.0 / CONFIG.turn_radius_min), (10.0, 1.0)):
        states = rollout(np.array([0.0, 0.0, speed, 0.0]), np.tile([0.0, 1.0], (30, 1)))
        np.testing.assert_allclose(np.diff(states[:, YAW]) / DT, expected, rtol=1e-12)


def test_without_the_turning_bound_a_vehicle_turns_in_place():
    config = DynamicsConfig(turn_radius_min=0.0)
    states = rollout(np.array([0.0, 0.0, 0.0, 0.3]), np.tile([0.0, 1.0], (10, 1)), config)
    np.testing.assert_allclose(states[-1, YAW], 1.3)
    np.testing.assert_array_equal(states[:, :2], 0.0)
    with pytest.raises(ValueError, match="turn_radius_min must be >= 0 m"):
        DynamicsConfig(turn_radius_min=-1.0)


@pytest.mark.parametrize("backend", [np.asarray, torch.tensor])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_check_actions_rejects_non_finite(backend, value):
    with pytest.raises(ValueError, match=r"actions\['car_3'\] must be finite"):
        check_actions(backend([[1.0, 0.0], [value, 0.1]]), name="actions['car_3']")


@pytest.mark.parametrize("bad", [np.zeros(3), np.zeros((4, 3)), torch.zeros(2, 1), np.float64(1)])
def test_check_actions_rejects_wrong_shape(bad):
    with pytest.raises(ValueError, match=r"my_actions must have shape \(\.\.\., 2\)"):
        check_actions(bad, name="my_actions")


def test_check_actions_accepts_and_converts():
    assert isinstance(check_actions([1.0, -0.2]), np.ndarray)
    tensor = torch.zeros(3, 2)
    assert check_actions(tensor) is tensor
    with pytest.raises(ValueError, match="plan must be numeric"):
        check_actions(["fast", "left"], name="plan")
    with pytest.raises(ValueError, match="plan must have a real numeric dtype"):
        check_actions(np.array([True, False]), name="plan")


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"state must have shape \(\.\.\., 4\)"):
        rollout(np.zeros(3), np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"actions must have shape \(\.\.\., T, 2\)"):
        rollout(np.zeros(4), np.zeros(2))
    with pytest.raises(ValueError, match=r"states must have shape \(\.\.\., T, 4\)"):
        inverse(np.zeros(4))


def test_public_constants():
    assert (dynamics.X, dynamics.Y, dynamics.SPEED, dynamics.YAW) == (0, 1, 2, 3)
    assert (dynamics.STATE_DIM, dynamics.ACTION_DIM, ACCEL, YAW_RATE) == (4, 2, 0, 1)
    assert Y == 1


def test_rollout_without_clip_equals_with_clip_for_actions_in_bounds():
    """``clip=False`` (actions known to be in bounds) changes neither values nor gradients."""
    generator = torch.Generator().manual_seed(0)
    state = torch.tensor([[0.0, 0.0, 3.0, 0.2], [5.0, -2.0, 38.0, -1.0]])
    actions = torch.rand(2, 40, 2, generator=generator) * torch.tensor([13.0, 2.0])
    actions = (actions - torch.tensor([8.0, 1.0])).requires_grad_(True)  # hits both speed bounds
    clipped = rollout(state, actions)
    unclipped = rollout(state, actions, clip=False)
    assert torch.equal(clipped, unclipped)
    weights = torch.randn(clipped.shape, generator=generator)
    (expected,) = torch.autograd.grad(clipped, actions, weights)
    (got,) = torch.autograd.grad(unclipped, actions, weights)
    assert torch.equal(got, expected)
