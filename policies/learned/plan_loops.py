"""numba kernels of the planning loops (:mod:`policies.learned.compiled_plans`).

:func:`avoid_scenes` runs every avoidance step of every scene of a batch
(``policies.learned.plan_avoidance.avoid_overlaps``' loop): per scene and step, the
rollout of its variables' plans, the SAT penetration gradient of the scored pairs whose
boxes can touch, the map term's gradient, the rollout's vector-Jacobian product and Adam
(:class:`policies.learned.adam.Adam`), with the reference's stopping rule.
:func:`guide_rows` runs output-space guidance's steps
(``policies.riskflow.guidance._guide_scenes``' loop) with the same pieces
(:mod:`policies.learned.plan_kernels`) and ``L_adv``, ``L_sep`` and the attacker's speed
floor. Both agree with the torch loops to float rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from policies.learned.plan_kernels import (
    _decoded,
    _map_gradient,
    _pair_gradient,
    _rollout,
    _rollout_vjp,
)
from riskflow_env.compiled_kernels import _grid

_jit = numba.njit(cache=True, nogil=True)

# SHA-256 of plan_kernels.py, whose functions these loops call: numba's cache checks only
# this file's source, so editing that file must edit this one.
PIECES_DIGEST = "d992bef8fe8b939946f3cbf9fdd9ce67a7673cd33fc172c9c770a7b928bba297"
BETA1, BETA2, EPSILON = 0.9, 0.999, 1e-8  # policies.learned.adam


@_jit
def avoid_scenes(
    scene_of_row, slot_of_row, now, moving, share, obstacles, length, width, pairs,
    use_map, frames, along, across, margins, weights, flat, grid_int, grid_float,
    map_of_row, norm, params, steps, step_size, slack, stop_margin, single,
):  # fmt: skip
    """Every avoidance step of every scene (``plan_avoidance.avoid_overlaps``' loop).

    Rows: the V variables, sorted by scene; ``scene_of_row``, ``slot_of_row`` (V,);
    ``now`` (V, 4); ``moving`` (V, H, 2) ``eps + u0`` [normalised]; ``share`` (V, H) the
    gain. Scenes: ``obstacles`` (B, A, H, 4) every row's plan, ``length``, ``width``
    (B, A), ``pairs`` (B, A, A) bool. Map (``use_map``): per row ``frames`` (V, 5),
    ``along``, ``across`` (V, 9), ``margins`` (V,), ``map_of_row`` (V,) into the
    ``grid_int`` / ``grid_float`` rows of the rasters ``flat``; ``weights`` (H,).
    ``norm`` (mean_a, mean_yaw, std_a, std_yaw); ``params`` the dynamics'.

    Returns:
        (V, H, 2) each row's correction ``share * delta``, added to ``u0``.
    """
    num_rows, horizon = moving.shape[0], moving.shape[1]
    num_agents = obstacles.shape[1]
    correction = np.zeros((num_rows, horizon, 2))
    start = 0
    while start < num_rows:
        scene = scene_of_row[start]
        end = start
        while end < num_rows and scene_of_row[end] == scene:
            end += 1
        _avoid_scene(
            scene, slot_of_row[start:end], now[start:end], moving[start:end], share[start:end],
            obstacles[scene], length[scene], width[scene], pairs[scene], use_map,
            frames[start:end], along[start:end], across[start:end], margins[start:end], weights,
            flat, grid_int, grid_float, map_of_row[start:end], norm, params, steps, step_size,
            slack, stop_margin, single, num_agents, correction[start:end],
        )  # fmt: skip
        start = end
    return correction


@_jit
def _avoid_scene(
    scene, slots, now, moving, share, obstacles, length, width, pairs, use_map, frames,
    along, across, margins, weights, flat, grid_int, grid_float, map_of_row, norm, params,
    steps, step_size, slack, stop_margin, single, num_agents, correction,
):  # fmt: skip
    """The avoidance steps of one scene's V variables (:func:`avoid_scenes`)."""
    num_rows, horizon = moving.shape[0], moving.shape[1]
    delta = np.zeros((num_rows, horizon, 2))
    first = np.zeros((num_rows, horizon, 2))
    second = np.zeros((num_rows, horizon, 2))
    actions = np.empty((num_rows, horizon, 2))
    saved = np.empty((num_rows, horizon, 9))
    joint = obstacles.copy()
    d_joint = np.zeros((num_agents, horizon, 4))
    gradient = np.empty((num_rows, horizon, 2))
    scratch = np.empty((horizon, 3))
    reach = np.empty(num_agents)
    sizes = np.empty((num_agents, 2))
    for a in range(num_agents):
        reach[a] = 0.5 * math.hypot(length[a], width[a])
        sizes[a, 0], sizes[a, 1] = length[a], width[a]
    std_a, std_y = norm[2], norm[3]
    count = 0
    for _ in range(steps):
        for r in range(num_rows):
            for t in range(horizon):
                for c in range(2):
                    actions[r, t, c] = _decoded(
                        moving[r, t, c], share[r, t], delta[r, t, c], norm[2 + c], norm[c], single
                    )
            _rollout(now[r], actions[r], params, True, joint[slots[r]], saved[r])
        d_joint[:] = 0.0
        closest = math.inf
        for i in range(num_agents):
            for j in range(i + 1, num_agents):
                if pairs[i, j]:
                    gap = _pair_gradient(
                        joint[i], joint[j], sizes[i], sizes[j], reach[i] + reach[j] + slack,
                        horizon, d_joint[i], d_joint[j],
                    )  # fmt: skip
                    closest = min(closest, gap)
        moved = False
        for r in range(num_rows):
            cotangent = d_joint[slots[r]]  # each variable's own slot: added to in place
            if use_map:
                g = map_of_row[r]
                _map_gradient(
                    joint[slots[r]], frames[r], along[r], across[r], margins[r], weights, flat,
                    _grid(grid_int, grid_float, g), cotangent,
                )  # fmt: skip
            _rollout_vjp(cotangent, actions[r], saved[r], params, True, gradient[r], scratch)
            for t in range(horizon):
                gradient[r, t, 0] *= std_a * share[r, t]
                gradient[r, t, 1] *= std_y * share[r, t]
                if gradient[r, t, 0] != 0.0 or gradient[r, t, 1] != 0.0:
                    moved = True
        if not moved and not (count > 0 and closest < stop_margin):
            break
        count += 1
        scale = step_size / (1.0 - BETA1**count)
        unbias = 1.0 - BETA2**count
        for r in range(num_rows):
            for t in range(horizon):
                for c in range(2):
                    g = gradient[r, t, c]
                    first[r, t, c] = first[r, t, c] * BETA1 + (1.0 - BETA1) * g
                    second[r, t, c] = second[r, t, c] * BETA2 + (1.0 - BETA2) * g * g
                    step = scale * first[r, t, c] / (math.sqrt(second[r, t, c] / unbias) + EPSILON)
                    delta[r, t, c] -= step
    for r in range(num_rows):
        for t in range(horizon):
            correction[r, t, 0] = share[r, t] * delta[r, t, 0]
            correction[r, t, 1] = share[r, t] * delta[r, t, 1]


@_jit
def _adversarial(plan, targets, valid, horizon, out):
    """``adversarial_term._adversarial`` of one row: returns its ``L_adv`` [m] (the mean
    distance to the nearest valid target over the first ``horizon`` steps) and writes its
    gradient into ``out[:horizon, :2]``; ``targets`` (J, H, 2), ``valid`` (J,) bool."""
    any_valid = False
    for j in range(valid.shape[0]):
        any_valid = any_valid or valid[j]
    total = 0.0
    for t in range(horizon):
        if not any_valid:
            out[t, 0], out[t, 1] = 0.0, 0.0
            continue
        best, best_dx, best_dy = math.inf, 0.0, 0.0
        for j in range(targets.shape[0]):
            if not valid[j]:
                continue
            dx = plan[t, 0] - targets[j, t, 0]
            dy = plan[t, 1] - targets[j, t, 1]
            squared = dx * dx + dy * dy
            if squared < best:
                best, best_dx, best_dy = squared, dx, dy
        distance = math.sqrt(best_dx * best_dx + best_dy * best_dy)
        total += distance
        scale = distance * horizon if distance > 0.0 else math.inf
        out[t, 0], out[t, 1] = best_dx / scale, best_dy / scale
    return total / horizon


@_jit
def guide_rows(
    state, offset, std, u, lower, upper, targets, valid, horizon, use_map, frames, along,
    across, margins, weights, flat, grid_int, grid_float, map_of_row, sep_pairs, sizes, fixed,
    use_floor, floor, lambdas, params, steps, step_size, adam, single,
):  # fmt: skip
    """The steps of output-space guidance (``policies.riskflow.guidance._guide_scenes``'
    loop) on the C guided rows of B scenes.

    Rows: ``state`` (C, 4), ``offset`` (C, T, 2) and ``std`` (2,) with ``a = offset + std *
    u``, ``u`` (C, T, 2) the residual to guide, kept within ``lower``/``upper`` (C, T, 2).
    ``L_adv``: ``targets`` (C, J, T, 2) and ``valid`` (C, J) each row's targets, over
    ``horizon`` steps (also ``L_sep``'s and the speed floor's). ``L_map`` (``use_map``): as
    :func:`avoid_scenes`. ``L_sep``: ``sep_pairs`` (P, 2) pairs
    of boxes, the C rows then the O bystanders whose plans ``fixed`` (O, horizon, 4) are
    held; ``sizes`` (C + O, 2). The speed floor (``use_floor``): ``floor`` (C,).
    ``lambdas``: (adv, map, sep, keep moving). ``adam``: Adam steps, else plain ones.

    Returns:
        ``(u, plans, losses)``: (C, T, 2) the guided residual, (C, T, 4) its rollout (the
        actions clipped, as ``dynamics.rollout``) and (steps + 1, C, 2) ``(L_adv, L_map)``
        of each row before each step and after the last.
    """
    num_rows, length = u.shape[0], u.shape[1]
    lambda_adv, lambda_map, lambda_sep, lambda_keep = lambdas[0], lambdas[1], lambdas[2], lambdas[3]
    u = u.copy()
    losses = np.zeros((steps + 1, num_rows, 2))
    actions = np.empty((num_rows, length, 2))
    plans = np.empty((num_rows, length, 4))
    saved = np.empty((num_rows, length, 9))
    cotangent = np.empty((num_rows, length, 4))
    term = np.empty((length, 4))
    gradient = np.empty((length, 2))
    scratch = np.empty((length, 3))
    first = np.zeros((num_rows, length, 2))
    second = np.zeros((num_rows, length, 2))
    num_boxes = sizes.shape[0]
    d_sep = np.empty((num_boxes, horizon, 4))
    reach = np.empty(num_boxes)
    for b in range(num_boxes):
        reach[b] = 0.5 * math.hypot(sizes[b, 0], sizes[b, 1])
    for step in range(steps + 1):  # the last pass scores the result
        last = step == steps
        for r in range(num_rows):
            for t in range(length):
                for c in range(2):
                    actions[r, t, c] = _decoded(
                        offset[r, t, c], std[c], u[r, t, c], 1.0, 0.0, single
                    )
            _rollout(state[r], actions[r], params, last, plans[r], saved[r])
        cotangent[:] = 0.0
        for r in range(num_rows):
            losses[step, r, 0] = _adversarial(plans[r], targets[r], valid[r], horizon, term)
            for t in range(horizon):
                cotangent[r, t, 0] = lambda_adv * term[t, 0]
                cotangent[r, t, 1] = lambda_adv * term[t, 1]
            if use_map:
                term[:] = 0.0
                g = map_of_row[r]
                losses[step, r, 1] = _map_gradient(
                    plans[r], frames[r], along[r], across[r], margins[r], weights, flat,
                    _grid(grid_int, grid_float, g), term,
                )  # fmt: skip
                for t in range(length):
                    for c in range(4):
                        cotangent[r, t, c] += lambda_map * term[t, c]
        if last:
            break
        if sep_pairs.shape[0] > 0:
            d_sep[:] = 0.0
            for p in range(sep_pairs.shape[0]):
                a, b = sep_pairs[p, 0], sep_pairs[p, 1]
                plan_a = plans[a] if a < num_rows else fixed[a - num_rows]
                plan_b = plans[b] if b < num_rows else fixed[b - num_rows]
                _pair_gradient(
                    plan_a, plan_b, sizes[a], sizes[b], reach[a] + reach[b], horizon, d_sep[a],
                    d_sep[b],
                )  # fmt: skip
            for r in range(num_rows):
                for t in range(horizon):
                    for c in range(4):
                        cotangent[r, t, c] += lambda_sep * d_sep[r, t, c]
        if use_floor:
            for r in range(num_rows):
                for t in range(horizon):
                    cotangent[r, t, 2] += -2.0 * lambda_keep * max(floor[r] - plans[r, t, 2], 0.0)
        scale = step_size / (1.0 - BETA1 ** (step + 1))
        unbias = 1.0 - BETA2 ** (step + 1)
        for r in range(num_rows):
            _rollout_vjp(cotangent[r], actions[r], saved[r], params, False, gradient, scratch)
            for t in range(length):
                for c in range(2):
                    g = gradient[t, c] * std[c]
                    if adam:
                        first[r, t, c] = first[r, t, c] * BETA1 + (1.0 - BETA1) * g
                        second[r, t, c] = second[r, t, c] * BETA2 + (1.0 - BETA2) * g * g
                        g = scale * first[r, t, c] / (math.sqrt(second[r, t, c] / unbias) + EPSILON)
                    else:
                        g = step_size * g
                    u[r, t, c] = min(max(u[r, t, c] - g, lower[r, t, c]), upper[r, t, c])
    return u, plans, losses
