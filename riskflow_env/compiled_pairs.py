"""numba kernels of the compiled step's vehicle pairs (:mod:`riskflow_env.compiled`):
the TTC risk features (:mod:`riskflow_env.risk`), the separating-axis collision test
(:mod:`riskflow_env.geometry`) and the nearest observed neighbours
(:mod:`riskflow_env.observations`), each repeating the reference's floating-point
operations in its order (see :mod:`riskflow_env.compiled_kernels`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from riskflow_env.risk import NUM_PAIR_FEATURES

NEIGHBOR_SIZE = NUM_PAIR_FEATURES + 3  # pair features, length, width, presence
_jit = numba.njit(cache=True, nogil=True)


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
def pairs(st, ln, wd, valid, cos, sin, diag, params, mask, features, full, risk_max, hit):
    """Pair mask, features (the observed pairs' entries of ``features`` (A, A, 8), when
    ``full``), row-max risk and collisions of one scene (risk.pairwise_features /
    pair_risk, geometry.pairwise_overlap)."""
    agents = st.shape[0]
    tau_max, max_distance = params[0], params[1]
    far = (max_distance * 1.001) ** 2  # beyond it no frame distance is within range
    row = np.empty(NUM_PAIR_FEATURES)
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
                    features[a, b, :] = row


@_jit
def neighbors(out, features, mask, ln, wd, i, count, best_d, best_j):
    """The ``count`` nearest observed neighbours of i (stable on ties, as the reference's
    argsort) into ``out`` (count * 11,), zeros before; absent ones stay zero."""
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
        j, at = best_j[k], k * NEIGHBOR_SIZE
        for f in range(NUM_PAIR_FEATURES):
            out[at + f] = features[i, j, f]
        end = at + NUM_PAIR_FEATURES
        out[end], out[end + 1], out[end + 2] = ln[j], wd[j], 1.0
