"""numba kernels of the compiled simulator step (:mod:`riskflow_env.compiled`).

Each kernel loops over scenes, agents and pairs inside compiled code and repeats, in
the same order, the floating-point operations of the array-API reference
(:mod:`~riskflow_env.dynamics`, :mod:`~riskflow_env.risk`,
:mod:`~riskflow_env.geometry`, :func:`~riskflow_env.maps.sampling.interpolate_flat`,
:mod:`~riskflow_env.events`, :mod:`~riskflow_env.observations`,
:mod:`~riskflow_env.rewards`): no fast-math, so on one machine the results equal the
reference's to the last bit wherever the C library's ``sin``/``cos`` are numpy's.
Only what the reference masks out is skipped (the features of pairs beyond the
interaction range, the separating-axis test of pairs whose bounding circles are apart).

Importing this module imports numba (ImportError without it); ``cache=True`` keeps the
machine code on disk, so only the first run on a machine compiles.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from riskflow_env.geometry import NUM_FOOTPRINT_POINTS
from riskflow_env.risk import NUM_PAIR_FEATURES

# Footprint point k at (_ALONG[k] * length/2, _ACROSS[k] * width/2) in the vehicle frame
# (riskflow_env.geometry's layout: 4 corners, 4 edge midpoints, the centre last).
_ALONG = np.array((1.0, 1.0, -1.0, -1.0, 1.0, 0.0, -1.0, 0.0, 0.0))
_ACROSS = np.array((-1.0, 1.0, 1.0, -1.0, 0.0, 1.0, 0.0, -1.0, 0.0))
_CENTRE = NUM_FOOTPRINT_POINTS - 1
_NEIGHBOR_SIZE = NUM_PAIR_FEATURES + 3  # pair features, length, width, presence
_OWN_SIZE = 6  # speed, accel, yaw rate, length, width, SDF at the centre
NUM_TERMS = 5  # reward terms in riskflow_env.rewards.REWARD_TERMS order

# params of `advance`: dt [s], accel_min, accel_max [m/s^2], yaw_rate_max [rad/s],
# speed_min, speed_max [m/s]
# params of `evaluate_scenes`: tau_max [s], max_distance [m], then the reward weights
# target_speed [m/s], speed, collision, offroad, risk, comfort, then accel_min,
# accel_max [m/s^2] and yaw_rate_max [rad/s] (the comfort term's scales)
_jit = numba.njit(cache=True, nogil=True)


@_jit
def advance(current, present, active, actions, params):
    """:func:`riskflow_env.simulator.advance` of N flattened slots: ``current`` (N, 4),
    ``present``, ``active`` (N,) bool, ``actions`` (N, 2) -> new (N, 4), applied (N, 2)."""
    dt, accel_min, accel_max = params[0], params[1], params[2]
    yaw_max, speed_min, speed_max = params[3], params[4], params[5]
    count = current.shape[0]
    new = np.empty((count, 4))
    applied = np.zeros((count, 2))
    for k in range(count):
        x, y, v0, psi0 = current[k, 0], current[k, 1], current[k, 2], current[k, 3]
        if not active[k]:
            new[k, 0], new[k, 1], new[k, 3] = x, y, psi0
            new[k, 2] = 0.0 if present[k] else v0  # a done vehicle stands still
            continue
        accel = min(max(actions[k, 0], accel_min), accel_max)
        yaw_rate = min(max(actions[k, 1], -yaw_max), yaw_max)
        free = v0 + dt * accel  # dynamics._bounded_speed with one step
        lower = free + max(speed_min - free, 0.0)
        both = lower - max(lower - speed_max, 0.0)
        speed = min(max(both, speed_min), speed_max)
        distance = 0.5 * (v0 + speed) * dt
        new[k, 0] = x + distance * math.cos(psi0)
        new[k, 1] = y + distance * math.sin(psi0)
        new[k, 2] = speed
        new[k, 3] = psi0 + dt * yaw_rate
        applied[k, 0], applied[k, 1] = accel, yaw_rate
    return new, applied


@_jit
def _sdf(flat, grid_int, grid_float, index, x, y):
    """Bilinear SDF [m] at (x, y) on map ``index`` (maps.sampling.interpolate_flat, extend)."""
    height, width, offset = grid_int[index, 0], grid_int[index, 1], grid_int[index, 2]
    origin_x, origin_y, resolution = (
        grid_float[index, 0],
        grid_float[index, 1],
        grid_float[index, 2],
    )
    col = (x - origin_x) / resolution - 0.5
    row = (y - origin_y) / resolution - 0.5
    col_c = min(max(col, 0.0), float(width - 1))
    row_c = min(max(row, 0.0), float(height - 1))
    col0 = max(min(int(col_c), width - 2), 0)
    row0 = max(min(int(row_c), height - 2), 0)
    fc = col_c - float(col0)
    fr = row_c - float(row0)
    base = row0 * width + col0 + offset
    v00, v01 = float(flat[base]), float(flat[base + 1])
    v10, v11 = float(flat[base + width]), float(flat[base + width + 1])
    gc, gr = 1.0 - fc, 1.0 - fr
    top = v00 * gc + v01 * fc
    bottom = v10 * gc + v11 * fc
    off_c, off_r = col - col_c, row - row_c
    return top * gr + bottom * fr + math.sqrt(off_c * off_c + off_r * off_r) * resolution


@_jit
def _axis_time(d, dv, ext, tau_max):
    """Time [s] for the gap along one axis to close (risk._pair_geometry's axis_time)."""
    gap = abs(d) - ext
    if gap <= 0.0:
        return 0.0
    sign = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
    closing = -sign * dv
    if closing > 0.0 and closing * tau_max > gap:
        return gap / closing
    return tau_max


@_jit
def _pair_features(out, st, ln, wd, diag, cos, sin, i, j, cos_d, sin_d, distance, tau_max):
    """The 8 features of j seen from i (risk.pairwise_features) into ``out`` (8,)."""
    c_i, s_i = cos[i], sin[i]
    wx, wy = st[j, 0] - st[i, 0], st[j, 1] - st[i, 1]
    wvx = st[j, 2] * cos[j] - st[i, 2] * c_i
    wvy = st[j, 2] * sin[j] - st[i, 2] * s_i
    dx, dy = c_i * wx + s_i * wy, -s_i * wx + c_i * wy
    dvx, dvy = c_i * wvx + s_i * wvy, -s_i * wvx + c_i * wvy
    abs_c, abs_s = abs(cos_d), abs(sin_d)
    ext_x = 0.5 * (ln[i] + abs_c * ln[j] + abs_s * wd[j])
    ext_y = 0.5 * (wd[i] + abs_s * ln[j] + abs_c * wd[j])
    ttc = max(_axis_time(dx, dvx, ext_x, tau_max), _axis_time(dy, dvy, ext_y, tau_max))
    ttc = min(max(ttc, 0.0), tau_max)
    out[0], out[1], out[2], out[3], out[4], out[5] = dx, dy, cos_d, sin_d, dvx, dvy
    out[6] = distance / (0.5 * (diag[i] + diag[j]))
    out[7] = (tau_max - min(max(ttc, 0.0), tau_max)) / tau_max


@_jit
def _frame_distance(st, cos, sin, i, j):
    """Centre distance [m] of j from i computed in i's frame, as risk._pair_geometry."""
    wx, wy = st[j, 0] - st[i, 0], st[j, 1] - st[i, 1]
    dx, dy = cos[i] * wx + sin[i] * wy, -sin[i] * wx + cos[i] * wy
    squared = dx * dx + dy * dy
    return math.sqrt(squared) if squared > 0.0 else 0.0


@_jit
def _overlap(st, ln, wd, cos, sin, a, b):
    """Boxes a and b intersect (geometry.separation <= 0)."""
    ca, sa, cb, sb = cos[a], sin[a], cos[b], sin[b]
    dx, dy = st[b, 0] - st[a, 0], st[b, 1] - st[a, 1]
    hla, hwa, hlb, hwb = 0.5 * ln[a], 0.5 * wd[a], 0.5 * ln[b], 0.5 * wd[b]
    cab = abs(ca * cb + sa * sb)
    sab = abs(ca * sb - sa * cb)
    g0 = abs(dx * ca + dy * sa) - hla - (hlb * cab + hwb * sab)
    g1 = abs(dy * ca - dx * sa) - hwa - (hlb * sab + hwb * cab)
    g2 = abs(dx * cb + dy * sb) - hlb - (hla * cab + hwa * sab)
    g3 = abs(dy * cb - dx * sb) - hwb - (hla * sab + hwa * cab)
    return max(max(g0, g1), max(g2, g3)) <= 0.0


@_jit
def _pairs(st, ln, wd, valid, cos, sin, diag, params, mask, features, s, risk_max, hit):
    """Pair mask, features (into ``features[s]`` when it has a row s), row-max risk and
    collisions of scene s (risk.pairwise_features / pair_risk, geometry.pairwise_overlap)."""
    agents = st.shape[0]
    tau_max, max_distance = params[0], params[1]
    far = (max_distance * 1.001) ** 2  # beyond it no frame distance is within range
    row = np.empty(NUM_PAIR_FEATURES)
    full = features.shape[0] > s
    for i in range(agents):
        for j in range(i + 1, agents):
            if not (valid[i] and valid[j]):
                continue
            wx, wy = st[j, 0] - st[i, 0], st[j, 1] - st[i, 1]
            reach = 0.5 * diag[i] + 0.5 * diag[j] + 0.0
            if wx * wx + wy * wy <= reach * reach * (1.0 + 1e-9) + 1e-9:
                if _overlap(st, ln, wd, cos, sin, i, j):
                    hit[i, j] = hit[j, i] = True
            if not wx * wx + wy * wy <= far:
                continue
            near_ij = _frame_distance(st, cos, sin, i, j)
            near_ji = _frame_distance(st, cos, sin, j, i)
            if near_ij > max_distance and near_ji > max_distance:
                continue
            dpsi = st[j, 3] - st[i, 3]
            cos_d, sin_d = math.cos(dpsi), math.sin(dpsi)  # (j, i): cos_d, -sin_d
            for a, b, s_d, distance in ((i, j, sin_d, near_ij), (j, i, -sin_d, near_ji)):
                if distance > max_distance:
                    continue
                mask[a, b] = True
                _pair_features(row, st, ln, wd, diag, cos, sin, a, b, cos_d, s_d, distance, tau_max)
                risk_max[a] = max(risk_max[a], row[NUM_PAIR_FEATURES - 1])
                if full:
                    features[s, a, b, :] = row


@_jit
def _neighbors(out, features, mask, ln, wd, i, count, best_d, best_j):
    """The ``count`` nearest observed neighbours of i (stable on ties, as the reference's
    argsort) into ``out`` (count * 11,); absent ones stay zero."""
    found = 0
    for j in range(mask.shape[1]):
        if not mask[i, j]:
            continue
        d = math.hypot(features[i, j, 0], features[i, j, 1])
        if found == count and not d < best_d[count - 1]:
            continue
        k = found if found < count else count - 1
        found = min(found + 1, count)
        while k > 0 and best_d[k - 1] > d:
            best_d[k], best_j[k] = best_d[k - 1], best_j[k - 1]
            k -= 1
        best_d[k], best_j[k] = d, j
    for k in range(found):
        j, at = best_j[k], k * _NEIGHBOR_SIZE
        out[at : at + NUM_PAIR_FEATURES] = features[i, j, :]
        end = at + NUM_PAIR_FEATURES
        out[end], out[end + 1], out[end + 2] = ln[j], wd[j], 1.0


@_jit
def evaluate_scenes(
    current,
    length,
    width,
    present,
    last_action,
    flat,
    grid_int,
    grid_float,
    scene_map,
    offsets,
    params,
    num_neighbors,
    observations,
):
    """:func:`riskflow_env.simulator.evaluate` of S scenes of A slots.

    Args:
        current: (S, A, 4); length, width: (S, A) [m]; present: (S, A) bool;
            last_action: (S, A, 2).
        flat, grid_int (G, 3) (height, width, offset), grid_float (G, 3) (origin_x,
            origin_y, resolution): G maps' SDF rasters end to end (maps.stack's layout);
            scene_map: (S,) the map of each scene.
        offsets: (2, P) observation sample offsets in the agent frame, centre first.
        params: see the module's parameter comment.
        num_neighbors: neighbours per observation.
        observations: build the features and observations (else they come back empty).

    Returns:
        mask, features (S, A, A, 8) or empty, collisions (S, A, A), offroad_fraction,
        sdf_depth (S, A), centroid_offroad (S, A) bool, observations (S, A, D) float32
        or empty, terms (5, S, A), reward (S, A).
    """
    scenes, agents = current.shape[0], current.shape[1]
    target, w_speed, w_collision, w_offroad = params[2], params[3], params[4], params[5]
    w_risk, w_comfort = params[6], params[7]
    accel_min, accel_max, yaw_max = params[8], params[9], params[10]
    rays = offsets.shape[1] - 1
    size = _OWN_SIZE + num_neighbors * _NEIGHBOR_SIZE + rays
    mask = np.zeros((scenes, agents, agents), dtype=np.bool_)
    hit = np.zeros((scenes, agents, agents), dtype=np.bool_)
    features = np.zeros((scenes if observations else 0, agents, agents, NUM_PAIR_FEATURES))
    fraction = np.zeros((scenes, agents))
    depth = np.zeros((scenes, agents))
    centroid = np.zeros((scenes, agents), dtype=np.bool_)
    rows = np.zeros((scenes if observations else 0, agents, size), dtype=np.float32)
    terms = np.empty((NUM_TERMS, scenes, agents))
    reward = np.empty((scenes, agents))
    cos, sin, diag = np.empty(agents), np.empty(agents), np.empty(agents)
    risk_max = np.empty(agents)
    row = np.empty(size)
    best_d, best_j = np.empty(max(num_neighbors, 1)), np.empty(max(num_neighbors, 1), np.int64)
    for s in range(scenes):
        st, ln, wd, valid = current[s], length[s], width[s], present[s]
        index = scene_map[s]
        for i in range(agents):
            cos[i], sin[i] = math.cos(st[i, 3]), math.sin(st[i, 3])
            diag[i] = math.sqrt(ln[i] * ln[i] + wd[i] * wd[i])
            risk_max[i] = 0.0
        _pairs(st, ln, wd, valid, cos, sin, diag, params, mask[s], features, s, risk_max, hit[s])
        for i in range(agents):
            x, y, c, sn = st[i, 0], st[i, 1], cos[i], sin[i]
            along, across = 0.5 * ln[i], 0.5 * wd[i]
            outside, deepest, centre = 0, -np.inf, 0.0
            for k in range(NUM_FOOTPRINT_POINTS):
                a, b = along * _ALONG[k], across * _ACROSS[k]
                value = _sdf(
                    flat, grid_int, grid_float, index, x + a * c - b * sn, y + a * sn + b * c
                )
                outside += value > 0.0
                deepest = max(deepest, value)
                centre = value
            if valid[i]:
                fraction[s, i] = outside / NUM_FOOTPRINT_POINTS
                depth[s, i] = deepest
                centroid[s, i] = centre > 0.0
            collided = False
            for j in range(agents):
                collided |= hit[s, i, j]
            speed, accel, yaw_rate = st[i, 2], last_action[s, i, 0], last_action[s, i, 1]
            scale = accel_max if accel >= 0 else -accel_min
            q_accel, q_yaw = accel / scale, yaw_rate / yaw_max
            terms[0, s, i] = w_speed * min(speed, target) / target
            terms[1, s, i] = w_collision * (1.0 if collided else 0.0)
            terms[2, s, i] = w_offroad * (1.0 if valid[i] and outside > 0 else 0.0)
            terms[3, s, i] = w_risk * risk_max[i]
            terms[4, s, i] = w_comfort * (q_accel * q_accel + q_yaw * q_yaw)
            total = 0.0
            for t in range(NUM_TERMS):
                total = total + terms[t, s, i]
            reward[s, i] = total
            if not (observations and valid[i]):
                continue
            row[:] = 0.0
            row[0], row[1], row[2], row[3], row[4] = speed, accel, yaw_rate, ln[i], wd[i]
            row[5] = centre
            if num_neighbors > 0:
                _neighbors(
                    row[_OWN_SIZE:], features[s], mask[s], ln, wd, i, num_neighbors, best_d, best_j
                )
            first_ray = size - rays
            for p in range(rays):
                forward, left = offsets[0, p + 1], offsets[1, p + 1]
                px, py = x + (c * forward - sn * left), y + (sn * forward + c * left)
                row[first_ray + p] = _sdf(flat, grid_int, grid_float, index, px, py)
            for k in range(size):
                rows[s, i, k] = np.float32(row[k])
    return mask, features, hit, fraction, depth, centroid, rows, terms, reward
