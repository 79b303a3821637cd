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
machine code on disk, so only the first run on a machine compiles. numba reuses that
code while this file's source is unchanged, even where a kernel it calls from another
file has changed: :data:`PAIRS_DIGEST` puts :mod:`~riskflow_env.compiled_pairs`'s
source into this file's (a test checks it is current).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from riskflow_env.compiled_pairs import NEIGHBOR_SIZE, neighbors, pairs
from riskflow_env.geometry import NUM_FOOTPRINT_POINTS
from riskflow_env.risk import NUM_PAIR_FEATURES

# Footprint point k at (_ALONG[k] * length/2, _ACROSS[k] * width/2) in the vehicle frame
# (riskflow_env.geometry's layout: 4 corners, 4 edge midpoints, the centre last).
_ALONG = np.array((1.0, 1.0, -1.0, -1.0, 1.0, 0.0, -1.0, 0.0, 0.0))
_ACROSS = np.array((-1.0, 1.0, 1.0, -1.0, 0.0, 1.0, 0.0, -1.0, 0.0))
_OWN_SIZE = 6  # speed, accel, yaw rate, length, width, SDF at the centre
NUM_TERMS = 5  # reward terms in riskflow_env.rewards.REWARD_TERMS order

# params of `advance`: dt [s], accel_min, accel_max [m/s^2], yaw_rate_max [rad/s],
# speed_min, speed_max [m/s], turn_radius_min [m]
# params of `evaluate_scenes`: tau_max [s], max_distance [m], then the reward weights
# target_speed [m/s], speed, collision, offroad, risk, comfort, then accel_min,
# accel_max [m/s^2] and yaw_rate_max [rad/s] (the comfort term's scales)
_jit = numba.njit(cache=True, nogil=True)
# SHA-256 of compiled_pairs.py: editing that file must edit this one, or numba's cache
# keeps the old pair kernels inside evaluate_scenes.
PAIRS_DIGEST = "b90e1f90a6b66397655b28d61a503b7956e448f092d07dcd6b297693ff972071"


@_jit
def advance(current, present, active, actions, params):
    """:func:`riskflow_env.simulator.advance` of N flattened slots: ``current`` (N, 4),
    ``present``, ``active`` (N,) bool, ``actions`` (N, 2) -> new (N, 4), applied (N, 2)."""
    dt, accel_min, accel_max = params[0], params[1], params[2]
    yaw_max, speed_min, speed_max, radius = params[3], params[4], params[5], params[6]
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
        turn, _ = _turn_bounded(yaw_rate, v0, speed, radius)
        new[k, 0] = x + distance * math.cos(psi0)
        new[k, 1] = y + distance * math.sin(psi0)
        new[k, 2] = speed
        new[k, 3] = psi0 + dt * turn
        applied[k, 0], applied[k, 1] = accel, yaw_rate
    return new, applied


@numba.njit(cache=True, inline="always")
def _turn_bounded(yaw_rate, speed_before, speed, radius):
    """:func:`riskflow_env.dynamics._turn_bounded` of one step: ``yaw_rate`` within
    ``+-(speed_before + speed) / (2 radius)`` (no bound where ``radius`` is 0), and +1 / -1
    where it was above / below that bound, else 0 (the side its VJP follows)."""
    if radius > 0.0:
        reach = (speed_before + speed) * (0.5 / radius)
        if yaw_rate > reach:
            return reach, 1.0
        if yaw_rate < -reach:
            return -reach, -1.0
    return yaw_rate, 0.0


@numba.njit(cache=True, inline="always")
def _cell(flat, grid, x, y):
    """The bilinear cell of (x, y) (maps.sampling.interpolate_flat) on the map ``grid`` =
    (height, width, offset, origin_x, origin_y, resolution, scale) of :func:`_grid`:
    ``(col, row, col_c, row_c, fc, fr, v00, v01, v10, v11)``, the pixel coordinates, their
    clamp onto the pixel centres, the fractions within the cell and its corner values.
    ``scale`` is 1 / resolution where that is exact (a power-of-two resolution: the
    product then equals the reference's quotient), else 0 (divide). Shared by this
    module's SDF lookup and the planning loops' (``policies.learned.plan_kernels``)."""
    height, width, offset, origin_x, origin_y, resolution, scale = grid
    if scale > 0.0:
        col = (x - origin_x) * scale - 0.5
        row = (y - origin_y) * scale - 0.5
    else:
        col = (x - origin_x) / resolution - 0.5
        row = (y - origin_y) / resolution - 0.5
    col_c = min(max(col, 0.0), float(width - 1))
    row_c = min(max(row, 0.0), float(height - 1))
    col0 = max(min(int(col_c), width - 2), 0)
    row0 = max(min(int(row_c), height - 2), 0)
    fc = col_c - float(col0)
    fr = row_c - float(row0)
    base = numba.uint64(row0 * width + col0 + offset)  # unsigned: no wraparound test
    v00, v01 = float(flat[base]), float(flat[base + 1])
    v10, v11 = float(flat[base + width]), float(flat[base + width + 1])
    return col, row, col_c, row_c, fc, fr, v00, v01, v10, v11


