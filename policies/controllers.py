"""Shared driving primitives for scene policies, vectorised over agents.

* :class:`LaneGraph` — a map's lane centrelines flattened into one segment table, so
  that matching every agent to a lane (distance plus a heading penalty) and looking
  up points ahead along lanes and their successors are a few array ops, with no
  Python loop over agents (nor over lanes).
* :func:`pure_pursuit` — yaw rate that steers a unicycle toward a lookahead point;
  :func:`arc_frame` — points in a vehicle's frame bent along its steering arc.
* :func:`speed_control` — proportional speed tracking.
* :func:`idm_acceleration` — the Intelligent Driver Model (Treiber, Hennecke and
  Helbing, "Congested traffic states in empirical observations and microscopic
  simulations", Phys. Rev. E 62, 1805, 2000).

All arrays are numpy; ``N`` is the number of agents queried.
"""

from __future__ import annotations

import numpy as np

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW, wrap_angle
from riskflow_env.maps import DrivableMap

HEADING_WEIGHT = 5.0  # [m] lane-matching cost of a lane at 90 deg to the agent's heading
MAX_HOPS = 4  # successor lanes followed by a lookup ahead
MERGE_MAX_OFFSET = 0.75  # [lane widths] farthest a dead end may lie from a lane it merges into
MERGE_MAX_TURN = 1.2  # [rad] largest heading change of a merge (roundabout entries: ~60 deg)
REACH_CAP = 300.0  # [m] a successor whose path runs this far without a dead end is "open"


