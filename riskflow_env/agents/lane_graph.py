"""Lane graph: a map's lane centrelines flattened into one segment table.

Matching every agent to a lane (distance plus a heading penalty) and looking up points
ahead along lanes and their successors become a few array ops, with no Python loop over
agents (nor over lanes). All arrays are numpy; ``N`` is the number of agents queried.
Where numba is installed (the ``fast`` extra) :meth:`LaneGraph.match`,
:meth:`~LaneGraph.position` and :meth:`~LaneGraph.distance_to_dead_end` run as numba
kernels (:mod:`riskflow_env.agents.lane_kernels`) with the same formulas; the numpy code
here is their reference and runs without numba or with ``RISKFLOW_COMPILED=0``.
"""

from __future__ import annotations

import functools
from types import ModuleType

import numpy as np

from riskflow_env.dynamics import wrap_angle
from riskflow_env.kernel_loading import optional_kernels
from riskflow_env.maps import DrivableMap

HEADING_WEIGHT = 5.0  # [m] lane-matching cost of a lane at 90 deg to the agent's heading
ROUTE_PENALTY = 3.0  # [m] lane-matching cost of a lane off an agent's route
NEAR = 25.0  # [m] segments farther than this from every query point are not considered
MATCH_CHUNK = 64  # query points projected at once (bounds the (points, segments) arrays)
MAX_HOPS = 4  # successor lanes followed by a lookup ahead
MERGE_MAX_OFFSET = 0.75  # [lane widths] farthest a dead end may lie from a lane it merges into
MERGE_MAX_TURN = 1.2  # [rad] largest heading change of a merge (roundabout entries: ~60 deg)
REACH_CAP = 300.0  # [m] a successor whose path runs this far without a dead end is "open"
NO_ROUTE = np.zeros((1, 1), dtype=bool)  # the kernels' route argument without a route


def _kernel_route(route: np.ndarray | None) -> tuple[np.ndarray, bool]:
    """The kernels' ``(route, has_route)`` arguments."""
    return (NO_ROUTE, False) if route is None else (np.ascontiguousarray(route), True)


def compiled() -> ModuleType | None:
    """The lane kernels, or None where numba is missing, finds no writable cache directory
    (a warning says so) or ``RISKFLOW_COMPILED=0``: the numpy reference runs."""
    return optional_kernels("riskflow_env.agents.lane_kernels", "the compiled lane lookups")