@numba.njit(cache=True, inline="always")
def _sdf(flat, grid, x, y):
    """Bilinear SDF [m] at (x, y) (maps.sampling.interpolate_flat with extend) on the map
    ``grid`` of :func:`_grid` (:func:`_cell`)."""
    col, row, col_c, row_c, fc, fr, v00, v01, v10, v11 = _cell(flat, grid, x, y)
    gc, gr = 1.0 - fc, 1.0 - fr
    top = v00 * gc + v01 * fc
    bottom = v10 * gc + v11 * fc
    value = top * gr + bottom * fr
    off_c, off_r = col - col_c, row - row_c
    if value > 0.0 and (off_c != 0.0 or off_r != 0.0):  # off-road beyond the raster
        return value + math.sqrt(off_c * off_c + off_r * off_r) * grid[5]
    return value + 0.0


@_jit
def _grid(grid_int, grid_float, index):
    """Map ``index``'s raster geometry as one tuple (read once per scene)."""
    height, width, offset = grid_int[index, 0], grid_int[index, 1], grid_int[index, 2]
    origin_x, origin_y = grid_float[index, 0], grid_float[index, 1]
    return height, width, offset, origin_x, origin_y, grid_float[index, 2], grid_float[index, 3]


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
        flat, grid_int (G, 3) (height, width, offset), grid_float (G, 4) (origin_x,
            origin_y, resolution, exact 1 / resolution or 0): G maps' SDF rasters end to
            end (maps.stack's layout);
            scene_map: (S,) the map of each scene.
        offsets: (2, P) observation sample offsets in the agent frame, centre first.
        params: see the module's parameter comment.
        num_neighbors: neighbours per observation.
        observations: build the observations (else they come back empty). The pair
            features are kept for one scene at a time, as the observations need them.

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
    size = _OWN_SIZE + num_neighbors * NEIGHBOR_SIZE + rays
    mask = np.zeros((scenes, agents, agents), dtype=np.bool_)
    hit = np.zeros((scenes, agents, agents), dtype=np.bool_)
    features = np.empty((agents, agents, NUM_PAIR_FEATURES))  # read only where mask is set
    fraction = np.zeros((scenes, agents))
    depth = np.zeros((scenes, agents))
    centroid = np.zeros((scenes, agents), dtype=np.bool_)
    rows = np.zeros((scenes if observations else 0, agents, size), dtype=np.float32)
    terms = np.empty((NUM_TERMS, scenes, agents))
    reward = np.empty((scenes, agents))
    cos, sin, diag = np.empty(agents), np.empty(agents), np.empty(agents)
    risk_max = np.empty(agents)
    best_d, best_j = np.empty(max(num_neighbors, 1)), np.empty(max(num_neighbors, 1), np.int64)
    for s in range(scenes):
        st, ln, wd, valid = current[s], length[s], width[s], present[s]
        grid = _grid(grid_int, grid_float, scene_map[s])
        for i in range(agents):
            cos[i], sin[i] = math.cos(st[i, 3]), math.sin(st[i, 3])
            diag[i] = math.sqrt(ln[i] * ln[i] + wd[i] * wd[i])
            risk_max[i] = 0.0
        pairs(
            st,
            ln,
            wd,
            valid,
            cos,
            sin,
            diag,
            params,
            mask[s],
            features,
            observations,
            risk_max,
            hit[s],
        )
        for i in range(agents):
            x, y, c, sn = st[i, 0], st[i, 1], cos[i], sin[i]
            along, across = 0.5 * ln[i], 0.5 * wd[i]
            outside, deepest, centre = 0, -np.inf, 0.0
            for k in range(NUM_FOOTPRINT_POINTS):
                a, b = along * _ALONG[k], across * _ACROSS[k]
                value = _sdf(flat, grid, x + a * c - b * sn, y + a * sn + b * c)
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
            out = rows[s, i]  # float32: each value rounds as the reference's astype
            out[0], out[1], out[2], out[3], out[4] = speed, accel, yaw_rate, ln[i], wd[i]
            out[5] = centre
            if num_neighbors > 0:
                neighbors(
                    out[_OWN_SIZE:], features, mask[s], ln, wd, i, num_neighbors, best_d, best_j
                )
            first_ray = size - rays
            for p in range(rays):
                forward, left = offsets[0, p + 1], offsets[1, p + 1]
                px, py = x + (c * forward - sn * left), y + (sn * forward + c * left)
                out[first_ray + p] = _sdf(flat, grid, px, py)
    return mask, hit, fraction, depth, centroid, rows, terms, reward
