"""Reactive IDM traffic: car following (Treiber et al. 2000), yielding and lane keeping.

Every step, for all controlled vehicles at once (no loop over agents):

1. Lane keeping: each vehicle is matched to a lane (distance plus heading penalty,
   :class:`~riskflow_env.agents.lane_graph.LaneGraph`) and steers with pure pursuit toward a
   point ``lookahead`` metres ahead along that lane and its successors. At forks it
   takes the lanes its reference future (the log) visits, if ``follow_log_route``
   and the scenario has one; else the straightest successor that does not run into
   a dead end.
2. Leader: the nearest vehicle ahead inside the vehicle's corridor. Other vehicles
   are placed in the vehicle's frame bent along its current pure-pursuit arc (so
   leaders around a bend are found); a vehicle is in the corridor when its centre is
   within ``(lane width + its width) / 2`` of the arc. The end of a dead-end lane is
   a standing leader, so vehicles stop before running off the road.
3. Yielding: every vehicle's path over the next ``yield_horizon`` seconds is predicted
   at constant speed (along its lane, or straight when it is off the lanes); where
   two boxes would overlap, the vehicle that is not ahead yields, i.e. treats the
   point before the conflict as a standing leader (between two IDM vehicles that
   would both yield, the one farther from the conflict point does). Vehicles driven
   by another policy (the ego) are always yielded to.
4. Speed: IDM acceleration toward the desired speed, lowered on curves so that the
   lateral acceleration stays under ``lateral_accel_max`` and the yaw rate within the
   dynamics bound; the result is clipped to the dynamics bounds.

Desired speed (per vehicle, fixed at ``reset``): ``IDMParams.desired_speed`` when set;
else the highest speed of the vehicle's logged track when the scenario has at least
1 s of reference future for it; else its lane's speed limit; else its current speed
(never below the current speed). Vehicles whose logged and current speeds stay below
``parked_speed`` are parked: they brake to a stop and hold it. On maps without lane
centrelines vehicles keep their heading (zero yaw rate) and the corridor is straight
with width ``IDMParams.lane_width``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env.agents.base import actions_dict, controlled_mask
from riskflow_env.agents.conflicts import box_extents, in_frame, yield_gaps
from riskflow_env.agents.controllers import (
    arc_curvature,
    arc_frame,
    idm_acceleration,
    pure_pursuit,
)
from riskflow_env.agents.lane_graph import LaneGraph
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.maps import DrivableMap
from riskflow_env.view import SceneView

ROUTE_STRIDE = 5  # [steps] logged future positions sampled to find a vehicle's route
PREDICTION_STEP = 0.25  # [s] time between conflict-prediction samples
PREDICTION_TIMES = np.arange(0.0, 30.0, PREDICTION_STEP)  # [s]


@dataclass(frozen=True)
class IDMParams:
    """Parameters of :class:`IDMPolicy`.

    Attributes:
        accel_max: IDM maximum acceleration a [m/s^2].
        decel_comfort: IDM comfortable deceleration b [m/s^2].
        time_headway: IDM desired time gap T [s].
        min_gap: IDM jam distance s0 [m] (bumper to bumper).
        delta: IDM free-road exponent [-].
        desired_speed: v0 for every vehicle [m/s]; None: from the log, the lane or the
            current speed (module docstring).
        parked_speed: vehicles whose logged and current speeds stay below this are
            parked [m/s].
        lookahead_time: pure-pursuit lookahead distance per unit speed [s].
        min_lookahead: shortest lookahead distance [m].
        lateral_accel_max: curve speed limit, v^2 * curvature <= this [m/s^2].
        curve_preview_time: how far ahead curvature is checked, in time at the
            current speed [s] (at least 10 m).
        leader_range: vehicles farther ahead along the path are ignored [m].
        lane_width: corridor width on maps without lanes [m].
        yield_horizon: how far ahead conflicts are predicted [s].
        min_predicted_speed: moving vehicles are predicted at least this fast, so
            that a vehicle waiting to go still claims its path [m/s].
        conflict_margin: boxes closer than this along (30% of it across) a vehicle
            are in conflict [m].
        follow_log_route: at junctions, take the lanes the vehicle's reference future
            (the log) visits, where it has one.
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
    yield_horizon: float = 4.0
    min_predicted_speed: float = 3.0
    conflict_margin: float = 1.0
    follow_log_route: bool = True

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
            "yield_horizon",
        )
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"IDMParams.{name} must be a finite number > 0, got {value!r}")
        for name in ("min_gap", "parked_speed", "min_predicted_speed", "conflict_margin"):
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
        self._route: np.ndarray | None = None

    def reset(self, view: SceneView) -> None:
        """Build the lane graph, each vehicle's route and desired speed (see the module
        docstring)."""
        if view.map is not self._map:
            self._map = view.map
            self._graph = LaneGraph(view.map) if view.map.lanes else None
        scenario, rows = view.scenario, np.asarray(view.scenario_rows)
        track = np.zeros((view.num_agents,) + scenario.states.shape[1:])
        track_valid = np.zeros((view.num_agents, scenario.states.shape[1]), dtype=bool)
        track[rows >= 0], track_valid[rows >= 0] = (
            scenario.states[rows[rows >= 0]],
            scenario.valid[rows[rows >= 0]],
        )
        future = track_valid.copy()
        future[:, : scenario.current_index] = False
        logged = np.where(track_valid, track[..., SPEED], 0.0).max(axis=1)
        speed = view.current[:, SPEED]
        desired = np.where(future.sum(axis=1) >= 10, logged, np.nan)  # >= 1 s of future log
        self._route = None
        if self._graph is not None:
            lane, *_ = self._graph.match(view.current[:, :2], view.current[:, YAW])
            desired = np.where(np.isfinite(desired), desired, self._graph.speed_limit[lane])
            if self.params.follow_log_route:
                sampled = future & (np.arange(future.shape[1]) % ROUTE_STRIDE == 0)
                self._route = self._graph.route_of(track[..., :2], track[..., YAW], sampled)
        desired = np.where(np.isfinite(desired), desired, speed)
        if self.params.desired_speed is not None:
            desired = np.full(view.num_agents, self.params.desired_speed)
        parked = np.maximum(speed, logged) < self.params.parked_speed
        self._desired = np.where(parked, 0.0, np.maximum(desired, speed))

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for the controlled live agents."""
        mask = self._prepare(view)
        actions = np.zeros((view.num_agents, 2))
        if mask.any():
            actions[mask] = self._actions(view, np.flatnonzero(mask))
        return actions_dict(view, mask, actions)

    def steer(self, view: SceneView) -> dict[str, float]:
        """``{agent: yaw_rate [rad/s]}`` for the controlled live agents: the lane keeping
        of :meth:`act` alone (step 1 of the module docstring), the same yaw rates as
        ``act(view)[agent][1]`` without the leaders, yielding and speed, so several times
        cheaper. What :class:`~policies.planners.LaneKeepingPlanner` drives with."""
        mask = self._prepare(view)
        rows, yaw_rate = np.flatnonzero(mask), np.zeros(view.num_agents)
        if rows.size and self._graph is not None:
            current, route = view.current, _rows(self._route, rows)
            lane, s, *_ = self._graph.match(current[rows, :2], current[rows, YAW], route=route)
            yaw_rate[rows] = self._pursuit(view, rows, lane, s)[0]
        return {view.agent_names[i]: float(yaw_rate[i]) for i in rows}

    def _prepare(self, view: SceneView) -> np.ndarray:
        """The controlled live slots (A,) bool, after a reset if ``view`` is a new scene."""
        if view.map is not self._map or self._desired.shape != (view.num_agents,):
            self.reset(view)
        return controlled_mask(view, self.controlled)

    def _pursuit(
        self, view: SceneView, rows: np.ndarray, lane: np.ndarray, s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pure-pursuit yaw rates [rad/s] and arc curvatures [1/m] (n,) of the slots
        ``rows`` matched to ``lane`` at arclength ``s`` (n,)."""
        speed = view.current[rows, SPEED]
        lookahead = np.maximum(self.params.min_lookahead, self.params.lookahead_time * speed)
        target, _ = self._graph.position(lane, s + lookahead, _rows(self._route, rows))
        current = view.current[rows]
        return pure_pursuit(current, target, self.dynamics), arc_curvature(current, target)

    def _actions(self, view: SceneView, rows: np.ndarray) -> np.ndarray:
        """(n, 2) actions of the controlled slots ``rows``."""
        params, dyn = self.params, self.dynamics
        current, graph = view.current, self._graph
        speed = current[:, SPEED]
        desired = self._desired.copy()
        count = view.num_agents
        lane, s = np.zeros(count, dtype=int), np.zeros(count)
        on_lane = np.zeros(count, dtype=bool)
        yaw_rate, curvature = np.zeros(count), np.zeros(count)
        lane_width = np.full(count, params.lane_width)
        dead_end = np.full(count, np.inf)
        present = np.flatnonzero(view.present)
        route = self._route
        if graph is not None:
            lane[present], s[present], lateral, error = graph.match(
                current[present, :2], current[present, YAW], route=_rows(route, present)
            )
            on_lane[present] = (np.abs(lateral) < graph.width[lane[present]]) & (
                np.abs(error) < 0.6
            )
            yaw_rate[rows], curvature[rows] = self._pursuit(view, rows, lane[rows], s[rows])
            lane_width[rows] = graph.width[lane[rows]]
            preview = np.maximum(10.0, params.curve_preview_time * speed[rows])
            bend = graph.curvature_ahead(lane[rows], s[rows], preview, _rows(route, rows))
            bend = np.maximum(bend, 1e-6)
            curve_speed = np.minimum(
                np.sqrt(params.lateral_accel_max / bend), 0.9 * dyn.yaw_rate_max / bend
            )
            moving = desired[rows] > 0
            desired[rows] = np.where(moving, np.clip(curve_speed, 1.0, desired[rows]), 0.0)
            dead_end[rows] = (
                graph.distance_to_dead_end(lane[rows], s[rows], _rows(route, rows))
                - 0.5 * view.length[rows]
            )

        gap, closing = self._leader(view, rows, curvature[rows], lane_width[rows])
        predicted = np.where(
            self._desired > 0, np.maximum(speed, params.min_predicted_speed), speed
        )
        path, heading = self._predict(view, lane, s, on_lane, predicted)
        conflict_gap = yield_gaps(
            view, rows, path, heading, predicted, params.conflict_margin, PREDICTION_STEP
        )
        for other_gap, other_closing in (
            (dead_end[rows], speed[rows]),
            (conflict_gap, speed[rows]),
        ):
            closing = np.where(other_gap < gap, other_closing, closing)
            gap = np.minimum(gap, other_gap)
        accel = idm_acceleration(
            speed[rows],
            np.maximum(desired[rows], 1e-3),
            gap,
            closing,
            accel_max=params.accel_max,
            decel_comfort=params.decel_comfort,
            time_headway=params.time_headway,
            min_gap=params.min_gap,
            delta=params.delta,
        )
        accel = np.where(desired[rows] > 0, accel, -speed[rows] / dyn.dt)  # parked: stop, hold
        accel = np.clip(accel, dyn.accel_min, dyn.accel_max)
        return np.stack([accel, yaw_rate[rows]], axis=-1)

    def _predict(
        self,
        view: SceneView,
        lane: np.ndarray,
        s: np.ndarray,
        on_lane: np.ndarray,
        speed: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Constant-speed paths (A, K, 2) [m] and headings (A, K) [rad] at ``PREDICTION_TIMES``:
        along the lanes for vehicles on a lane, straight ahead for the others."""
        current = view.current
        times = PREDICTION_TIMES[: int(round(self.params.yield_horizon / PREDICTION_STEP)) + 1]
        ahead = speed[:, None] * times  # (A, K)
        direction = np.stack([np.cos(current[:, YAW]), np.sin(current[:, YAW])], axis=-1)
        path = current[:, None, :2] + ahead[..., None] * direction[:, None]
        heading = np.broadcast_to(current[:, YAW, None], ahead.shape).copy()
        if self._graph is not None and on_lane.any():
            path[on_lane], heading[on_lane] = self._graph.position(
                lane[on_lane, None], s[on_lane, None] + ahead[on_lane], _rows(self._route, on_lane)
            )
        return path, heading

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
        current = view.current
        me = current[rows]
        dx, dy = in_frame(current[None, :, :2] - me[:, None, :2], me[:, YAW, None])
        along, lateral, turned = arc_frame(dx, dy, curvature[:, None])
        relative = current[None, :, YAW] - (me[:, YAW, None] + turned)  # (n, A) [rad]
        extent_along, extent_across = box_extents(relative, view.length, view.width)
        candidate = view.present[None, :] & (along > 0)
        candidate &= np.abs(lateral) < 0.5 * lane_width[:, None] + extent_across
        candidate &= along < self.params.leader_range
        candidate[np.arange(len(rows)), rows] = False
        gap = along - 0.5 * view.length[rows, None] - extent_along
        gap = np.where(candidate, gap, np.inf)
        leader = np.argmin(gap, axis=-1)
        index = np.arange(len(rows))
        heading = me[:, YAW] + turned[index, leader]  # path direction at the leader
        leader_speed = current[leader, SPEED] * np.cos(current[leader, YAW] - heading)
        return gap[index, leader], me[:, SPEED] - leader_speed


def _rows(route: np.ndarray | None, rows: np.ndarray) -> np.ndarray | None:
    """``route[rows]``, or None without route."""
    return None if route is None else route[rows]