class LaneGraph:
    """Lane centrelines of one map as a flat segment table.

    Lanes are laid end to end on one global arclength axis (``offset[lane] + s``), so
    ``np.searchsorted`` finds the segment of any (lane, s) pair at once. Each lane's
    continuations (:meth:`_edges`) are ranked: first those whose onward path runs at
    least ``REACH_CAP`` metres without a dead end, then by heading change ("straight
    on"). Lookups ahead take the best-ranked one, or, given a ``route`` ((N, L) bool,
    the lanes each query agent should use, e.g. those its logged future visits), the
    best-ranked one on the route.

    Args:
        drivable_map: a map with at least one lane.
    """

    def __init__(self, drivable_map: DrivableMap) -> None:
        lanes = drivable_map.lanes
        if not lanes:
            raise ValueError(f"LaneGraph: map {drivable_map.name!r} has no lane centrelines")
        self.num_lanes = len(lanes)
        self.length = np.array([lane.length for lane in lanes])  # (L,) [m]
        self.width = np.array([lane.width for lane in lanes])  # (L,) [m]
        self.speed_limit = np.array(  # (L,) [m/s], NaN where the map has none
            [np.nan if lane.speed_limit is None else lane.speed_limit for lane in lanes]
        )
        self.offset = np.concatenate([[0.0], np.cumsum(self.length + 1.0)[:-1]])  # (L,) [m]
        counts = np.array([len(lane.centerline) - 1 for lane in lanes])
        self.first_segment = np.concatenate([[0], np.cumsum(counts)[:-1]])  # (L,)
        self.last_segment = self.first_segment + counts - 1  # (L,)
        self.segment_lane = np.repeat(np.arange(self.num_lanes), counts)  # (S,)
        self.start = np.concatenate([lane.centerline[:-1] for lane in lanes])  # (S, 2) [m]
        self.delta = np.concatenate([np.diff(lane.centerline, axis=0) for lane in lanes])
        self.segment_length = np.linalg.norm(self.delta, axis=-1)  # (S,) [m]
        self.segment_s = np.concatenate([lane.arclength[:-1] for lane in lanes])  # (S,) [m]
        self.segment_heading = np.arctan2(self.delta[:, 1], self.delta[:, 0])  # (S,) [rad]
        self.segment_key = self.offset[self.segment_lane] + self.segment_s  # (S,) increasing
        self.segment_low = np.minimum(self.start, self.start + self.delta)  # (S, 2) bbox
        self.segment_high = np.maximum(self.start, self.start + self.delta)

        source, target, entry = self._edges(drivable_map)
        reach = self.length.copy()  # path length before a dead end, capped at REACH_CAP
        for _ in range(self.num_lanes):  # relaxation; converges in at most L rounds
            best = np.zeros(self.num_lanes)
            np.maximum.at(best, source, reach[target] - entry)
            updated = np.minimum(self.length + best, REACH_CAP)
            if np.array_equal(updated, reach):
                break
            reach = updated
        end_heading = self.segment_heading[self.last_segment]
        start_heading = self.segment_heading[self._segment_at(target, entry)]
        score = np.abs(wrap_angle(start_heading - end_heading[source]))
        score += 10.0 * (reach[target] - entry < REACH_CAP - 1e-9)
        order = np.lexsort((score, source))
        source, target, entry = source[order], target[order], entry[order]
        rank = np.arange(source.size) - np.searchsorted(source, source)
        width = int(rank.max()) + 1 if rank.size else 1
        self.successors = np.full((self.num_lanes, width), -1)  # (L, K) ranked, -1 padded
        self.successors_s = np.zeros((self.num_lanes, width))  # (L, K) [m] joining arclength
        self.successors[source, rank] = target
        self.successors_s[source, rank] = entry

    @functools.cached_property
    def tables(self) -> tuple:
        """The segment and lane tables as the kernels take them (module
        :mod:`~riskflow_env.agents.lane_kernels`)."""
        return (
            self.start, self.delta, self.segment_length, self.segment_s,
            self.segment_heading, self.segment_lane, self.segment_low, self.segment_high,
            self.segment_key, self.offset, self.length, self.first_segment,
            self.last_segment, self.successors, self.successors_s,
        )  # fmt: skip

    def _route_fits(self, route: np.ndarray | None, count: int) -> bool:
        return route is None or (
            isinstance(route, np.ndarray) and route.dtype == bool
            and route.shape == (count, self.num_lanes)
        )  # fmt: skip

    def _lanes_fit(self, lane: np.ndarray, route: np.ndarray | None) -> bool:
        """The kernels take the query: integer lanes (N, ...) with N >= 1, all valid, and a
        route of N rows; anything else runs the reference (which raises where it must)."""
        return (
            lane.ndim >= 1 and lane.size > 0 and np.issubdtype(lane.dtype, np.integer)
            and int(lane.min()) >= 0 and int(lane.max()) < self.num_lanes
            and self._route_fits(route, lane.shape[0])
        )  # fmt: skip

    def _edges(self, drivable_map: DrivableMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(source, target, entry arclength [m]) of every continuation of a lane.

        Listed successors are joined at their start. A lane with none whose end lies
        on another lane (within ``MERGE_MAX_OFFSET`` of its width, heading within
        ``MERGE_MAX_TURN``, 1 m or more before that lane's end) merges into it there,
        e.g. an entry ending on the ring of a roundabout. Dead ends are taken in spatial
        order, ``MATCH_CHUNK`` at a time, against the segments within reach of them only
        (all of them made this quadratic: 20,000 dead ends took 38 s).
        """
        lanes = drivable_map.lanes
        index = {lane.lane_id: i for i, lane in enumerate(lanes)}
        pairs = [
            (i, index[n], 0.0) for i, ln in enumerate(lanes) for n in ln.successors if n in index
        ]
        listed = {i for i, _, _ in pairs}
        ends = np.array([i for i in range(self.num_lanes) if i not in listed], dtype=int)
        end_points = np.array([lanes[i].centerline[-1] for i in ends]).reshape(-1, 2)
        ends = ends[np.lexsort(np.floor(end_points / NEAR).T)]  # nearby ends share a chunk
        reach = MERGE_MAX_OFFSET * float(self.width.max())  # farther segments never qualify
        for chunk in np.array_split(ends, max(1, ends.size // MATCH_CHUNK)):
            if not chunk.size:
                continue
            end_xy = np.stack([lanes[i].centerline[-1] for i in chunk])
            low, high = end_xy.min(axis=0) - reach, end_xy.max(axis=0) + reach
            near = np.all((self.segment_high >= low) & (self.segment_low <= high), axis=1)
            segments = np.flatnonzero(near)  # a map's dead ends against nearby segments only
            if not segments.size:
                continue
            distance, error, s = self._project(
                end_xy, self.segment_heading[self.last_segment[chunk]], segments
            )
            lane = self.segment_lane[segments]
            distance = np.where(lane == chunk[:, None], np.inf, np.abs(distance))
            distance = np.where(np.abs(error) < MERGE_MAX_TURN, distance, np.inf)
            best = np.argmin(distance, axis=-1)
            rows = np.arange(chunk.size)
            target, entry = lane[best], s[rows, best]
            ok = distance[rows, best] < MERGE_MAX_OFFSET * self.width[target]
            ok &= entry < self.length[target] - 1.0
            pairs += zip(chunk[ok].tolist(), target[ok].tolist(), entry[ok].tolist(), strict=True)
        edges = np.array(pairs, dtype=float).reshape(-1, 3)
        return edges[:, 0].astype(int), edges[:, 1].astype(int), edges[:, 2]

    def _project(
        self, xy: np.ndarray, yaw: np.ndarray, segments: np.ndarray | slice = slice(None)
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed lateral distance [m] (positive left), heading error (point minus segment)
        [rad] and arclength [m] of points (N, 2) with headings (N,) on ``segments``: (N, S)."""
        start, delta, length = (
            self.start[segments],
            self.delta[segments],
            self.segment_length[segments],
        )
        rel = xy[:, None, :] - start  # (N, S, 2)
        t = np.clip(np.einsum("nsk,sk->ns", rel, delta) / length**2, 0.0, 1.0)
        offset = rel - t[..., None] * delta
        cross = delta[:, 0] * offset[..., 1] - delta[:, 1] * offset[..., 0]
        distance = np.where(cross >= 0, 1.0, -1.0) * np.linalg.norm(offset, axis=-1)
        error = wrap_angle(yaw[:, None] - self.segment_heading[segments])
        return distance, error, self.segment_s[segments] + t * length

    def _segment_at(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(...) segment index holding arclength ``s`` (clamped to the lane) of ``lane``."""
        key = self.offset[lane] + np.clip(s, 0.0, self.length[lane])
        segment = np.searchsorted(self.segment_key, key, side="right") - 1
        return np.clip(segment, self.first_segment[lane], self.last_segment[lane])

    def match(
        self,
        xy: np.ndarray,
        yaw: np.ndarray,
        heading_weight: float = HEADING_WEIGHT,
        route: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lane of each agent: least ``|lateral| + heading_weight * (1 - cos(heading error))``,
        plus ``ROUTE_PENALTY`` for lanes off the agent's route when it has one.

        The heading term keeps agents off crossing and opposite lanes where lanes
        overlap (junctions) or run side by side; the route term picks, among lanes
        that start together, the one the agent takes. Only segments within ``NEAR``
        of the query points are searched (all of them when none is).

        Args:
            xy: (N, 2) [m] positions.
            yaw: (N,) [rad] headings.
            heading_weight: [m] cost of a 90 deg heading error (twice that when opposite).
            route: (N, L) bool, lanes on each agent's route; rows without any are free.

        Returns:
            lane: (N,) int lane index; s: (N,) [m] arclength on it; lateral: (N,) [m]
            signed offset (positive left); heading_error: (N,) [rad] agent minus lane.
        """
        out = np.zeros((4, len(xy)))
        kernels = compiled()
        xy, yaw = np.asarray(xy, dtype=np.float64), np.asarray(yaw, dtype=np.float64)
        if (
            kernels is not None
            and xy.ndim == 2 and xy.shape[1] == 2 and yaw.shape == xy.shape[:1] and len(xy)
            and heading_weight >= 0  # the kernel's pruning needs costs >= the distance
            and self._route_fits(route, len(xy))
        ):  # fmt: skip
            kernels.match(
                np.ascontiguousarray(xy), np.ascontiguousarray(yaw), float(heading_weight),
                *_kernel_route(route), ROUTE_PENALTY, NEAR, MATCH_CHUNK, self.tables, out,
            )  # fmt: skip
            return out[0].astype(int), out[1], out[2], out[3]
        for start in range(0, len(xy), MATCH_CHUNK):  # chunks of query points, bounded memory
            rows = np.arange(start, min(start + MATCH_CHUNK, len(xy)))
            low, high = xy[rows].min(axis=0) - NEAR, xy[rows].max(axis=0) + NEAR
            near = np.all((self.segment_high >= low) & (self.segment_low <= high), axis=1)
            segments = np.flatnonzero(near) if near.any() else np.arange(len(self.start))
            lateral, error, s = self._project(xy[rows], yaw[rows], segments)
            cost = np.abs(lateral) + heading_weight * (1.0 - np.cos(error))
            if route is not None:
                on_route = route[rows][:, self.segment_lane[segments]]
                cost += ROUTE_PENALTY * (~on_route & route[rows].any(axis=1, keepdims=True))
            best = np.argmin(cost, axis=-1)[:, None]
            lane = self.segment_lane[segments][best[:, 0]]
            picked = [np.take_along_axis(v, best, axis=-1)[:, 0] for v in (s, lateral, error)]
            out[:, rows] = np.stack([lane, *picked])
        return out[0].astype(int), out[1], out[2], out[3]

    def route_of(self, xy: np.ndarray, yaw: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(N, L) bool: lanes that tracks (N, T, 2) [m] / (N, T) [rad] / (N, T) bool visit
        (matched within a lane width and 0.6 rad of the lane heading)."""
        rows, steps = np.nonzero(valid)
        route = np.zeros((valid.shape[0], self.num_lanes), dtype=bool)
        if rows.size:
            lane, _, lateral, error = self.match(xy[rows, steps], yaw[rows, steps])
            ok = (np.abs(lateral) < self.width[lane]) & (np.abs(error) < 0.6)
            route[rows[ok], lane[ok]] = True
        return route

    def _next(self, lane: np.ndarray, route: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Continuation lane (-1 at a dead end) and joining arclength [m] of ``lane`` (N, ...)."""
        if route is None:
            return self.successors[lane, 0], self.successors_s[lane, 0]
        candidates = self.successors[lane]  # (N, ..., K)
        flat = np.maximum(candidates, 0).reshape(len(route), -1)
        on = np.take_along_axis(route, flat, axis=1).reshape(candidates.shape) & (candidates >= 0)
        pick = np.where(on.any(axis=-1), np.argmax(on, axis=-1), 0)[..., None]
        chosen = np.take_along_axis(candidates, pick, axis=-1)[..., 0]
        return chosen, np.take_along_axis(self.successors_s[lane], pick, axis=-1)[..., 0]

    def advance(
        self, lane: np.ndarray, s: np.ndarray, route: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Carry arclengths past a lane's end onto its successors (up to ``MAX_HOPS``).

        Args:
            lane: (N, ...) int lane indices; s: (N, ...) [m] arclengths.
            route: (N, L) bool or None, see the class docstring.

        Returns:
            lane, s: (N, ...) where s <= length[lane] unless the path hits a dead end.
        """
        lane, s = np.broadcast_arrays(lane, s)
        for _ in range(MAX_HOPS):  # a fixed number of vectorised hops, not a loop over agents
            nxt, entry = self._next(lane, route)
            move = (s > self.length[lane]) & (nxt >= 0)
            if not move.any():
                break
            s = np.where(move, s - self.length[lane] + entry, s)
            lane = np.where(move, nxt, lane)
        return lane, s

    def position(
        self, lane: np.ndarray, s: np.ndarray, route: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Point and heading at arclength ``s`` along ``lane`` and its successors.

        Beyond a dead end (or before a lane's start) the last (first) segment is
        extended in a straight line.

        Args:
            lane: (N, ...) int lane indices; s: (N, ...) [m]; route: (N, L) bool or None.

        Returns:
            xy: (N, ..., 2) [m]; heading: (N, ...) [rad].
        """
        kernels = compiled()
        lane, s = np.broadcast_arrays(lane, s)
        if kernels is not None and self._lanes_fit(lane, route):
            rows = lane.reshape(lane.shape[0], -1).astype(np.int64)
            arclength = np.ascontiguousarray(s.reshape(rows.shape), dtype=float)
            out = np.empty((*rows.shape, 3))
            kernels.positions(
                np.ascontiguousarray(rows), arclength,
                *_kernel_route(route), MAX_HOPS, self.tables, out,
            )  # fmt: skip
            out = out.reshape(*lane.shape, 3)
            return out[..., :2], out[..., 2]
        lane, s = self.advance(lane, s, route)
        segment = self._segment_at(lane, s)
        fraction = (s - self.segment_s[segment]) / self.segment_length[segment]
        xy = self.start[segment] + fraction[..., None] * self.delta[segment]
        return xy, self.segment_heading[segment]

    def distance_to_dead_end(
        self, lane: np.ndarray, s: np.ndarray, route: np.ndarray | None = None
    ) -> np.ndarray:
        """(N,) [m] path distance from ``(lane, s)`` to the end of a lane without
        successor, inf if none is met within ``MAX_HOPS`` lanes."""
        kernels = compiled()
        lane, s = np.broadcast_arrays(lane, s)
        if kernels is not None and lane.ndim == 1 and self._lanes_fit(lane, route):
            out = np.empty(len(lane))
            kernels.dead_end_distances(
                np.ascontiguousarray(lane, dtype=np.int64), np.ascontiguousarray(s, float),
                *_kernel_route(route), MAX_HOPS, self.tables, out,
            )  # fmt: skip
            return out
        remaining = self.length[lane] - s
        for _ in range(MAX_HOPS):
            nxt, entry = self._next(lane, route)
            ended = nxt < 0
            if ended.all():
                break
            remaining = np.where(ended, remaining, remaining + self.length[nxt] - entry)
            lane = np.where(ended, lane, nxt)
        return np.where(self._next(lane, route)[0] < 0, remaining, np.inf)

    def curvature_ahead(
        self,
        lane: np.ndarray,
        s: np.ndarray,
        distance: np.ndarray,
        route: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N,) [1/m] largest |heading change| per metre over ``distance`` (N,) [m] ahead,
        from headings sampled every quarter of ``distance``."""
        ahead = s[:, None] + distance[:, None] * np.linspace(0.0, 1.0, 5)  # (N, 5)
        _, heading = self.position(lane[:, None], ahead, route)
        turn = np.abs(wrap_angle(np.diff(heading, axis=-1)))
        return turn.max(axis=-1) / np.maximum(distance * 0.25, 1e-6)
