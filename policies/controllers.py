"""Shared driving primitives for scene policies, vectorised over agents.

* :class:`LaneGraph` — a map's lane centrelines flattened into one segment table, so
  that matching every agent to a lane (distance plus a heading penalty) and looking
  up points ahead along lanes and their successors are a few array ops, with no
  Python loop over agents (nor over lanes).
* :func:`pure_pursuit` — yaw rate that steers a unicycle toward a lookahead point.
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


class LaneGraph:
    """Lane centrelines of one map as a flat segment table.

    Lanes are laid end to end on one global arclength axis (``offset[lane] + s``), so
    ``np.searchsorted`` finds the segment of any (lane, s) pair at once. Each lane
    keeps one successor: the one whose start heading is closest to its end heading
    ("straight on"), or -1 for a dead end.

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

        index = {lane.lane_id: i for i, lane in enumerate(lanes)}
        end_heading = self.segment_heading[self.last_segment]
        self.successor = np.full(self.num_lanes, -1)  # (L,) straightest successor, -1 if none
        for i, lane in enumerate(lanes):  # once per map
            known = [index[s] for s in lane.successors if s in index]
            if known:
                turn = np.abs(
                    wrap_angle(self.segment_heading[self.first_segment[known]] - end_heading[i])
                )
                self.successor[i] = known[int(np.argmin(turn))]

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
        rel = xy[:, None, :] - self.start  # (N, S, 2)
        t = np.clip(np.einsum("nsk,sk->ns", rel, self.delta) / self.segment_length**2, 0.0, 1.0)
        offset = rel - t[..., None] * self.delta
        distance = np.linalg.norm(offset, axis=-1)  # (N, S)
        error = wrap_angle(yaw[:, None] - self.segment_heading)
        best = np.argmin(distance + heading_weight * (1.0 - np.cos(error)), axis=-1)  # (N,)
        rows = np.arange(len(best))
        delta, off = self.delta[best], offset[rows, best]
        cross = delta[:, 0] * off[:, 1] - delta[:, 1] * off[:, 0]
        lateral = np.where(cross >= 0.0, 1.0, -1.0) * distance[rows, best]
        s = self.segment_s[best] + t[rows, best] * self.segment_length[best]
        return self.segment_lane[best], s, lateral, error[rows, best]

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
            s = np.where(move, s - self.length[lane], s)
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
        key = self.offset[lane] + np.clip(s, 0.0, self.length[lane])
        segment = np.searchsorted(self.segment_key, key, side="right") - 1
        segment = np.clip(segment, self.first_segment[lane], self.last_segment[lane])
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
            remaining = np.where(ended, remaining, remaining + self.length[np.maximum(nxt, 0)])
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
    rel = target - state[:, :2]
    cos, sin = np.cos(state[:, YAW]), np.sin(state[:, YAW])
    lateral = -sin * rel[:, 0] + cos * rel[:, 1]
    curvature = 2.0 * lateral / np.maximum(np.sum(rel * rel, axis=-1), 1e-6)
    return np.clip(state[:, SPEED] * curvature, -config.yaw_rate_max, config.yaw_rate_max)


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
