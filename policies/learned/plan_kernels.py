"""numba kernels of the planning loops' pieces (:mod:`policies.learned.compiled_plans`;
the loops themselves: :mod:`policies.learned.plan_loops`).

Each function repeats, for one plan or one pair, the formula of the torch function it
names, op for op: the rollout with its speed bounds (:func:`riskflow_env.dynamics.rollout`)
and its vector-Jacobian product (:func:`riskflow_env.dynamics.rollout_with_vjp`), the SAT
penetration gradient of a pair of plans
(:func:`policies.learned.plan_overlap.overlap_gradient`) and the map term's value and
gradient (:meth:`policies.learned.guidance_losses.MapTerm.rows_and_gradient`). The
arithmetic is float64 (the reference runs in the plans' dtype, float32, and the actions
are decoded with its rounding: :func:`_decoded`), so the two paths agree to float
rounding, not bit for bit.

Importing this module imports numba (ImportError without it); ``cache=True`` keeps the
machine code on disk, so only the first run on a machine compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from riskflow_env.compiled_kernels import _cell, _turn_bounded

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, inline="always")

# SHA-256 of riskflow_env/compiled_kernels.py, whose SDF cell lookup and turning bound
# these kernels call: numba's cache checks only this file's source, so editing that file
# must edit this one.
KERNELS_DIGEST = "bda33b1eda98d9ce616e123c93745c16a56ae50c54c7be3887b33c37a95fb7a8"


@_inline
def _decoded(base, weight, value, scale, shift, single):
    """The action ``(base + weight * value) * scale + shift``, op by op in float32 when the
    plans are float32 (``single``): the reference's rounding, so that a correction that
    cancels exactly there (a residue ``-eps`` on the noise ``eps``: a base plan that keeps
    its speed and heading) cancels here too; Adam would blow a residue of 1e-9 up to a
    step of its full length."""
    if single:
        product = np.float32(np.float32(weight) * np.float32(value))
        total = np.float32(np.float32(base) + product)
        return float(np.float32(np.float32(total * np.float32(scale)) + np.float32(shift)))
    return (base + weight * value) * scale + shift


@_jit
def _rollout(state, actions, params, clip, out, saved):
    """``dynamics._rollout`` of one plan: ``state`` (4,), commanded ``actions`` (H, 2) ->
    ``out`` (H, 4), the actions clipped to the bounds if ``clip``; ``saved`` (H, 9) keeps
    what :func:`_rollout_vjp` needs (below, below_max, above, above_max, both, distance,
    cos_before, sin_before, and +1 / -1 where the yaw rate was above / below the turning
    bound, else 0)."""
    dt, accel_min, accel_max, yaw_max, speed_min, speed_max, radius = params
    x0, y0, v0, psi0 = state[0], state[1], state[2], state[3]
    sum_accel, sum_yaw_rate, sum_x, sum_y = 0.0, 0.0, 0.0, 0.0  # the reference's cumsums
    below_max = -math.inf
    above_max = -math.inf
    speed_before, yaw_before = v0, psi0
    for t in range(actions.shape[0]):
        accel, yaw_rate = actions[t, 0], actions[t, 1]
        if clip:
            accel = min(max(accel, accel_min), accel_max)
            yaw_rate = min(max(yaw_rate, -yaw_max), yaw_max)
        sum_accel += accel
        free = v0 + dt * sum_accel
        below = speed_min - free
        below_max = max(below_max, below)
        lower = free + max(below_max, 0.0)
        above = lower - speed_max
        above_max = max(above_max, above)
        both = lower - max(above_max, 0.0)
        speed = min(max(both, speed_min), speed_max)
        yaw_rate, side = _turn_bounded(yaw_rate, speed_before, speed, radius)
        sum_yaw_rate += yaw_rate
        yaw = psi0 + dt * sum_yaw_rate
        cos_before, sin_before = math.cos(yaw_before), math.sin(yaw_before)
        distance = 0.5 * (speed_before + speed) * dt
        sum_x += distance * cos_before
        sum_y += distance * sin_before
        out[t, 0], out[t, 1], out[t, 2], out[t, 3] = x0 + sum_x, y0 + sum_y, speed, yaw
        saved[t, 0], saved[t, 1], saved[t, 2], saved[t, 3] = below, below_max, above, above_max
        saved[t, 4], saved[t, 5], saved[t, 6], saved[t, 7] = both, distance, cos_before, sin_before
        saved[t, 8] = side
        speed_before, yaw_before = speed, yaw


@_jit
def _bounded_speed_vjp(d_speed, saved, params, out):
    """``dynamics._bounded_speed_vjp`` of one plan: ``d_speed`` (H,) -> ``out`` (H,)."""
    dt, speed_min, speed_max = params[0], params[4], params[5]
    horizon = d_speed.shape[0]
    touched = False
    for t in range(horizon):
        if saved[t, 1] >= 0.0 or saved[t, 3] >= 0.0:
            touched = True
    if not touched:  # the free path: dt * reverse cumsum
        total = 0.0
        for t in range(horizon - 1, -1, -1):
            total += d_speed[t]
            out[t] = dt * total
        return
    first = np.zeros(horizon, dtype=np.int64)  # window start of the lower reflection
    latest_below, latest_above = 0, 0
    latest = np.zeros(horizon, dtype=np.int64)  # argmax step of the upper reflection
    for t in range(horizon):
        if saved[t, 0] == saved[t, 1]:
            latest_below = t
        if saved[t, 2] == saved[t, 3]:
            latest_above = t
        first[t] = latest_below + 1 if saved[t, 1] >= 0.0 else 0
        latest[t] = latest_above
    for k in range(horizon):
        out[k] = 0.0
    for t in range(horizon):
        both = saved[t, 4]
        if not (both >= speed_min and both <= speed_max):
            continue
        cot = d_speed[t]
        for k in range(first[t], t + 1):
            out[k] += cot
        if saved[t, 3] >= 0.0:
            for k in range(first[latest[t]], latest[t] + 1):
                out[k] -= cot
    for k in range(horizon):
        out[k] = dt * out[k]


@_jit
def _rollout_vjp(cotangent, actions, saved, params, clip, out, scratch):
    """``dynamics._rollout_vjp`` of one plan (with ``clip``, the clip's mask):
    ``cotangent`` (H, 4) -> ``out`` (H, 2); ``scratch`` (H, 3)."""
    dt, accel_min, accel_max, yaw_max = params[0], params[1], params[2], params[3]
    radius = params[6]
    horizon = cotangent.shape[0]
    inc_x, inc_y = 0.0, 0.0
    next_d_distance, next_d_yaw_before = 0.0, 0.0
    d_speed, d_yaw = scratch[:, 0], scratch[:, 1]
    for t in range(horizon - 1, -1, -1):
        inc_x += cotangent[t, 0]
        inc_y += cotangent[t, 1]
        distance, cos_before, sin_before = saved[t, 5], saved[t, 6], saved[t, 7]
        d_distance = inc_x * cos_before + inc_y * sin_before
        d_yaw_before = distance * (inc_y * cos_before - inc_x * sin_before)
        d_yaw[t] = cotangent[t, 3] + next_d_yaw_before
        d_speed[t] = cotangent[t, 2] + (0.5 * dt) * (d_distance + next_d_distance)
        next_d_distance, next_d_yaw_before = d_distance, d_yaw_before
    total, next_reach = 0.0, 0.0
    for t in range(horizon - 1, -1, -1):  # d_yaw becomes the cotangent on the yaw rates
        total += d_yaw[t]
        d_yaw[t] = dt * total
        if radius > 0.0:  # a bounded yaw rate follows the step's speeds, not the action
            reach = (saved[t, 8] * d_yaw[t]) * (0.5 / radius) if saved[t, 8] != 0.0 else 0.0
            d_speed[t] = (d_speed[t] + reach) + next_reach
            next_reach = reach
            if saved[t, 8] != 0.0:
                d_yaw[t] = 0.0
    _bounded_speed_vjp(d_speed, saved, params, scratch[:, 2])
    for t in range(horizon):
        accel, yaw_rate = actions[t, 0], actions[t, 1]
        inside_a = not clip or (accel >= accel_min and accel <= accel_max)
        inside_y = not clip or (yaw_rate >= -yaw_max and yaw_rate <= yaw_max)
        out[t, 0] = scratch[t, 2] if inside_a else 0.0
        out[t, 1] = d_yaw[t] if inside_y else 0.0


@_inline
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@_inline
def _share(a, b):
    """The part of ``torch.maximum(a, b)``'s gradient that autograd gives ``a``."""
    return 1.0 if a > b else (0.5 if a == b else 0.0)


@_jit
def _separation_gradient(xa, ya, yaw_a, len_a, wid_a, xb, yb, yaw_b, len_b, wid_b, split):
    """``geometry.separation_gradient`` of one pair of boxes: ``(gap, d_x, d_y, d_yaw_a,
    d_yaw_b)``, the derivatives of the first largest SAT gap (d/d xy_a = -d/d xy_b); with
    ``split``, autograd's through ``geometry.separation`` instead, which shares the
    gradient among equal gaps (``torch.maximum`` gives each half)."""
    cos_a, sin_a = math.cos(yaw_a), math.sin(yaw_a)
    cos_b, sin_b = math.cos(yaw_b), math.sin(yaw_b)
    dx, dy = xb - xa, yb - ya
    hl_a, hw_a, hl_b, hw_b = 0.5 * len_a, 0.5 * wid_a, 0.5 * len_b, 0.5 * wid_b
    cos_ab = cos_a * cos_b + sin_a * sin_b
    sin_ab = cos_a * sin_b - sin_a * cos_b
    abs_cos, abs_sin = abs(cos_ab), abs(sin_ab)
    p0 = dx * cos_a + dy * sin_a
    p1 = dy * cos_a - dx * sin_a
    p2 = dx * cos_b + dy * sin_b
    p3 = dy * cos_b - dx * sin_b
    g0 = abs(p0) - hl_a - (hl_b * abs_cos + hw_b * abs_sin)
    g1 = abs(p1) - hw_a - (hl_b * abs_sin + hw_b * abs_cos)
    g2 = abs(p2) - hl_b - (hl_a * abs_cos + hw_a * abs_sin)
    g3 = abs(p3) - hw_b - (hl_a * abs_sin + hw_a * abs_cos)
    best = max(max(g0, g1), max(g2, g3))
    c_turn = _sign(cos_ab) * sin_ab
    s_turn = _sign(sin_ab) * cos_ab
    if split:
        m01, m23 = max(g0, g1), max(g2, g3)
        w01, w23 = _share(m01, m23), _share(m23, m01)
        weights = (
            w01 * _share(g0, g1),
            w01 * _share(g1, g0),
            w23 * _share(g2, g3),
            w23 * _share(g3, g2),
        )
        d_x, d_y, d_yaw_a, d_yaw_b = 0.0, 0.0, 0.0, 0.0
        for k in range(4):
            w = weights[k]
            if w == 0.0:
                continue
            if k == 0:
                s0 = _sign(p0)
                turn_b = hl_b * c_turn - hw_b * s_turn
                terms = (s0 * cos_a, s0 * sin_a, s0 * p1 - turn_b, turn_b)
            elif k == 1:
                s1 = _sign(p1)
                cross_b = hl_b * s_turn - hw_b * c_turn
                terms = (-s1 * sin_a, s1 * cos_a, -s1 * p0 + cross_b, -cross_b)
            elif k == 2:
                s2 = _sign(p2)
                turn_a = hl_a * c_turn - hw_a * s_turn
                terms = (s2 * cos_b, s2 * sin_b, -turn_a, s2 * p3 + turn_a)
            else:
                s3 = _sign(p3)
                cross_a = hl_a * s_turn - hw_a * c_turn
                terms = (-s3 * sin_b, s3 * cos_b, cross_a, -s3 * p2 - cross_a)
            d_x += w * terms[0]
            d_y += w * terms[1]
            d_yaw_a += w * terms[2]
            d_yaw_b += w * terms[3]
        return best, d_x, d_y, d_yaw_a, d_yaw_b
    if g0 == best:
        s0 = _sign(p0)
        turn_b = hl_b * c_turn - hw_b * s_turn
        return best, s0 * cos_a, s0 * sin_a, s0 * p1 - turn_b, turn_b
    if g1 == best:
        s1 = _sign(p1)
        cross_b = hl_b * s_turn - hw_b * c_turn
        return best, -s1 * sin_a, s1 * cos_a, -s1 * p0 + cross_b, -cross_b
    if g2 == best:
        s2 = _sign(p2)
        turn_a = hl_a * c_turn - hw_a * s_turn
        return best, s2 * cos_b, s2 * sin_b, -turn_a, s2 * p3 + turn_a
    s3 = _sign(p3)
    cross_a = hl_a * s_turn - hw_a * c_turn
    return best, -s3 * sin_b, s3 * cos_b, cross_a, -s3 * p2 - cross_a


@_jit
def _pair_gradient(plan_i, plan_j, size_i, size_j, touch, horizon, d_i, d_j):
    """``plan_overlap.overlap_gradient`` of one pair of plans over their first
    ``horizon`` steps: when their centres come within ``touch`` [m] at some step, adds the
    gradient of ``sum relu(-separation)^2`` to ``d_i`` and ``d_j`` (H, 4) and returns the
    pair's smallest separation [m]; ``inf`` otherwise. ``size_*``: (length, width)."""
    near = False
    for t in range(horizon):
        dx = plan_i[t, 0] - plan_j[t, 0]
        dy = plan_i[t, 1] - plan_j[t, 1]
        if math.sqrt(dx * dx + dy * dy) <= touch:
            near = True
            break
    if not near:
        return math.inf
    closest = math.inf
    for t in range(horizon):
        gap, g_x, g_y, g_yaw_i, g_yaw_j = _separation_gradient(
            plan_i[t, 0], plan_i[t, 1], plan_i[t, 3], size_i[0], size_i[1],
            plan_j[t, 0], plan_j[t, 1], plan_j[t, 3], size_j[0], size_j[1], False,
        )  # fmt: skip
        closest = min(closest, gap)
        if gap >= 0.0:
            continue
        weight = 2.0 * gap
        d_i[t, 0] -= weight * g_x
        d_i[t, 1] -= weight * g_y
        d_i[t, 3] += weight * g_yaw_i
        d_j[t, 0] += weight * g_x
        d_j[t, 1] += weight * g_y
        d_j[t, 3] += weight * g_yaw_j
    return closest


@_jit
def _sdf_with_gradient(flat, grid, x, y):
    """``maps.sampling.interpolate_flat`` with ``extend`` and its gradient at one point:
    ``(value, d/dx, d/dy)`` on the map ``grid`` (``riskflow_env.compiled_kernels._grid``;
    the cell lookup is the compiled step's, ``_cell``)."""
    col, row, col_c, row_c, fc, fr, v00, v01, v10, v11 = _cell(flat, grid, x, y)
    resolution = grid[5]
    gc, gr = 1.0 - fc, 1.0 - fr
    top = v00 * gc + v01 * fc
    bottom = v10 * gc + v11 * fc
    value = top * gr + bottom * fr
    off_c, off_r = col - col_c, row - row_c
    distance = math.sqrt(off_c * off_c + off_r * off_r) if value > 0.0 else 0.0
    inside_c = 1.0 if col == col_c else 0.0
    inside_r = 1.0 if row == row_c else 0.0
    d_col = ((v01 - v00) * gr + (v11 - v10) * fr) * (inside_c / resolution)
    d_row = (bottom - top) * (inside_r / resolution)
    if distance > 0.0:
        d_col += off_c / distance
        d_row += off_r / distance
    return value + distance * resolution, d_col, d_row


@_jit
def _map_gradient(plan, frame, along, across, margin, weights, flat, grid, out):
    """``MapTerm._evaluate`` with the gradient of one plan (H, 4): returns its ``L_map``
    [m^2] and adds its gradient to ``out`` (H, 4); ``frame`` (origin_x, origin_y, yaw,
    cos, sin) of the scene frame in the world, ``along`` and ``across`` (9,) the footprint
    offsets [m], ``weights`` (H,) the decay; ``grid`` the map's (``compiled_kernels._grid``)."""
    origin_x, origin_y, frame_yaw, cos_f, sin_f = frame[0], frame[1], frame[2], frame[3], frame[4]
    total = 0.0
    for t in range(plan.shape[0]):
        if weights[t] == 0.0:  # past the horizon the term scores: its terms are 0
            continue
        x_s, y_s = plan[t, 0], plan[t, 1]
        world_x = origin_x + cos_f * x_s - sin_f * y_s
        world_y = origin_y + sin_f * x_s + cos_f * y_s
        yaw = plan[t, 3] + frame_yaw
        cos, sin = math.cos(yaw), math.sin(yaw)
        d_wx, d_wy, d_yaw = 0.0, 0.0, 0.0
        for k in range(along.shape[0]):
            along_x, across_x = cos * along[k], sin * across[k]
            along_y, across_y = sin * along[k], cos * across[k]
            px = world_x + along_x - across_x
            py = world_y + along_y + across_y
            sdf, g_x, g_y = _sdf_with_gradient(flat, grid, px, py)
            depth = max(sdf + margin, 0.0)
            if depth == 0.0:
                continue
            total += depth * depth * weights[t]
            slope = 2.0 * depth * weights[t]
            slope_x, slope_y = slope * g_x, slope * g_y
            d_wx += slope_x
            d_wy += slope_y
            d_yaw += slope_y * (along_x - across_x) - slope_x * (along_y + across_y)
        out[t, 0] += cos_f * d_wx + sin_f * d_wy
        out[t, 1] += -sin_f * d_wx + cos_f * d_wy
        out[t, 3] += d_yaw
    return total
