"""Unicycle dynamics: bounds, one-step update, vectorised rollout and inverse.

One implementation, written against the array API, serves numpy arrays (the env,
float32 or float64) and torch tensors (policies: differentiable, any device).

State ``(..., 4)`` = ``(x [m], y [m], v [m/s], psi [rad])``; action ``(..., 2)`` =
``(accel [m/s^2], yaw_rate [rad/s])``. Semi-implicit scheme (DESIGN.md section 4),
applied in this order, with the heading *before* the step in the position update::

    x   += cos(psi) * (v + 0.5 * a * dt) * dt
    y   += sin(psi) * (v + 0.5 * a * dt) * dt
    v   += a * dt
    psi += omega * dt

Bounds (``DynamicsConfig``, defaults in brackets): the commanded acceleration is
clipped to ``[accel_min, accel_max]`` [-8, 5 m/s^2] and the yaw rate to
``[-yaw_rate_max, yaw_rate_max]`` [1 rad/s] by :func:`clip_actions`; these are the
model's physical limits. Speed is kept in ``[speed_min, speed_max]`` [0, 40 m/s]:
the effective acceleration ``a_eff = (v_next - v) / dt`` is what the bounded speed
implies, and the position uses it, i.e. the position increment is
``0.5 * (v + v_next) * dt * cos(psi)``. ``a_eff`` has the sign of ``a`` and
``|a_eff| <= |a|``. The heading is never wrapped by the dynamics (it stays
continuous, which keeps gradients and yaw-rate recovery simple); wrap it with
:func:`wrap_angle` where a bounded angle is needed.

:func:`step` is :func:`rollout` with one action, so the env's step-by-step
integration and the policies' vectorised rollout cannot drift apart.
"""

from __future__ import annotations

import math

import numpy as np

from riskflow_env._array import Array, cummax, namespace
from riskflow_env.config import DynamicsConfig

X, Y, SPEED, YAW = 0, 1, 2, 3
STATE_DIM = 4
ACCEL, YAW_RATE = 0, 1
ACTION_DIM = 2

DEFAULT_CONFIG = DynamicsConfig()

__all__ = [
    "ACCEL",
    "ACTION_DIM",
    "DEFAULT_CONFIG",
    "SPEED",
    "STATE_DIM",
    "X",
    "Y",
    "YAW",
    "YAW_RATE",
    "check_actions",
    "clip_actions",
    "inverse",
    "rollout",
    "step",
    "wrap_angle",
]


def _require_last_dim(x: Array, size: int, name: str, min_ndim: int = 1) -> None:
    shape = tuple(x.shape)
    if len(shape) < min_ndim or shape[-1] != size:
        lead = "..., T, " if min_ndim == 2 else "..., "
        raise ValueError(f"{name} must have shape ({lead}{size}), got {shape}")


def check_actions(actions: Array, name: str = "actions") -> Array:
    """Validate actions at an API boundary (the env) and return them as an array.

    Args:
        actions: ``(..., 2)`` ``(accel [m/s^2], yaw_rate [rad/s])``; numpy array,
            torch tensor, or anything ``numpy.asarray`` accepts.
        name: argument name used in the error message (e.g. ``"actions['ego']"``).

    Returns:
        ``actions`` unchanged if it already is a numpy array or torch tensor, else
        as a float64 numpy array. Values are not clipped.

    Raises:
        ValueError: naming ``name``, if the values are not numeric, the last
            dimension is not 2, or any value is NaN or infinite.
    """
    try:
        xp = namespace(actions)
    except TypeError:
        try:
            actions = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(
                f"{name} must be numeric (accel [m/s^2], yaw_rate [rad/s]) pairs, got {err}"
            ) from None
        xp = np
    _require_last_dim(actions, ACTION_DIM, name)
    if not xp.isdtype(actions.dtype, ("real floating", "integral")):
        raise ValueError(f"{name} must have a real numeric dtype, got {actions.dtype}")
    bad = int(xp.sum(xp.astype(~xp.isfinite(actions), xp.int64)))
    if bad:
        raise ValueError(f"{name} must be finite, got {bad} NaN or inf value(s)")
    return actions


def clip_actions(actions: Array, config: DynamicsConfig = DEFAULT_CONFIG) -> Array:
    """Clip actions to the model's physical limits.

    Args:
        actions: ``(..., 2)`` ``(accel [m/s^2], yaw_rate [rad/s])``.
        config: bounds ``accel_min, accel_max`` [m/s^2] and ``yaw_rate_max`` [rad/s].

    Returns:
        ``(..., 2)`` with accel in ``[accel_min, accel_max]`` and yaw rate in
        ``[-yaw_rate_max, yaw_rate_max]``. Gradients are zero where a bound is active.
    """
    _require_last_dim(actions, ACTION_DIM, "actions")
    xp = namespace(actions)
    accel = xp.clip(actions[..., ACCEL], config.accel_min, config.accel_max)
    yaw_rate = xp.clip(actions[..., YAW_RATE], -config.yaw_rate_max, config.yaw_rate_max)
    return xp.stack([accel, yaw_rate], axis=-1)


def _bounded_speed(v0: Array, accel: Array, config: DynamicsConfig) -> Array:
    """Speeds ``(..., T)`` after each step, kept in ``[speed_min, speed_max]``.

    The unbounded path is ``S_t = v0 + dt * cumsum(a)_t``. The lower bound is the
    Skorokhod reflection ``S_t + max(0, max_{k<=t}(speed_min - S_k))``, which equals
    clamping after every step exactly. The upper bound applies the same reflection
    to that result. This is exact when only one bound is reached within the horizon;
    when both are reached it approximates sequential clamping (the speed is then
    clipped into the bounds, and the effective acceleration still has the sign of
    the commanded one and no larger magnitude). With the default bounds, reaching
    both needs at least (40 - 0) / 8 = 5 s of full braking.
    """
    xp = namespace(v0, accel)
    free = v0 + config.dt * xp.cumulative_sum(accel, axis=-1)
    lower = free + xp.clip(cummax(config.speed_min - free, axis=-1), 0.0, None)
    both = lower - xp.clip(cummax(lower - config.speed_max, axis=-1), 0.0, None)
    return xp.clip(both, config.speed_min, config.speed_max)


