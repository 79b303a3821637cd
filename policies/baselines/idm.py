"""Reactive IDM traffic: car following (Treiber et al. 2000) plus lane keeping.

Every step, for all controlled vehicles at once:

1. Lane keeping: each vehicle is matched to a lane of the map (distance plus a
   heading penalty, :class:`~policies.controllers.LaneGraph`) and steers with pure
   pursuit toward a point ``lookahead`` metres ahead along that lane and its
   straight-on successors.
2. Leader: the nearest vehicle ahead inside the vehicle's corridor. Other vehicles
   are placed in the vehicle's frame bent along its current pure-pursuit arc (so
   leaders around a bend are found); a vehicle is in the corridor when its centre is
   within ``(lane width + its width) / 2`` of the arc. The end of a dead-end lane is
   a standing leader, so vehicles stop before running off the road.
3. Speed: IDM acceleration toward the desired speed, lowered on curves so that the
   lateral acceleration stays under ``lateral_accel_max`` and the yaw rate within
   the dynamics bound; the result is clipped to the dynamics bounds.

Desired speed (per vehicle, fixed at ``reset``): ``IDMParams.desired_speed`` when set,
else the speed limit of the vehicle's lane when the map has one, else the vehicle's
speed at reset. Vehicles slower than ``parked_speed`` at reset stay parked (they brake
to a stop and hold it), as parked cars in recorded scenes should. On maps without lane
centrelines vehicles keep their heading (zero yaw rate) and the corridor is straight
with width ``IDMParams.lane_width``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from policies.base import actions_dict, controlled_mask
from policies.controllers import LaneGraph, idm_acceleration, pure_pursuit
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW, X, Y
from riskflow_env.maps import DrivableMap
from riskflow_env.view import SceneView


@dataclass(frozen=True)
class IDMParams:
    """Parameters of :class:`IDMPolicy`.

    Attributes:
        accel_max: IDM maximum acceleration a [m/s^2].
        decel_comfort: IDM comfortable deceleration b [m/s^2].
        time_headway: IDM desired time gap T [s].
        min_gap: IDM jam distance s0 [m] (bumper to bumper).
        delta: IDM free-road exponent [-].
        desired_speed: v0 for every vehicle [m/s]; None: lane speed limit, else the
            vehicle's speed at reset.
        parked_speed: vehicles slower than this at reset stay stopped [m/s].
        lookahead_time: pure-pursuit lookahead distance per unit speed [s].
        min_lookahead: shortest lookahead distance [m].
        lateral_accel_max: curve speed limit, v^2 * curvature <= this [m/s^2].
        curve_preview_time: how far ahead curvature is checked, in time at the
            current speed [s] (at least 10 m).
        leader_range: vehicles farther ahead along the path are ignored [m].
        lane_width: corridor width on maps without lanes [m].
    """

    accel_max: float = 1.5
    decel_comfort: float = 2.0
    time_headway: float = 1.5
    min_gap: float = 2.0
    delta: float = 4.0
    desired_speed: float | None = None
    parked_speed: float = 0.5
    lookahead_time: float = 0.8
    min_lookahead: float = 5.0
    lateral_accel_max: float = 3.0
    curve_preview_time: float = 2.5
    leader_range: float = 80.0
    lane_width: float = 3.5

    def __post_init__(self) -> None:
        positive = (
            "accel_max",
            "decel_comfort",
            "time_headway",
            "delta",
            "lookahead_time",
            "min_lookahead",
            "lateral_accel_max",
            "curve_preview_time",
            "leader_range",
            "lane_width",
        )
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"IDMParams.{name} must be a finite number > 0, got {value!r}")
        for name in ("min_gap", "parked_speed"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"IDMParams.{name} must be a finite number >= 0, got {value!r}")
        if self.desired_speed is not None and not self.desired_speed > 0:
            raise ValueError(
                f"IDMParams.desired_speed must be > 0 m/s or None, got {self.desired_speed!r}"
            )


class IDMPolicy:
    """IDM car following with pure-pursuit lane keeping (see the module docstring).

    Args:
        controlled: ``"others"`` (every vehicle but the ego), ``"all"``, or agent names.
        params: IDM and lane-keeping parameters.
        dynamics: the env's dynamics bounds (accelerations and yaw rates are clipped
            to them).
    """

    def __init__(
        self,
        controlled: str | Sequence[str] = "others",
        params: IDMParams | None = None,
        dynamics: DynamicsConfig | None = None,
    ) -> None:
        self.controlled = controlled
        self.params = params or IDMParams()
        self.dynamics = dynamics or DynamicsConfig()
        self._map: DrivableMap | None = None
        self._graph: LaneGraph | None = None
        self._desired = np.zeros(0)

    def reset(self, view: SceneView) -> None:
        """Match the map's lanes and fix every vehicle's desired speed."""
        if view.map is not self._map:
            self._map = view.map
            self._graph = LaneGraph(view.map) if view.map.lanes else None
        speed = view.current[:, SPEED]
        desired = np.full(view.num_agents, np.nan)
        if self.params.desired_speed is not None:
            desired[:] = self.params.desired_speed
        elif self._graph is not None:
            lane, *_ = self._graph.match(view.current[:, :2], view.current[:, YAW])
            desired = self._graph.speed_limit[lane]
        desired = np.where(np.isfinite(desired), desired, speed)
        self._desired = np.where(speed < self.params.parked_speed, 0.0, desired)

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for the controlled live agents."""
        if view.map is not self._map or self._desired.shape != (view.num_agents,):
            self.reset(view)
        mask = controlled_mask(view, self.controlled)
        actions = np.zeros((view.num_agents, 2))
        if mask.any():
            actions[mask] = self._actions(view, np.flatnonzero(mask))
        return actions_dict(view, mask, actions)

    def _actions(self, view: SceneView, rows: np.ndarray) -> np.ndarray:
        """(n, 2) actions of slots ``rows``."""
        params, dyn = self.params, self.dynamics
        state = view.current[rows]
        speed = state[:, SPEED]
        desired = self._desired[rows]
        lookahead = np.maximum(params.min_lookahead, params.lookahead_time * speed)
        dead_end = np.full(len(rows), np.inf)
        if self._graph is None:
            yaw_rate = np.zeros(len(rows))
            curvature = np.zeros(len(rows))
            lane_width = np.full(len(rows), params.lane_width)
        else:
            graph = self._graph
            lane, s, _, _ = graph.match(state[:, :2], state[:, YAW])
            target, _ = graph.position(lane, s + lookahead)
            yaw_rate = pure_pursuit(state, target, dyn)
            curvature = _arc_curvature(state, target)
            lane_width = graph.width[lane]
            preview = np.maximum(10.0, params.curve_preview_time * speed)
            bend = graph.curvature_ahead(lane, s, preview)
            curve_speed = np.sqrt(params.lateral_accel_max / np.maximum(bend, 1e-6))
            curve_speed = np.minimum(curve_speed, 0.9 * dyn.yaw_rate_max / np.maximum(bend, 1e-6))
            desired = np.where(desired > 0, np.maximum(np.minimum(desired, curve_speed), 1.0), 0.0)
            dead_end = graph.distance_to_dead_end(lane, s) - 0.5 * view.length[rows]

        gap, closing = self._leader(view, rows, curvature, lane_width)
        closing = np.where(dead_end < gap, speed, closing)
        gap = np.minimum(gap, dead_end)
        accel = idm_acceleration(
            speed,
            np.maximum(desired, 1e-3),
            gap,
            closing,
            accel_max=params.accel_max,
            decel_comfort=params.decel_comfort,
            time_headway=params.time_headway,
            min_gap=params.min_gap,
            delta=params.delta,
        )
        accel = np.where(desired > 0, accel, -speed / dyn.dt)  # parked: stop and hold
        accel = np.clip(accel, dyn.accel_min, dyn.accel_max)
        return np.stack([accel, yaw_rate], axis=-1)

    def _leader(
        self, view: SceneView, rows: np.ndarray, curvature: np.ndarray, lane_width: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gap [m] to and closing speed [m/s] on the nearest vehicle in each corridor.

        Args:
            rows: (n,) slots of the following vehicles.
            curvature: (n,) [1/m] each follower's path curvature (positive left).
            lane_width: (n,) [m] each follower's corridor width.

        Returns:
            gap: (n,) bumper-to-bumper [m], inf without leader; closing: (n,) [m/s].
        """
        current, present = view.current, view.present
        me = current[rows]
        rel = current[None, :, :2] - me[:, None, :2]  # (n, A, 2)
        cos, sin = np.cos(me[:, YAW])[:, None], np.sin(me[:, YAW])[:, None]
        dx = cos * rel[..., X] + sin * rel[..., Y]
        dy = -sin * rel[..., X] + cos * rel[..., Y]
        along, lateral, turned = _arc_frame(dx, dy, curvature[:, None])
        half = 0.5 * (lane_width[:, None] + view.width[None, :])
        candidate = present[None, :] & (along > 0) & (np.abs(lateral) < half)
        candidate &= along < self.params.leader_range
        candidate[np.arange(len(rows)), rows] = False
        gap = along - 0.5 * (view.length[rows, None] + view.length[None, :])
        gap = np.where(candidate, gap, np.inf)
        leader = np.argmin(gap, axis=-1)
        index = np.arange(len(rows))
        heading = me[:, YAW] + turned[index, leader]  # path direction at the leader
        leader_speed = current[leader, SPEED] * np.cos(current[leader, YAW] - heading)
        return gap[index, leader], me[:, SPEED] - leader_speed


def _arc_curvature(state: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N,) [1/m] curvature of the arc from each vehicle through its target point."""
    rel = target - state[:, :2]
    cos, sin = np.cos(state[:, YAW]), np.sin(state[:, YAW])
    lateral = -sin * rel[:, 0] + cos * rel[:, 1]
    return 2.0 * lateral / np.maximum(np.sum(rel * rel, axis=-1), 1e-6)


def _arc_frame(
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
