"""numba kernels of the lane graph's per-step lookups
(:class:`riskflow_env.agents.lane_graph.LaneGraph`): lane matching, positions along lanes
and their successors, and the distance to a dead end.

Each repeats, point by point, the formula of the numpy method it names, op for op and in
float64, so the two give the same numbers (``tests/riskflow_env/agents/test_lane_graph.py``
checks them against each other). The numpy methods are the reference: a step of IDM traffic
is a few hundred small array operations there, whose cost is per call, not arithmetic.

``tables`` is :meth:`LaneGraph.tables`: (start (S, 2), delta (S, 2), segment length,
arclength and heading (S,), segment lane (S,), segment bounding boxes (S, 2) low and high,
segment keys (S,), lane offsets, lengths, first and last segments (L,), successors (L, K)
and their joining arclengths (L, K)).
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)
_inline = numba.njit(cache=True, inline="always")

TWO_PI = 2 * math.pi


@_inline
def _wrap(angle):
    """``dynamics.wrap_angle``."""
    return angle + TWO_PI * math.floor((math.pi - angle) / TWO_PI)


@_jit
def match(xy, yaw, heading_weight, route, has_route, route_penalty, near, chunk, tables, out):
    """``LaneGraph.match``: ``out`` (4, N) = lane, arclength, lateral offset and heading
    error of each point (``route`` (N, L) bool when ``has_route``)."""
    start, delta, seg_length, seg_s, seg_heading, seg_lane, low, high = tables[:8]
    count, segments = xy.shape[0], start.shape[0]
    candidates = np.empty(segments, dtype=np.int64)
    for first in range(0, count, chunk):
        last = min(first + chunk, count)
        low_x, low_y, high_x, high_y = math.inf, math.inf, -math.inf, -math.inf
        for p in range(first, last):
            if xy[p, 0] != xy[p, 0] or xy[p, 1] != xy[p, 1]:  # NaN: numpy's box is NaN
                low_x = math.nan
                break
            low_x, high_x = min(low_x, xy[p, 0]), max(high_x, xy[p, 0])
            low_y, high_y = min(low_y, xy[p, 1]), max(high_y, xy[p, 1])
        low_x, low_y, high_x, high_y = low_x - near, low_y - near, high_x + near, high_y + near
        found = 0
        for g in range(segments):
            if high[g, 0] >= low_x and high[g, 1] >= low_y and low[g, 0] <= high_x:
                if low[g, 1] <= high_y:
                    candidates[found] = g
                    found += 1
        if found == 0:  # no segment near the chunk: all of them
            for g in range(segments):
                candidates[g] = g
            found = segments
        for p in range(first, last):
            free = True
            if has_route:
                for lane in range(route.shape[1]):
                    if route[p, lane]:
                        free = False
                        break
            best = math.inf
            pick, pick_s, pick_lateral, pick_error = 0, 0.0, 0.0, 0.0
            for q in range(found):
                g = candidates[q]
                d_x, d_y, length = delta[g, 0], delta[g, 1], seg_length[g]
                # the cost is at least the distance to the segment's bounding box: a
                # segment whose box is farther than the best cost cannot win (a segment of
                # length 0, whose cost is NaN, is always scored)
                box_x = max(low[g, 0] - xy[p, 0], xy[p, 0] - high[g, 0], 0.0)
                box_y = max(low[g, 1] - xy[p, 1], xy[p, 1] - high[g, 1], 0.0)
                if box_x * box_x + box_y * box_y > best * best and length > 0.0:
                    continue
                rel_x, rel_y = xy[p, 0] - start[g, 0], xy[p, 1] - start[g, 1]
                t = min(max((rel_x * d_x + rel_y * d_y) / (length * length), 0.0), 1.0)
                off_x, off_y = rel_x - t * d_x, rel_y - t * d_y
                cross = d_x * off_y - d_y * off_x
                lateral = (1.0 if cross >= 0 else -1.0) * math.sqrt(off_x * off_x + off_y * off_y)
                error = _wrap(yaw[p] - seg_heading[g])
                cost = abs(lateral) + heading_weight * (1.0 - math.cos(error))
                if not free and not route[p, seg_lane[g]]:
                    cost += route_penalty
                if q == 0 or cost < best or cost != cost:  # argmin: the first minimum or NaN
                    best, pick, pick_s = cost, g, seg_s[g] + t * length
                    pick_lateral, pick_error = lateral, error
                    if cost != cost:
                        break
            out[0, p], out[1, p] = seg_lane[pick], pick_s
            out[2, p], out[3, p] = pick_lateral, pick_error


@_inline
def _next(lane, row, route, has_route, successors, successors_s):
    """``LaneGraph._next`` of one lane: the continuation (-1 at a dead end) and its
    joining arclength; with a route, the first-ranked successor on ``route[row]``."""
    pick = 0
    if has_route:
        for k in range(successors.shape[1]):
            candidate = successors[lane, k]
            if candidate >= 0 and route[row, candidate]:
                pick = k
                break
    return successors[lane, pick], successors_s[lane, pick]


@_inline
def _advance(lane, s, row, route, has_route, length, successors, successors_s, hops):
    """``LaneGraph.advance`` of one (lane, s)."""
    for _ in range(hops):
        following, entry = _next(lane, row, route, has_route, successors, successors_s)
        if not (s > length[lane] and following >= 0):
            break
        s = s - length[lane] + entry
        lane = following
    return lane, s


@_jit
def positions(lane, s, route, has_route, hops, tables, out):
    """``LaneGraph.position``: ``out`` (N, P, 3) = x, y and heading of each (lane, s)
    (N, P) along the lanes and their successors (row n on ``route[n]``)."""
    start, delta, seg_length, seg_s, seg_heading = tables[:5]
    key, offset, length, first, last, successors, successors_s = tables[8:]
    for n in range(lane.shape[0]):
        for p in range(lane.shape[1]):
            on, at = _advance(
                lane[n, p], s[n, p], n, route, has_route, length, successors, successors_s, hops
            )
            query = offset[on] + min(max(at, 0.0), length[on])
            g = np.searchsorted(key, query, side="right") - 1
            g = min(max(g, first[on]), last[on])
            fraction = (at - seg_s[g]) / seg_length[g]
            out[n, p, 0] = start[g, 0] + fraction * delta[g, 0]
            out[n, p, 1] = start[g, 1] + fraction * delta[g, 1]
            out[n, p, 2] = seg_heading[g]


@_jit
def dead_end_distances(lane, s, route, has_route, hops, tables, out):
    """``LaneGraph.distance_to_dead_end``: ``out`` (N,) [m], inf where no dead end is met
    within ``hops`` lanes."""
    length, successors, successors_s = tables[10], tables[13], tables[14]
    for n in range(lane.shape[0]):
        on, remaining = lane[n], length[lane[n]] - s[n]
        for _ in range(hops):
            following, entry = _next(on, n, route, has_route, successors, successors_s)
            if following < 0:
                break
            remaining = remaining + length[following] - entry
            on = following
        ended = _next(on, n, route, has_route, successors, successors_s)[0] < 0
        out[n] = remaining if ended else math.inf