class LaneGraph:
    """Lane centrelines of one map as a flat segment table.

    Lanes are laid end to end on one global arclength axis (``offset[lane] + s``), so
    ``np.searchsorted`` finds the segment of any (lane, s) pair at once. Each lane
    keeps one successor (-1 for a dead end): among those whose onward path runs at
    least ``REACH_CAP`` metres without a dead end (all, if none does), the one whose
    start heading is closest to the lane's end heading ("straight on").

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
        turn = np.abs(wrap_angle(start_heading - end_heading[source]))
        # prefer successors that do not run into a dead end within REACH_CAP, then straight on
        score = turn + 10.0 * (reach[target] - entry < REACH_CAP - 1e-9)
        order = np.lexsort((score, source))
        first = np.unique(source[order], return_index=True)[1]
        chosen = order[first]
        self.successor = np.full(self.num_lanes, -1)  # (L,) chosen successor, -1 if none
        self.successor[source[chosen]] = target[chosen]
        self.successor_s = np.zeros(self.num_lanes)  # (L,) [m] where the successor is joined
        self.successor_s[source[chosen]] = entry[chosen]

    def _edges(self, drivable_map: DrivableMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(source, target, entry arclength [m]) of every continuation of a lane.

        Listed successors are joined at their start. A lane with none whose end lies
        on another lane (within ``MERGE_MAX_OFFSET`` of its width, heading within
        ``MERGE_MAX_TURN``, 1 m or more before that lane's end) merges into it there,
        e.g. an entry ending on the ring of a roundabout.
        """
        lanes = drivable_map.lanes
        index = {lane.lane_id: i for i, lane in enumerate(lanes)}
        pairs = [
            (i, index[n], 0.0)
            for i, lane in enumerate(lanes)
            for n in lane.successors
            if n in index
        ]
        listed = {i for i, _, _ in pairs}
        ends = np.array([i for i in range(self.num_lanes) if i not in listed], dtype=int)
        if ends.size:
            end_xy = np.stack([lanes[i].centerline[-1] for i in ends])
            end_yaw = self.segment_heading[self.last_segment[ends]]
            distance, error, s, lane = self._project(end_xy, end_yaw)
            distance = np.where(lane == ends[:, None], np.inf, np.abs(distance))
            distance = np.where(np.abs(error) < MERGE_MAX_TURN, distance, np.inf)
            best = np.argmin(distance, axis=-1)
            rows = np.arange(ends.size)
            target, entry = lane[rows, best], s[rows, best]
            ok = (distance[rows, best] < MERGE_MAX_OFFSET * self.width[target]) & (
                entry < self.length[target] - 1.0
            )
            pairs += zip(ends[ok].tolist(), target[ok].tolist(), entry[ok].tolist(), strict=True)
        edges = np.array(pairs, dtype=float).reshape(-1, 3)
        return edges[:, 0].astype(int), edges[:, 1].astype(int), edges[:, 2]

    def _project(
        self, xy: np.ndarray, yaw: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Projection of points (N, 2) [m] with headings (N,) on every segment: distance,
        heading error (point minus segment) [rad], arclength [m] and lane, each (N, S)."""
        rel = xy[:, None, :] - self.start  # (N, S, 2)
        t = np.clip(np.einsum("nsk,sk->ns", rel, self.delta) / self.segment_length**2, 0.0, 1.0)
        offset = rel - t[..., None] * self.delta
        cross = self.delta[:, 0] * offset[..., 1] - self.delta[:, 1] * offset[..., 0]
        distance = np.where(cross >= 0, 1.0, -1.0) * np.linalg.norm(offset, axis=-1)
        error = wrap_angle(yaw[:, None] - self.segment_heading)
        s = self.segment_s + t * self.segment_length
        return distance, error, s, np.broadcast_to(self.segment_lane, s.shape)

    def _segment_at(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(...) segment index holding arclength ``s`` (clamped to the lane) of ``lane``."""
        key = self.offset[lane] + np.clip(s, 0.0, self.length[lane])
        segment = np.searchsorted(self.segment_key, key, side="right") - 1
        return np.clip(segment, self.first_segment[lane], self.last_segment[lane])

    def match(
        self, xy: np.ndarray, yaw: np.ndarray, heading_weight: float = HEADING_WEIGHT
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lane of each agent: least ``distance + heading_weight * (1 - cos(heading error))``.

        The heading term keeps agents off crossing and opposite lanes where lanes
        overlap (junctions) or run side by side.

        Args:
            xy: (N, 2) [m] positions.
            yaw: (N,) [rad] headings.
            heading_weight: [m] cost of a 90 deg heading error (twice that when opposite).

        Returns:
            lane: (N,) int lane index; s: (N,) [m] arclength on it; lateral: (N,) [m]
            signed offset (positive left); heading_error: (N,) [rad] agent minus lane.
        """
        lateral, error, s, lane = self._project(xy, yaw)
        best = np.argmin(np.abs(lateral) + heading_weight * (1.0 - np.cos(error)), axis=-1)[:, None]

        def pick(values: np.ndarray) -> np.ndarray:
            return np.take_along_axis(values, best, axis=-1)[:, 0]

        return pick(lane), pick(s), pick(lateral), pick(error)

    def advance(self, lane: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Carry arclengths past a lane's end onto its successors (up to ``MAX_HOPS``).

        Args:
            lane: (...) int lane indices; s: (...) [m] arclengths, broadcast together.

        Returns:
            lane, s: (...) where s <= length[lane] unless the path hits a dead end.
        """
        lane, s = np.broadcast_arrays(lane, s)
        for _ in range(MAX_HOPS):  # a fixed number of vectorised hops, not a loop over agents
            nxt = self.successor[lane]
            move = (s > self.length[lane]) & (nxt >= 0)
            if not move.any():
                break
            s = np.where(move, s - self.length[lane] + self.successor_s[lane], s)
            lane = np.where(move, nxt, lane)
        return lane, s

    def position(self, lane: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Point and heading at arclength ``s`` along ``lane`` and its successors.

        Beyond a dead end (or before a lane's start) the last (first) segment is
        extended in a straight line.

        Args:
            lane: (...) int lane indices; s: (...) [m], broadcast together.

        Returns:
            xy: (..., 2) [m]; heading: (...) [rad].
        """
        lane, s = self.advance(lane, s)
        segment = self._segment_at(lane, s)
        fraction = (s - self.segment_s[segment]) / self.segment_length[segment]
        xy = self.start[segment] + fraction[..., None] * self.delta[segment]
        return xy, self.segment_heading[segment]

    def distance_to_dead_end(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(N,) [m] path distance from ``(lane, s)`` to the end of a lane without
        successor, inf if none is met within ``MAX_HOPS`` lanes."""
        remaining = self.length[lane] - s
        current = lane
        for _ in range(MAX_HOPS):
            nxt = self.successor[current]
            ended = nxt < 0
            if ended.all():
                break
            joined = self.length[np.maximum(nxt, 0)] - self.successor_s[current]
            remaining = np.where(ended, remaining, remaining + joined)
            current = np.where(ended, current, nxt)
        return np.where(self.successor[current] < 0, remaining, np.inf)

    def curvature_ahead(self, lane: np.ndarray, s: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """(N,) [1/m] largest |heading change| per metre over ``distance`` (N,) [m] ahead,
        from headings sampled every quarter of ``distance``."""
        fractions = np.linspace(0.0, 1.0, 5)
        ahead = s[:, None] + distance[:, None] * fractions  # (N, 5)
        _, heading = self.position(lane[:, None], ahead)
        turn = np.abs(wrap_angle(np.diff(heading, axis=-1)))
        return turn.max(axis=-1) / np.maximum(distance * 0.25, 1e-6)


def pure_pursuit(
    state: np.ndarray, target: np.ndarray, config: DynamicsConfig | None = None
) -> np.ndarray:
    """Yaw rate that puts a unicycle on the circular arc through a target point.

    curvature = 2 * lateral / distance^2 (target in the vehicle frame), yaw rate =
    speed * curvature, clipped to ``[-yaw_rate_max, yaw_rate_max]``.

    Args:
        state: (N, 4) (x [m], y [m], v [m/s], psi [rad]).
        target: (N, 2) [m] lookahead points.
        config: dynamics bounds (``yaw_rate_max`` [rad/s]); defaults when None.

    Returns:
        (N,) [rad/s].
    """
    config = config or DynamicsConfig()
    curvature = arc_curvature(state, target)
    return np.clip(state[:, SPEED] * curvature, -config.yaw_rate_max, config.yaw_rate_max)


def arc_curvature(state: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N,) [1/m] curvature (positive left) of the arc from each vehicle through its target.

    Args:
        state: (N, 4) (x [m], y [m], v [m/s], psi [rad]); target: (N, 2) [m].
    """
    rel = target - state[:, :2]
    cos, sin = np.cos(state[:, YAW]), np.sin(state[:, YAW])
    lateral = -sin * rel[:, 0] + cos * rel[:, 1]
    return 2.0 * lateral / np.maximum(np.sum(rel * rel, axis=-1), 1e-6)


def arc_frame(
    dx: np.ndarray, dy: np.ndarray, curvature: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points in a vehicle's frame -> coordinates along the arc of ``curvature``.

    Args:
        dx, dy: (...) [m] points ahead (x) and to the left (y) of the vehicle.
        curvature: (...) [1/m] signed, positive turning left; |k| < 1e-4 is straight.

    Returns:
        along: (...) [m] arclength to the point's projection on the arc (in
        (-pi R, pi R]); lateral: (...) [m] offset from the arc, positive left;
        turned: (...) [rad] heading change of the arc up to that point.
    """
    straight = np.abs(curvature) < 1e-4
    k = np.where(straight, 1.0, curvature)
    radius = 1.0 / np.abs(k)
    sign = np.sign(k)
    angle = np.arctan2(dx, radius - sign * dy)
    along = np.where(straight, dx, radius * angle)
    lateral = np.where(straight, dy, sign * (radius - np.hypot(dx, dy - 1.0 / k)))
    turned = np.where(straight, 0.0, sign * angle)
    return along, lateral, turned


def speed_control(speed: np.ndarray, target: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """(N,) [m/s^2] proportional acceleration ``gain * (target - speed)``.

    Args:
        speed, target: (N,) [m/s]; gain: [1/s].
    """
    return gain * (np.asarray(target) - np.asarray(speed))


def idm_acceleration(
    speed: np.ndarray,
    desired_speed: np.ndarray,
    gap: np.ndarray,
    closing_speed: np.ndarray,
    *,
    accel_max: float,
    decel_comfort: float,
    time_headway: float,
    min_gap: float,
    delta: float = 4.0,
) -> np.ndarray:
    """Intelligent Driver Model acceleration (Treiber et al. 2000).

    ``a = a_max * (1 - (v / v0)^delta - (s* / s)^2)`` with the desired gap
    ``s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))``.

    Args:
        speed: (N,) v [m/s].
        desired_speed: (N,) v0 [m/s], > 0.
        gap: (N,) s [m] bumper-to-bumper gap to the leader, ``inf`` when there is none
            (floored at 1 cm).
        closing_speed: (N,) dv = v - v_leader [m/s] (positive when approaching).
        accel_max: a_max [m/s^2]; decel_comfort: b [m/s^2], > 0.
        time_headway: T [s]; min_gap: s0 [m]; delta: free-road exponent [-].

    Returns:
        (N,) [m/s^2], unbounded below (clip to the dynamics bounds).
    """
    speed = np.asarray(speed, dtype=np.float64)
    brake = speed * closing_speed / (2.0 * np.sqrt(accel_max * decel_comfort))
    desired_gap = min_gap + np.maximum(0.0, speed * time_headway + brake)
    interaction = (desired_gap / np.maximum(gap, 1e-2)) ** 2
    free_road = (speed / desired_speed) ** delta
    return accel_max * (1.0 - free_road - interaction)
