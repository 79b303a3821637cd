"""numba kernel of the WOSAC features' distance to the nearest object
(:func:`riskflow_env.metrics.wosac_features.interaction_features`).

The numpy reference, :func:`~riskflow_env.metrics.wosac_features.box_signed_distance`,
computes the signed distance of every pair of boxes at every step, (T, A, A) arrays of
corners and SAT gaps, and keeps the smallest of each row. This kernel visits each pair
once per step with the same formulas and skips a pair whose centres are farther apart
than its circumradii plus the smaller of the two distances found so far: the boxes'
distance exceeds that, so it cannot be the nearest. The two agree to float rounding
(``tests/riskflow_env/metrics/test_wosac.py``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)
CORNER_ALONG = (1.0, 1.0, -1.0, -1.0)  # geometry.box_corners: FR, FL, RL, RR
CORNER_ACROSS = (-1.0, 1.0, 1.0, -1.0)


@_jit
def _min(a, b):
    """numpy's minimum: NaN when either is."""
    if a != a or b != b:
        return math.nan
    return min(a, b)


@_jit
def _corner_distance(x, y, cos, sin, half_len, half_wid, cx, cy, c_cos, c_sin, c_len, c_wid):
    """Smallest distance [m] from the corners of box c to box (x, y, yaw, size)."""
    best = math.inf
    for k in range(4):
        along, across = 0.5 * c_len * CORNER_ALONG[k], 0.5 * c_wid * CORNER_ACROSS[k]
        dx = cx + along * c_cos - across * c_sin - x
        dy = cy + along * c_sin + across * c_cos - y
        out_x = max(abs(cos * dx + sin * dy) - half_len, 0.0)
        out_y = max(abs(-sin * dx + cos * dy) - half_wid, 0.0)
        best = _min(best, math.hypot(out_x, out_y))
    return best


@_jit
def _signed_distance(xa, ya, ca, sa, la, wa, xb, yb, cb, sb, lb, wb):
    """``box_signed_distance`` of one pair: the Euclidean gap when apart, minus the
    penetration depth (the SAT separation) when overlapping."""
    dx, dy = xb - xa, yb - ya
    cos_ab, sin_ab = abs(ca * cb + sa * sb), abs(ca * sb - sa * cb)
    gap = max(
        max(
            abs(dx * ca + dy * sa) - 0.5 * la - (0.5 * lb * cos_ab + 0.5 * wb * sin_ab),
            abs(dy * ca - dx * sa) - 0.5 * wa - (0.5 * lb * sin_ab + 0.5 * wb * cos_ab),
        ),
        max(
            abs(dx * cb + dy * sb) - 0.5 * lb - (0.5 * la * cos_ab + 0.5 * wa * sin_ab),
            abs(dy * cb - dx * sb) - 0.5 * wb - (0.5 * la * sin_ab + 0.5 * wa * cos_ab),
        ),
    )
    if gap <= 0.0:
        return gap
    return _min(
        _corner_distance(xa, ya, ca, sa, 0.5 * la, 0.5 * wa, xb, yb, cb, sb, lb, wb),
        _corner_distance(xb, yb, cb, sb, 0.5 * lb, 0.5 * wb, xa, ya, ca, sa, la, wa),
    )


@_jit
def nearest_objects(states, valid, length, width, out):
    """``out`` (A, T) [m]: each valid agent's signed distance to the nearest other valid
    one at each step (inf when alone); ``states`` (A, T, 4), ``valid`` (A, T)."""
    agents, steps = valid.shape
    radius = np.empty(agents)
    for a in range(agents):
        radius[a] = 0.5 * math.hypot(length[a], width[a])
    for t in range(steps):
        cos, sin = np.empty(agents), np.empty(agents)
        for a in range(agents):
            out[a, t] = math.inf
            cos[a], sin[a] = math.cos(states[a, t, 3]), math.sin(states[a, t, 3])
        for a in range(agents):
            if not valid[a, t]:
                continue
            xa, ya = states[a, t, 0], states[a, t, 1]
            for b in range(a + 1, agents):
                if not valid[b, t]:
                    continue
                xb, yb = states[b, t, 0], states[b, t, 1]
                bound = math.hypot(xb - xa, yb - ya) - radius[a] - radius[b]
                if bound > out[a, t] and bound > out[b, t]:
                    continue  # farther than both nearest objects found so far
                distance = _signed_distance(
                    xa, ya, cos[a], sin[a], length[a], width[a],
                    xb, yb, cos[b], sin[b], length[b], width[b],
                )  # fmt: skip
                out[a, t] = _min(out[a, t], distance)
                out[b, t] = _min(out[b, t], distance)
