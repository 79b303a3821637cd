"""The rollout's closed-form vector-Jacobian product against torch autograd of the rollout."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, rollout, rollout_vjp, rollout_with_vjp

CONFIG = DynamicsConfig(speed_max=20.0)  # [m/s]: low enough to reach both bounds in 52 steps
TOP = CONFIG.speed_max
AGENTS, STEPS = 6, 52


def _state(rng, speed):
    return np.stack(
        [
            rng.normal(0.0, 10.0, AGENTS),
            rng.normal(0.0, 10.0, AGENTS),
            np.broadcast_to(speed, (AGENTS,)),
            rng.uniform(-3.0, 3.0, AGENTS),
        ],
        axis=-1,
    )


def _actions(rng, accel):
    yaw_rate = rng.uniform(-0.9, 0.9, (AGENTS, STEPS))
    return np.stack([np.broadcast_to(accel, (AGENTS, STEPS)), yaw_rate], axis=-1)


def _scenario(name, rng):
    """(state (A, 4), actions (A, T, 2), clip, which speed bounds the rollout reaches)."""
    if name == "free":  # no bound reached
        return _state(rng, rng.uniform(10, 20, AGENTS)), _actions(rng, rng.uniform(-1, 1)), False
    if name == "clipped":  # actions beyond the accel and yaw-rate bounds, some exactly on them
        actions = np.stack(
            [rng.uniform(-10, 7, (AGENTS, STEPS)), rng.uniform(-1.3, 1.3, (AGENTS, STEPS))], -1
        )
        actions[:, ::7] = [CONFIG.accel_min, CONFIG.yaw_rate_max]
        actions[:, 3::7] = [CONFIG.accel_max, -CONFIG.yaw_rate_max]
        return _state(rng, rng.uniform(5, 30, AGENTS)), actions, True
    if name == "lower":  # brakes to a stop, stays there, drives off again
        accel = np.where(np.arange(STEPS) < 30, -3.0, 2.0) + rng.uniform(-1, 1, (AGENTS, STEPS))
        return _state(rng, rng.uniform(0, 3, AGENTS)), _actions(rng, accel), False
    if name == "upper":
        accel = rng.uniform(-2, 5, (AGENTS, STEPS))
        return _state(rng, rng.uniform(TOP - 3, TOP, AGENTS)), _actions(rng, accel), False
    if name == "both":  # to the top speed, full braking to 0, off again: both reflections
        accel = np.select([np.arange(STEPS) < 5, np.arange(STEPS) < 40], [5.0, -8.0], 3.0)
        return _state(rng, TOP - 1.0), _actions(rng, accel), False
    if name == "ties_at_zero":  # standing still exactly: every step ties the running max
        accel = np.where((np.arange(STEPS) >= 10) & (np.arange(STEPS) < 20), -1.0, 0.0)
        accel = np.where(np.arange(STEPS) >= 30, 2.0, accel)
        return _state(rng, 0.0), _actions(rng, accel), True
    if name == "ties_at_max":  # at the top speed exactly, pushing on and off the bound
        accel = np.resize([5.0, -5.0, 0.0], STEPS)
        return _state(rng, TOP), _actions(rng, accel), True
    raise ValueError(name)


SCENARIOS = ("free", "clipped", "lower", "upper", "both", "ties_at_zero", "ties_at_max")
REACHES = {
    "lower": (0.0,),
    "upper": (TOP,),
    "both": (0.0, TOP),
    "ties_at_zero": (0.0,),
    "ties_at_max": (TOP,),
}


def _autograd(state, actions, cotangent, clip):
    actions = torch.tensor(actions, requires_grad=True)
    trajectories = rollout(torch.tensor(state), actions, CONFIG, clip=clip)
    (gradient,) = torch.autograd.grad(trajectories, actions, torch.tensor(cotangent))
    return gradient.numpy()


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("name", SCENARIOS)
def test_vjp_is_autograd_of_the_rollout(name, backend):
    rng = np.random.default_rng(SCENARIOS.index(name))
    state, actions, clip = _scenario(name, rng)
    speeds = rollout(state, actions, CONFIG)[..., SPEED]
    for bound in REACHES.get(name, ()):
        assert np.any(speeds == bound), f"{name} must reach {bound} m/s"
    cotangent = rng.standard_normal((AGENTS, STEPS, 4))
    expected = _autograd(state, actions, cotangent, clip)
    convert = torch.tensor if backend == "torch" else np.asarray
    got = rollout_vjp(convert(state), convert(actions), convert(cotangent), CONFIG, clip=clip)
    assert type(got) is type(convert(state)) and got.shape == actions.shape
    scale = np.abs(expected).max()
    np.testing.assert_allclose(np.asarray(got), expected, rtol=0, atol=1e-12 * scale)


def test_stopped_vehicle_gets_exactly_zero_gradient_on_braking():
    """Braking while stopped moves nothing: exactly 0 (no rounding residue), and the
    acceleration that drives off again is not affected by the braking before it."""
    state = np.array([[0.0, 0.0, 1.0, 0.0]])
    accel = np.where(np.arange(STEPS) < 30, -2.0, 1.0)
    actions = np.stack([accel, np.full(STEPS, 0.1)], -1)[None]
    cotangent = np.random.default_rng(0).standard_normal((1, STEPS, 4))
    gradient = rollout_vjp(state, actions, cotangent, CONFIG)
    stopped = rollout(state, actions, CONFIG)[0, :, SPEED] == 0.0
    last_stop = int(np.nonzero(stopped)[0].max())
    assert last_stop >= 20
    # a_k for k <= the last step at the bound cannot change any speed
    assert np.all(gradient[0, 5 : last_stop + 1, 0] == 0.0)
    np.testing.assert_allclose(
        gradient, _autograd(state, actions, cotangent, True), rtol=0, atol=1e-12
    )


@pytest.mark.parametrize(
    ("state_shape", "actions_shape"),
    [((AGENTS, 4), (2, AGENTS, STEPS, 2)), ((2, AGENTS, 4), (AGENTS, STEPS, 2))],
)
def test_vjp_sums_over_broadcast_dimensions(state_shape, actions_shape):
    rng = np.random.default_rng(1)
    state = np.concatenate(
        [rng.normal(0, 5, state_shape[:-1] + (2,)), rng.uniform(0, 3, state_shape[:-1] + (2,))],
        axis=-1,
    )
    actions = np.stack(
        [rng.uniform(-6, 4, actions_shape[:-1]), rng.uniform(-1, 1, actions_shape[:-1])], -1
    )
    trajectories, vjp = rollout_with_vjp(state, actions, CONFIG)
    cotangent = rng.standard_normal(trajectories.shape)
    expected = _autograd(state, actions, cotangent, True)
    np.testing.assert_allclose(vjp(cotangent), expected, rtol=0, atol=1e-12 * abs(expected).max())


def test_forward_is_rollout_and_cotangent_shape_is_checked():
    rng = np.random.default_rng(2)
    state, actions, _ = _scenario("lower", rng)
    trajectories, vjp = rollout_with_vjp(state, actions, CONFIG)
    assert np.array_equal(trajectories, rollout(state, actions, CONFIG))
    with pytest.raises(ValueError, match="cotangent"):
        vjp(np.zeros((AGENTS, STEPS, 2)))
    with pytest.raises(ValueError, match="cotangent"):
        vjp(np.zeros((AGENTS, STEPS - 1, 4)))


def test_float32_vjp_matches_float64_to_rounding():
    rng = np.random.default_rng(3)
    state, actions, _ = _scenario("lower", rng)
    cotangent = rng.standard_normal((AGENTS, STEPS, 4))
    exact = rollout_vjp(state, actions, cotangent, CONFIG)
    single = rollout_vjp(
        *(torch.tensor(a, dtype=torch.float32) for a in (state, actions)),
        torch.tensor(cotangent, dtype=torch.float32),
        CONFIG,
    )
    assert single.dtype == torch.float32
    np.testing.assert_allclose(single.numpy(), exact, rtol=0, atol=1e-4 * abs(exact).max())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_each_row_gets_the_vjp_it_gets_alone(dtype):
    """A row's gradient does not depend on the rows batched with it: a row that no speed
    bound touches gets the same bits whether or not another row brakes to a stop (batched
    planning equals planning each scene alone)."""
    rng = np.random.default_rng(3)
    state = torch.tensor(_state(rng, rng.uniform(10, 20, AGENTS)), dtype=dtype)
    actions = torch.tensor(_actions(rng, rng.uniform(-1, 1)), dtype=dtype)
    state[-1, SPEED] = 1.0
    actions[-1, :, 0] = -3.0  # the last row stops within the horizon: the lower bound
    cotangent = torch.tensor(rng.normal(size=(AGENTS, STEPS, 4)), dtype=dtype)
    together = rollout_vjp(state, actions, cotangent, CONFIG)
    for row in range(AGENTS):
        alone = rollout_vjp(
            state[row : row + 1], actions[row : row + 1], cotangent[row : row + 1], CONFIG
        )
        assert torch.equal(together[row : row + 1], alone)
