"""Unicycle dynamics: bounds, one-step update, vectorised rollout and inverse.

One implementation, written against the array API, serves numpy arrays (the env,
float32 or float64) and torch tensors (policies: differentiable, any device).

State ``(..., 4)`` = ``(x [m], y [m], v [m/s], psi [rad])``; action ``(..., 2)`` =
``(accel [m/s^2], yaw_rate [rad/s])``. Semi-implicit scheme (docs/explanation/architecture.md),
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
``|a_eff| <= |a|``. The yaw rate is then kept within ``(v + v_next) / (2 *
turn_radius_min)`` [5 m]: a vehicle turns no tighter than a car at full lock, and not at
all while it stands. The heading is never wrapped by the dynamics (it stays
continuous, which keeps gradients and yaw-rate recovery simple); wrap it with
:func:`wrap_angle` where a bounded angle is needed.

:func:`step` is :func:`rollout` with one action, so the env's step-by-step
integration and the policies' vectorised rollout cannot drift apart.
:func:`rollout_with_vjp` returns the rollout with its vector-Jacobian product in closed
form (reverse cumulative sums; the speed bounds through the reflections' argmax steps),
equal to autograd of :func:`rollout` to float rounding, for gradient loops that need no
autograd (output-space guidance).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from riskflow_env._array import Array, asarray_like, cummax, device, namespace
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
    "rollout_vjp",
    "rollout_with_vjp",
    "step",
    "wrap_angle",
]


def _require_last_dim(x: Array, size: int, name: str, min_ndim: int = 1) -> None:
    shape = tuple(x.shape)
    if len(shape) < min_ndim or shape[-1] != size:
        lead = "..., T, " if min_ndim == 2 else "..., "
        raise ValueError(f"{name} must have shape ({lead}{size}), got {shape}")


def check_actions(actions: Array, name: str = "actions") -> Array:
    """Validate ``(..., 2)`` ``(accel [m/s^2], yaw_rate [rad/s])`` actions at an API
    boundary (the env): a numpy array or torch tensor is returned unchanged, anything else
    ``numpy.asarray`` accepts as float64; values are not clipped. A ``ValueError`` naming
    ``name`` (e.g. ``"actions['ego']"``) refuses non-numeric values, a last dimension
    other than 2, and NaN or inf."""
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


def _bounded_speed(v0: Array, accel: Array, config: DynamicsConfig) -> tuple[Array, tuple]:
    """Speeds ``(..., T)`` after each step, kept in ``[speed_min, speed_max]``, and what
    :func:`_bounded_speed_vjp` needs (the reflections' inputs and running maxima).

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
    below = config.speed_min - free
    below_max = cummax(below, axis=-1)
    lower = free + xp.clip(below_max, 0.0, None)
    above = lower - config.speed_max
    above_max = cummax(above, axis=-1)
    both = lower - xp.clip(above_max, 0.0, None)
    speed = xp.clip(both, config.speed_min, config.speed_max)
    return speed, (below, below_max, above, above_max, both)


def _argcummax(inner: Array, running_max: Array, steps: Array) -> Array:
    """``(..., T)`` step of each running maximum; the latest on ties, as ``torch.cummax``."""
    xp = namespace(inner)
    return cummax(xp.where(inner == running_max, steps, 0), axis=-1)


def _windows(first: Array, last: Array, steps: Array) -> Array:
    """``(..., T, T)`` bool ``[first_t <= k <= last_t]`` (row t, column k)."""
    return (steps >= first[..., None]) & (steps <= last[..., None])


def _bounded_speed_vjp(cotangent: Array, saved: tuple, config: DynamicsConfig) -> Array:
    """Cotangent ``(..., T)`` on the accelerations from the one on the speeds of
    :func:`_bounded_speed`: autograd of its forward, ties included, in closed form.

    Each speed is ``v0``, or the bound last touched, plus ``dt`` times the sum of the
    accelerations over a window of steps: after the lower reflection's argmax ``k_t``
    where it is active (its running max ``>= 0``: ``torch.clamp`` passes the gradient
    at 0), from step 0 otherwise; the upper reflection takes back the window of its
    argmax ``j_t``. So ``d speed_t / d a_k`` is ``dt`` times an exact -1/0/1 matrix:
    an action that cannot move a speed (braking while stopped) gets exactly 0, with no
    rounding residue for an optimiser to amplify.
    """
    below, below_max, above, above_max, both = saved
    xp = namespace(cotangent, below)
    lower_on, upper_on = below_max >= 0, above_max >= 0
    free = config.dt * _reverse_cumsum(cotangent, axis=-1)  # speed = v0 + dt * cumsum(a)
    # Each row by its own bounds: a row that no bound touches keeps the free path's
    # rounding whatever the rows batched with it do.
    touched = xp.any(lower_on | upper_on, axis=-1)
    if not bool(xp.any(touched)):
        return free
    upper_reached = bool(xp.any(upper_on))
    steps = xp.arange(below.shape[-1], device=device(below))
    first = xp.where(lower_on, _argcummax(below, below_max, steps) + 1, 0)  # (..., T)
    jacobian = xp.astype(_windows(first, steps, steps), cotangent.dtype)  # lower / dt
    if upper_reached:
        latest = _argcummax(above, above_max, steps)  # (..., T) j_t
        back = _windows(xp.take_along_axis(first, latest, axis=-1), latest, steps)
        jacobian = jacobian - xp.astype(back & upper_on[..., None], cotangent.dtype)
    inside = (both >= config.speed_min) & (both <= config.speed_max)  # the final clip
    cotangent = xp.where(inside, cotangent, 0.0)
    bounded = config.dt * xp.sum(cotangent[..., :, None] * jacobian, axis=-2)
    return xp.where(touched[..., None], bounded, free)


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
    return _rollout(state, actions, config, clip)[0]


def _rollout(state: Array, actions: Array, config: DynamicsConfig, clip: bool) -> tuple:
    """:func:`rollout` and what its vector-Jacobian product needs."""
    _require_last_dim(state, STATE_DIM, "state")
    _require_last_dim(actions, ACTION_DIM, "actions", min_ndim=2)
    xp = namespace(state, actions)
    dt = config.dt
    commanded = actions
    if clip:
        actions = clip_actions(actions, config)
    x0, y0 = state[..., X, None], state[..., Y, None]  # (..., 1)
    v0, psi0 = state[..., SPEED, None], state[..., YAW, None]

    speed, bounds = _bounded_speed(v0, actions[..., ACCEL], config)  # (..., T)
    speed_before = _shift_in(v0, speed)
    yaw_rate, turn = _turn_bounded(actions[..., YAW_RATE], speed_before, speed, config)
    yaw = psi0 + dt * xp.cumulative_sum(yaw_rate, axis=-1)
    yaw_before = _shift_in(psi0, yaw)
    cos_before, sin_before = xp.cos(yaw_before), xp.sin(yaw_before)
    distance = 0.5 * (speed_before + speed) * dt  # (..., T) [m], uses a_eff
    x = x0 + xp.cumulative_sum(distance * cos_before, axis=-1)
    y = y0 + xp.cumulative_sum(distance * sin_before, axis=-1)
    x, y, speed, yaw = xp.broadcast_arrays(x, y, speed, yaw)
    saved = (commanded if clip else None, bounds, distance, cos_before, sin_before, turn)
    return xp.stack([x, y, speed, yaw], axis=-1), saved


def _turn_bounded(yaw_rate: Array, speed_before: Array, speed: Array, config: DynamicsConfig):
    """Yaw rates ``(..., T)`` within the turning bound, and where they were above, below."""
    if not config.turn_radius_min:
        return yaw_rate, None
    xp = namespace(yaw_rate, speed)
    reach = (speed_before + speed) * (0.5 / config.turn_radius_min)  # [rad/s]
    above, below = yaw_rate > reach, yaw_rate < -reach
    return xp.where(above, reach, xp.where(below, -reach, yaw_rate)), (above, below)


def rollout_with_vjp(
    state: Array, actions: Array, config: DynamicsConfig = DEFAULT_CONFIG, clip: bool = True
) -> tuple[Array, Callable[[Array], Array]]:
    """:func:`rollout` and its vector-Jacobian product with respect to the actions,
    in closed form (no autograd; numpy or torch).

    Args: as :func:`rollout`.

    Returns:
        ``(trajectories, vjp)``: the ``(..., T, 4)`` rollout, and ``vjp(cotangent)``
        mapping a cotangent ``(..., T, 4)`` on ``(x, y, v, psi)`` (e.g. ``dL/d
        trajectories``) to ``(..., T, 2)`` on the actions (``dL/d actions``, shaped as
        ``actions``): what torch autograd of :func:`rollout` gives, to float rounding,
        including at the speed bounds (the reflections' argmax steps; gradient 1 at a
        tie, as ``torch.clamp``) and at clipped actions (0 outside the bounds).
        Reverse cumulative sums over time; no Python loop over time.
    """
    trajectories, saved = _rollout(state, actions, config, clip)
    shape = tuple(actions.shape)

    def vjp(cotangent: Array) -> Array:
        _require_last_dim(cotangent, STATE_DIM, "cotangent", min_ndim=2)
        if tuple(cotangent.shape) != tuple(trajectories.shape):
            raise ValueError(
                f"cotangent must have the trajectories' shape {tuple(trajectories.shape)}, "
                f"got {tuple(cotangent.shape)}"
            )
        return _rollout_vjp(cotangent, saved, shape, config)

    return trajectories, vjp


def rollout_vjp(
    state: Array,
    actions: Array,
    cotangent: Array,
    config: DynamicsConfig = DEFAULT_CONFIG,
    clip: bool = True,
) -> Array:
    """``cotangent^T d rollout / d actions``: ``(..., T, 2)`` from a ``(..., T, 4)``
    cotangent on the rollout's states (:func:`rollout_with_vjp`)."""
    return rollout_with_vjp(state, actions, config, clip)[1](cotangent)


def _reverse_cumsum(x: Array, axis: int) -> Array:
    """``sum_{s >= t} x_s`` along ``axis``."""
    xp = namespace(x)
    return xp.flip(xp.cumulative_sum(xp.flip(x, axis=axis), axis=axis), axis=axis)


def _shift_out(seq: Array) -> Array:
    """``(..., T)`` the next step's values: ``[seq_1, ..., seq_{T-1}, 0]``."""
    xp = namespace(seq)
    return xp.concat([seq[..., 1:], xp.zeros_like(seq[..., :1])], axis=-1)


def _rollout_vjp(cotangent: Array, saved: tuple, shape: tuple, config: DynamicsConfig) -> Array:
    """The backward pass of :func:`_rollout`, op by op in reverse."""
    commanded, bounds, distance, cos_before, sin_before, turn = saved
    xp = namespace(cotangent)
    dt = config.dt
    # x_t = x0 + sum_{k<=t} distance_k cos(psi_{k-1}) (y: sin): each step's increment
    # moves every later position.
    increment = _reverse_cumsum(cotangent[..., :2], axis=-2)  # (..., T, 2)
    increment_x, increment_y = increment[..., 0], increment[..., 1]
    d_distance = increment_x * cos_before + increment_y * sin_before  # (..., T)
    d_yaw_before = distance * (increment_y * cos_before - increment_x * sin_before)
    # psi_t enters as psi_before_{t+1}; v_t in distance_t and distance_{t+1}.
    d_yaw = cotangent[..., YAW] + _shift_out(d_yaw_before)
    d_speed = cotangent[..., SPEED] + (0.5 * dt) * (d_distance + _shift_out(d_distance))
    d_yaw_rate = dt * _reverse_cumsum(d_yaw, axis=-1)
    if turn is not None:  # a bounded yaw rate follows the step's speeds, not the action
        above, below = turn
        d_reach = xp.where(above, d_yaw_rate, 0.0) - xp.where(below, d_yaw_rate, 0.0)
        d_reach = (0.5 / config.turn_radius_min) * d_reach
        d_speed = d_speed + d_reach + _shift_out(d_reach)
        d_yaw_rate = xp.where(above | below, 0.0, d_yaw_rate)
    d_accel = _bounded_speed_vjp(d_speed, bounds, config)
    d_actions = xp.stack([d_accel, d_yaw_rate], axis=-1)
    if commanded is not None:  # clip_actions: gradient 1 inside the bounds (inclusive)
        low = asarray_like([config.accel_min, -config.yaw_rate_max], commanded)
        high = asarray_like([config.accel_max, config.yaw_rate_max], commanded)
        inside = (commanded >= low) & (commanded <= high)
        d_actions = xp.where(inside, d_actions, 0.0)
    return _sum_to_shape(d_actions, shape)


def _sum_to_shape(x: Array, shape: tuple) -> Array:
    """``x`` summed over the leading dimensions it was broadcast along, to ``shape``."""
    xp = namespace(x)
    if x.ndim > len(shape):
        x = xp.sum(x, axis=tuple(range(x.ndim - len(shape))))
    stretched = tuple(i for i, n in enumerate(shape) if n == 1 and x.shape[i] != 1)
    return xp.sum(x, axis=stretched, keepdims=True) if stretched else x


def step(
    state: Array, action: Array, config: DynamicsConfig = DEFAULT_CONFIG, clip: bool = True
) -> Array:
    """The ``(..., 4)`` state ``dt`` later: :func:`rollout` of one ``(..., 2)`` action
    (``clip``: False when the caller has clipped the actions already, as the simulator)."""
    _require_last_dim(action, ACTION_DIM, "action")
    return rollout(state, action[..., None, :], config, clip)[..., 0, :]


def inverse(states: Array, config: DynamicsConfig = DEFAULT_CONFIG, clip: bool = False) -> Array:
    """Actions that reproduce speeds and headings of a state sequence.

    ``accel = dv / dt`` and ``yaw_rate = wrap_angle(dpsi) / dt``, so a heading that
    jumps across +-pi is handled. Positions are not used: a logged trajectory is
    reproduced exactly in speed and heading where it keeps the bounds (a heading that
    turns faster than the turning radius allows at its speed is not), and in position
    only as far as it follows this model.

    Args:
        states: ``(..., T + 1, 4)`` ``(x [m], y [m], v [m/s], psi [rad])``; the first
            one is the initial state.
        config: time step ``dt`` [s] and bounds.
        clip: clip the result with :func:`clip_actions` (default: as measured).

    Returns ``(..., T, 2)`` ``(accel [m/s^2], yaw_rate [rad/s])``.
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
