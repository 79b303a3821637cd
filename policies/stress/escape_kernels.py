"""numba kernels of the hindsight escape search (:mod:`policies.stress.escape`).

The torch search (:class:`policies.stress.escape._Problem`) is the reference; these
kernels repeat its two phases row by row with its formulas:

* :func:`score_rows`: the soft cost, the hard check, the least separation and the deepest
  footprint sample of each candidate (``_Problem.evaluate``);
* :func:`refine_rows`: projected Adam (``torch.optim.Adam``'s update) on the soft cost
  until a row passes the hard check (``escape._refine``), the gradient in closed form: the
  SAT separation's, the SDF's and the rollout's vector-Jacobian product, the pieces of the
  compiled planning loops (:mod:`policies.learned.plan_kernels`).

A candidate, another vehicle and a step whose bounding circles are farther apart than
``sqrt(2)`` times the soft cost's margin are skipped unless ``exact``: their SAT
separation, at least the boxes' distance over ``sqrt(2)``, exceeds the margin, so they add
nothing to the cost, its gradient or the hard check (only the reported least separation
can change, and the search rescores its pick exactly).

The arithmetic is float64, as the reference's, in another order (sequential sums, the
closed-form gradient), so the two agree to float rounding, not bit for bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from policies.learned.plan_kernels import (
    _rollout,
    _rollout_vjp,
    _sdf_with_gradient,
    _separation_gradient,
)
from riskflow_env.compiled_kernels import _grid

_jit = numba.njit(cache=True, nogil=True)

# SHA-256 of policies/learned/plan_kernels.py, whose pieces these kernels call: numba's
# cache checks only this file's source, so editing that file must edit this one.
PIECES_DIGEST = "d992bef8fe8b939946f3cbf9fdd9ce67a7673cd33fc172c9c770a7b928bba297"
BETA1, BETA2, EPSILON = 0.9, 0.999, 1e-8  # torch.optim.Adam's defaults


@_jit
def _score_row(
    knots, interp, start, params, obstacles, sizes, present, ego_size, road, limits, exact,
    want_gradient, work, d_knots,
):  # fmt: skip
    """One candidate's ``(cost, clearance, worst excess, deepest)``, its states in
    ``work[0]`` and, if ``want_gradient``, the cost's gradient in ``d_knots`` (K, 2).

    ``obstacles`` (N, H, 3) x, y, yaw; ``sizes`` (N, 3) length, width, circumradius;
    ``road`` = (use_map, flat, grid_int, grid_float, along (9,), across (9,));
    ``limits`` = (margin, allowance, ego circumradius, road slack) [m]; ``work`` the
    buffers of :func:`_buffers`."""
    states, saved, actions, d_states, d_actions, scratch = work
    horizon, num_knots = interp.shape
    for t in range(horizon):
        accel, yaw_rate = 0.0, 0.0
        for k in range(num_knots):
            accel += interp[t, k] * knots[k, 0]
            yaw_rate += interp[t, k] * knots[k, 1]
        actions[t, 0], actions[t, 1] = accel, yaw_rate
    _rollout(start, actions, params, False, states, saved)
    d_states[:] = 0.0
    margin, allowance, ego_radius, road_slack = limits
    skip = math.sqrt(2.0) * margin + 1e-9
    gap_cost, clear = 0.0, math.inf
    for n in range(obstacles.shape[0]):
        reach = ego_radius + sizes[n, 2] + skip
        for t in range(horizon):
            if not present[n, t]:
                continue
            x, y = obstacles[n, t, 0], obstacles[n, t, 1]
            if not exact:
                dx, dy = x - states[t, 0], y - states[t, 1]
                if dx * dx + dy * dy > reach * reach:
                    continue
            gap, g_x, g_y, g_yaw_ego, _ = _separation_gradient(
                states[t, 0], states[t, 1], states[t, 3], ego_size[0], ego_size[1],
                x, y, obstacles[n, t, 2], sizes[n, 0], sizes[n, 1], True,
            )  # fmt: skip
            clear = min(clear, gap)
            if gap < margin:
                gap_cost += margin - gap
                d_states[t, 0] += g_x  # d gap / d ego xy = -(g_x, g_y); d cost / d gap = -1
                d_states[t, 1] += g_y
                d_states[t, 3] -= g_yaw_ego
    road_cost, worst, deepest = 0.0, -math.inf, -math.inf
    use_map, flat, grid_int, grid_float, along, across = road
    if use_map:
        grid = _grid(grid_int, grid_float, 0)
        values, slope = np.empty(along.shape[0]), np.empty((along.shape[0], 2))
        for t in range(horizon):
            cos, sin = math.cos(states[t, 3]), math.sin(states[t, 3])
            depth = -math.inf
            for k in range(along.shape[0]):
                px = states[t, 0] + along[k] * cos - across[k] * sin
                py = states[t, 1] + along[k] * sin + across[k] * cos
                value, slope[k, 0], slope[k, 1] = _sdf_with_gradient(flat, grid, px, py)
                values[k] = value
                depth = max(depth, value)
            excess = depth - allowance
            worst, deepest = max(worst, excess), max(deepest, depth)
            if excess + road_slack > 0.0:
                road_cost += excess + road_slack
                ties = 0  # autograd's amax shares the gradient among equal samples
                for k in range(along.shape[0]):
                    ties += values[k] == depth
                for k in range(along.shape[0]):
                    if values[k] != depth:
                        continue
                    g_x, g_y = slope[k, 0] / ties, slope[k, 1] / ties
                    d_states[t, 0] += g_x
                    d_states[t, 1] += g_y
                    d_states[t, 3] += g_x * (-along[k] * sin - across[k] * cos) + g_y * (
                        along[k] * cos - across[k] * sin
                    )
    if want_gradient:
        _rollout_vjp(d_states, actions, saved, params, False, d_actions, scratch)
        for k in range(num_knots):
            for c in range(2):
                total = 0.0
                for t in range(horizon):
                    total += interp[t, k] * d_actions[t, c]
                d_knots[k, c] = total
    return gap_cost + road_cost, clear, worst, deepest


@_jit
def _buffers(horizon):
    """States (H, 4), the rollout's saved terms (H, 9), actions (H, 2), their cotangents
    (H, 4) and (H, 2), the VJP's scratch (H, 3)."""
    return (
        np.empty((horizon, 4)), np.empty((horizon, 9)), np.empty((horizon, 2)),
        np.empty((horizon, 4)), np.empty((horizon, 2)), np.empty((horizon, 3)),
    )  # fmt: skip