def _shift_in(first: Array, seq: Array) -> Array:
    """``(..., T)`` sequence of values before each step: ``[first, seq_0, ..., seq_{T-2}]``."""
    xp = namespace(first, seq)
    first = xp.broadcast_arrays(first, seq[..., :1])[0]  # leading dims may broadcast
    return xp.concat([first, seq[..., :-1]], axis=-1)


def rollout(
    state: Array, actions: Array, config: DynamicsConfig = DEFAULT_CONFIG, clip: bool = True
) -> Array:
    """Integrate a sequence of actions from one state, vectorised over time.

    No Python loop over time: speed, heading and position are cumulative sums,
    so this runs as a handful of array ops and is differentiable in torch.

    Args:
        state: ``(..., 4)`` initial ``(x [m], y [m], v [m/s], psi [rad])``.
        actions: ``(..., T, 2)`` ``(accel [m/s^2], yaw_rate [rad/s])`` applied at
            steps ``0 .. T-1``; clipped to the bounds (:func:`clip_actions`).
            Leading dimensions broadcast with ``state``'s, e.g. ``(B, A, 4)`` with
            ``(B, A, T, 2)``.
        config: time step ``dt`` [s] and bounds.
        clip: False when the caller guarantees the actions lie within the bounds (a
            projected optimiser): the clip, then the identity, is skipped (same values
            and gradients, fewer ops in an autograd graph).

    Returns:
        ``(..., T, 4)`` the states *after* each action (the initial state is not
        included). Speeds lie in ``[speed_min, speed_max]``; the heading is
        continuous (not wrapped).
    """
    _require_last_dim(state, STATE_DIM, "state")
    _require_last_dim(actions, ACTION_DIM, "actions", min_ndim=2)
    xp = namespace(state, actions)
    dt = config.dt
    if clip:
        actions = clip_actions(actions, config)
    x0, y0 = state[..., X, None], state[..., Y, None]  # (..., 1)
    v0, psi0 = state[..., SPEED, None], state[..., YAW, None]

    speed = _bounded_speed(v0, actions[..., ACCEL], config)  # (..., T)
    yaw = psi0 + dt * xp.cumulative_sum(actions[..., YAW_RATE], axis=-1)
    speed_before = _shift_in(v0, speed)
    yaw_before = _shift_in(psi0, yaw)
    distance = 0.5 * (speed_before + speed) * dt  # (..., T) [m], uses a_eff
    x = x0 + xp.cumulative_sum(distance * xp.cos(yaw_before), axis=-1)
    y = y0 + xp.cumulative_sum(distance * xp.sin(yaw_before), axis=-1)
    x, y, speed, yaw = xp.broadcast_arrays(x, y, speed, yaw)
    return xp.stack([x, y, speed, yaw], axis=-1)


def step(state: Array, action: Array, config: DynamicsConfig = DEFAULT_CONFIG) -> Array:
    """Advance one time step (:func:`rollout` with ``T = 1``).

    Args:
        state: ``(..., 4)`` ``(x [m], y [m], v [m/s], psi [rad])``.
        action: ``(..., 2)`` ``(accel [m/s^2], yaw_rate [rad/s])``, clipped to bounds.
        config: time step ``dt`` [s] and bounds.

    Returns:
        ``(..., 4)`` the state ``dt`` later (leading dimensions broadcast).
    """
    _require_last_dim(action, ACTION_DIM, "action")
    return rollout(state, action[..., None, :], config)[..., 0, :]


def inverse(states: Array, config: DynamicsConfig = DEFAULT_CONFIG, clip: bool = False) -> Array:
    """Actions that reproduce speeds and headings of a state sequence.

    ``accel = dv / dt`` and ``yaw_rate = wrap_angle(dpsi) / dt``, so a heading that
    jumps across +-pi is handled. Positions are not used: a logged trajectory is
    reproduced exactly in speed and heading, and in position only as far as it
    follows this model.

    Args:
        states: ``(..., T + 1, 4)`` ``(x [m], y [m], v [m/s], psi [rad])``; the first
            one is the initial state.
        config: time step ``dt`` [s] and bounds.
        clip: if True, clip the result with :func:`clip_actions`; by default the
            actions are returned as measured, possibly outside the bounds.

    Returns:
        ``(..., T, 2)`` ``(accel [m/s^2], yaw_rate [rad/s])``.
    """
    _require_last_dim(states, STATE_DIM, "states", min_ndim=2)
    xp = namespace(states)
    accel = (states[..., 1:, SPEED] - states[..., :-1, SPEED]) / config.dt
    yaw_rate = wrap_angle(states[..., 1:, YAW] - states[..., :-1, YAW]) / config.dt
    actions = xp.stack([accel, yaw_rate], axis=-1)
    return clip_actions(actions, config) if clip else actions


def wrap_angle(angle: Array | float) -> Array:
    """Wrap angles [rad] to ``(-pi, pi]``; any shape, numpy or torch (gradient 1)."""
    if isinstance(angle, (int, float)):
        angle = np.asarray(angle, dtype=np.float64)
    xp = namespace(angle)
    return angle + (2 * math.pi) * xp.floor((math.pi - angle) / (2 * math.pi))