@_jit
def score_rows(
    knots, interp, start, params, obstacles, sizes, present, ego_size, road, limits, exact,
    states, scores,
):  # fmt: skip
    """``_Problem.evaluate`` of every candidate ``knots`` (S, K, 2): its states into
    ``states`` (S, H, 4) and ``(cost, clearance, worst excess, deepest)`` into ``scores``
    (S, 4)."""
    work = _buffers(interp.shape[0])
    unused = np.empty((interp.shape[1], 2))
    for r in range(knots.shape[0]):
        cost, clear, worst, deepest = _score_row(
            knots[r], interp, start, params, obstacles, sizes, present, ego_size, road,
            limits, exact, False, work, unused,
        )  # fmt: skip
        states[r] = work[0]
        scores[r, 0], scores[r, 1], scores[r, 2], scores[r, 3] = cost, clear, worst, deepest


@_jit
def refine_rows(
    knots, low, high, steps, learning_rate, clearance, interp, start, params, obstacles,
    sizes, present, ego_size, road, limits,
):  # fmt: skip
    """``escape._refine``: projected Adam steps on ``knots`` (R, K, 2), in place, until a
    row passes the hard check (separation ``>= clearance`` from every vehicle, no excess
    off the road) or ``steps`` ran out; returns the steps taken."""
    work = _buffers(interp.shape[0])
    gradient = np.zeros(knots.shape)
    first, second = np.zeros(knots.shape), np.zeros(knots.shape)
    for step in range(steps):
        feasible = False
        for r in range(knots.shape[0]):
            _, clear, worst, _ = _score_row(
                knots[r], interp, start, params, obstacles, sizes, present, ego_size, road,
                limits, False, True, work, gradient[r],
            )  # fmt: skip
            feasible = feasible or (clear >= clearance and worst <= 0.0)
        if feasible:
            return step
        scale = learning_rate / (1.0 - BETA1 ** (step + 1))
        unbias = math.sqrt(1.0 - BETA2 ** (step + 1))
        for r in range(knots.shape[0]):
            for k in range(knots.shape[1]):
                for c in range(2):
                    g = gradient[r, k, c]
                    first[r, k, c] = first[r, k, c] * BETA1 + (1.0 - BETA1) * g
                    second[r, k, c] = second[r, k, c] * BETA2 + (1.0 - BETA2) * g * g
                    move = scale * first[r, k, c] / (math.sqrt(second[r, k, c]) / unbias + EPSILON)
                    knots[r, k, c] = max(min(knots[r, k, c] - move, high[c]), low[c])
    return steps
