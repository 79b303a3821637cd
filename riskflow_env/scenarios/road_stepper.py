"""highway-env road stepping, faster and with the same results.

:class:`RoadStepper` does what highway-env's ``Road.act()`` + ``RegulatedRoad.step(dt)``
do for a road of IDM/MOBIL vehicles, in less time: leader / follower queries
(``Road.neighbour_vehicles`` with connected lanes) share per-step lane tables computed
with vectorised lane coordinates, every vehicle's closest lane is found for all at once,
and vectorised broad phases leave out pairs too far apart to collide within the step or
to conflict within ``CONFLICT_HORIZON``. The
narrow phases are highway-env's own functions, so the traffic is highway-env's.

Differences, on purpose: right of way (``RegulatedRoad.enforce_road_rules``) is only
applied when ``regulated``, never between vehicles on the same road (car following and
lane changes are IDM / MOBIL's), and a vehicle that stops yielding wants its own desired
speed back (highway-env gives it the lane's speed limit).
"""

from __future__ import annotations

import functools

import numpy as np

DT = 0.1  # [s] simulation and recording step (highway-env simulation_frequency = 10 Hz)
REGULATION_PERIOD = 5  # [steps] right-of-way checks every 0.5 s (highway-env: 2 Hz)
CONFLICT_HORIZON = 3.0  # [s] highway-env's RegulatedRoad prediction horizon
MAX_YAW_RATE = 1.0  # [rad/s] steering is capped so the yaw rate stays within (env default)
CONFLICT_MARGIN = 20.0  # [m] added to the reach of the conflict broad phase (extents)
STOP_EASE_SPEED = 2.0  # [m/s] a halting vehicle below this brakes less, in proportion
STOP_MIN_SPEED = 0.1  # [m/s] floor of that speed, so a halting vehicle does come to rest


class RoadStepper:
    """Steps a highway-env road of :func:`traffic_vehicle_class` vehicles by ``DT``.

    Args:
        road: a highway-env ``Road``; its ``neighbour_vehicles`` is replaced by
            :meth:`neighbours` (same results, cached per step).
        regulated: apply right of way at crossings (intersections, roundabout entries).
    """

    def __init__(self, road, regulated: bool = False) -> None:
        self.road = road
        self.regulated = regulated
        self.steps = 0
        self.lane_tables: dict[tuple, tuple[list, list]] = {}
        road.neighbour_vehicles = self.neighbours
        self.lanes = [  # (index, lane) in RoadNetwork.get_closest_lane_index's order
            ((start, end, index), lane)
            for start, ends in road.network.graph.items()
            for end, lanes in ends.items()
            for index, lane in enumerate(lanes)
        ]

    def step(self) -> None:
        """One 0.1 s step: ``road.act()``, right of way (when regulated), vehicle
        dynamics, collisions."""
        road = self.road
        vehicles = list(road.vehicles)
        xy = np.array([v.position for v in vehicles]).reshape(-1, 2)
        distance = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        self.lane_tables = {}
        road.act()
        self.steps += 1
        if self.regulated and self.steps % REGULATION_PERIOD == 0:
            self.regulate(vehicles, distance)
        road.lane_updates_deferred = True
        try:
            move_unicycle(vehicles, DT)
        finally:
            road.lane_updates_deferred = False
        xy = np.array([v.position for v in vehicles]).reshape(-1, 2)
        self.update_lanes(vehicles, xy)
        diagonal = np.array([v.diagonal for v in vehicles])
        speed = np.array([abs(v.speed) for v in vehicles])
        reach = (diagonal[:, None] + diagonal[None]) / 2 + (speed[:, None] + speed[None]) * DT
        close = np.linalg.norm(xy[:, None] - xy[None], axis=-1) < reach
        for i, j in np.argwhere(np.triu(close, k=1)):
            vehicles[i].handle_collisions(vehicles[j], DT)
        for vehicle in vehicles:
            for other in road.objects:
                vehicle.handle_collisions(other, DT)

    def update_lanes(self, vehicles: list, xy: np.ndarray) -> None:
        """Each vehicle's closest lane (``Vehicle.on_state_update``), for all at once."""
        if not vehicles:
            return
        heading = np.array([v.heading for v in vehicles], dtype=float)
        distance = np.stack([_distance_with_heading(lane, xy, heading) for _, lane in self.lanes])
        for vehicle, best in zip(vehicles, np.argmin(distance, axis=0), strict=True):
            vehicle.lane_index, vehicle.lane = self.lanes[best]

    def neighbours(self, vehicle, lane_index=None):
        """``Road.neighbour_vehicles`` (connected lanes on), same result, cached per step.

        Positions do not move during ``road.act()``, so each lane's longitudinal
        coordinates of all vehicles are computed once per step, not once per query.
        """
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        if lane_index not in self.lane_tables:
            self.lane_tables[lane_index] = self.lane_table(lane_index)
        others, along = self.lane_tables[lane_index]
        s = self.road.network.get_lane(lane_index).local_coordinates(vehicle.position)[0]
        front = rear = None
        s_front = s_rear = None
        for other, s_other in zip(others, along, strict=True):  # highway-env's tie rules
            if other is vehicle or s_other is None:
                continue
            if s <= s_other and (s_front is None or s_other <= s_front):
                s_front, front = s_other, other
            if s_other < s and (s_rear is None or s_other > s_rear):
                s_rear, rear = s_other, other
        return front, rear

    def lane_table(self, lane_index: tuple) -> tuple[list, list]:
        """Every vehicle and object, with its coordinate along ``lane_index`` (connected
        lanes included, None when on none of them), as ``Road.neighbour_vehicles``."""
        from highway_env.vehicle.objects import Landmark

        graph = self.road.network.graph
        lane = self.road.network.get_lane(lane_index)
        start, end, index = lane_index
        searched = [(lane, 0.0)]
        for lanes in graph.get(end, {}).values():
            if lanes:
                searched.append((lanes[index] if index < len(lanes) else lanes[0], lane.length))
        for ends in graph.values():
            lanes = ends.get(start)
            if lanes:
                previous = lanes[index] if index < len(lanes) else lanes[0]
                searched.append((previous, -previous.length))
        others = [v for v in self.road.vehicles + self.road.objects if not isinstance(v, Landmark)]
        xy = np.array([v.position for v in others], dtype=float).reshape(-1, 2)
        along = np.full(len(others), np.nan)
        for search_lane, offset in searched:  # the first lane a vehicle is on counts
            todo = np.flatnonzero(np.isnan(along))
            s, on = _on_lane(search_lane, xy[todo])
            along[todo[on]] = s[on] + offset
        return others, [None if np.isnan(a) else float(a) for a in along]

    def regulate(self, vehicles: list, distance: np.ndarray) -> None:
        """highway-env's ``RegulatedRoad.enforce_road_rules``, every ``REGULATION_PERIOD``.

        Pairs that may overlap within ``CONFLICT_HORIZON`` at constant speed: the one on
        the lower-priority lane (else the one behind) stops (target speed 0) until the
        next regulation finds no conflict; then it wants its own desired speed again
        (highway-env would give it the lane speed limit).
        """
        from highway_env.road.regulation import RegulatedRoad

        for vehicle in vehicles:
            if vehicle.is_yielding:
                vehicle.is_yielding = False
                vehicle.target_speed = vehicle.desired_speed
        speed = np.array([abs(v.speed) for v in vehicles])
        reach = CONFLICT_HORIZON * (speed[:, None] + speed[None]) + CONFLICT_MARGIN
        for i, j in np.argwhere(np.triu(distance < reach, k=1)):
            if vehicles[i].lane_index[:2] == vehicles[j].lane_index[:2]:
                continue  # same road: car following and lane changes are IDM / MOBIL's
            if RegulatedRoad.is_conflict_possible(vehicles[i], vehicles[j]):
                yielding = RegulatedRoad.respect_priorities(vehicles[i], vehicles[j])
                yielding.target_speed = 0.0
                yielding.is_yielding = True


def _lane_frame(lane, xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """highway-env's ``lane.local_coordinates``, ``width_at`` and ``heading_at`` for many
    points (N, 2) [m]: arclength s, lateral offset [m], half width [m] and lane heading at
    s [rad], each (N,); vectorised for straight and circular lanes, a loop otherwise."""
    from highway_env.road.lane import CircularLane, StraightLane

    count = len(xy)
    if type(lane) is StraightLane:
        delta = xy - lane.start
        s, lateral = delta @ lane.direction, delta @ lane.direction_lateral
        return s, lateral, np.full(count, lane.width / 2), np.full(count, lane.heading)
    if type(lane) is CircularLane:
        delta = xy - lane.center
        phi = _wrap(np.arctan2(delta[:, 1], delta[:, 0]) - lane.start_phase)
        s = lane.direction * phi * lane.radius
        lateral = lane.direction * (lane.radius - np.linalg.norm(delta, axis=-1))
        heading = lane.direction * s / lane.radius + lane.start_phase
        return s, lateral, np.full(count, lane.width / 2), heading + np.pi / 2 * lane.direction
    coordinates = np.array([lane.local_coordinates(p) for p in xy], dtype=float).reshape(-1, 2)
    s, lateral = coordinates[:, 0], coordinates[:, 1]
    half_width = np.array([lane.width_at(v) / 2 for v in s], dtype=float).reshape(count)
    heading = np.array([lane.heading_at(v) for v in s], dtype=float).reshape(count)
    return s, lateral, half_width, heading


def _on_lane(lane, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arclength (N,) [m] and ``lane.on_lane(margin=1)`` flags (N,) of points (N, 2)."""
    s, lateral, half_width, _ = _lane_frame(lane, xy)
    length = lane.VEHICLE_LENGTH
    on = (np.abs(lateral) <= half_width + 1.0) & (-length <= s) & (s < lane.length + length)
    return s, on


def _distance_with_heading(lane, xy: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``lane.distance_with_heading`` (N,) for points (N, 2) [m] and headings (N,) [rad]."""
    s, lateral, _, lane_heading = _lane_frame(lane, xy)
    outside = np.maximum(s - lane.length, 0.0) + np.maximum(-s, 0.0)
    return np.abs(lateral) + outside + np.abs(_wrap(heading - lane_heading))


def _wrap(angle: np.ndarray) -> np.ndarray:
    """highway_env.utils.wrap_to_pi: angle [rad] in [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def move_unicycle(vehicles: list, dt: float) -> None:
    """One step of highway-env vehicles through the simulator's unicycle, all at once.

    highway-env's ``Vehicle.step`` integrates a kinematic bicycle that moves along
    ``heading + beta`` (slip angle ``tan(beta) = tan(steering) / 2``): its heading is
    not the direction of travel, and a generator trained on such tracks learns the
    mismatch (it over-steers on curves). Here the same commands drive
    :func:`riskflow_env.dynamics.step` instead: acceleration as commanded, yaw rate the
    bicycle's ``speed * sin(beta) / (length / 2)`` (already capped at ``MAX_YAW_RATE`` by
    the steering), motion along the heading. Bounds are the simulator's
    (``DynamicsConfig``: speed in [0, 40] m/s, acceleration in [-8, 5] m/s^2). Crashed
    vehicles brake as in highway-env (``clip_actions``) and collision impacts are applied
    as there; lanes are updated by :meth:`RoadStepper.update_lanes` (or, for a vehicle
    stepped on its own, ``on_state_update``).
    """
    from riskflow_env.dynamics import step as unicycle_step

    if not vehicles:
        return
    for vehicle in vehicles:
        vehicle.timer += dt  # IDMVehicle's lane-change timer
        vehicle.clip_actions()
    steering = np.array([v.action["steering"] for v in vehicles], dtype=float)
    half_length = np.array([v.LENGTH / 2 for v in vehicles], dtype=float)
    state = np.array([[*v.position, v.speed, v.heading] for v in vehicles], dtype=float)
    beta = np.arctan(0.5 * np.tan(steering))
    yaw_rate = state[:, 2] * np.sin(beta) / half_length
    accel = np.array([v.action["acceleration"] for v in vehicles], dtype=float)
    config = _dynamics_config(dt)
    new = unicycle_step(state, np.stack([accel, yaw_rate], axis=-1), config)
    for vehicle, (x, y, speed, heading) in zip(vehicles, new, strict=True):
        vehicle.position = np.array([x, y])
        if vehicle.impact is not None:
            vehicle.position += vehicle.impact
            vehicle.crashed = True
            vehicle.impact = None
        vehicle.speed, vehicle.heading = float(speed), float(heading)
        if not getattr(vehicle.road, "lane_updates_deferred", False):
            vehicle.on_state_update()


@functools.lru_cache(maxsize=4)
def _dynamics_config(dt: float):
    """The recorder's unicycle: the simulator's bounds without the turning radius, with
    which the shipped banks were recorded (``riskflow-data generate`` makes them again).
    Recorded highway-env traffic turns only while it drives, so the radius rarely binds."""
    from riskflow_env.config import DynamicsConfig

    return DynamicsConfig(dt=dt, turn_radius_min=0.0)


@functools.cache
def traffic_vehicle_class() -> type:
    """highway-env's IDMVehicle, subclassed so that

    * it moves as the simulator's unicycle (:func:`move_unicycle`), so recorded tracks
      reproduce themselves through :mod:`riskflow_env.dynamics`; speeds stop at 0;
    * the yaw rate stays within ``MAX_YAW_RATE`` (highway-env's heading controller asks
      for 5 rad/s per rad of heading error, e.g. spikes at lane-segment joints);
    * a stopped vehicle may still change lanes (highway-env's MOBIL skips vehicles below
      1 m/s, so a queue at a lane end, e.g. the merge lane's, would wait forever); MOBIL
      then evaluates it as if moving at 1 m/s;
    * its lane can be updated by :class:`RoadStepper` for all vehicles at once;
    * while its ``halting`` flag is set (a stop drawn by the recorder), it brakes to a
      standstill at its comfortable deceleration, in proportion to its speed below
      ``STOP_EASE_SPEED`` (no jerk spike at rest), and stays there; IDM's own braking
      applies when it asks for more.

    Built on first use: importing highway-env (and pygame) takes most of a second.
    """
    from highway_env.vehicle.behavior import IDMVehicle

    class TrafficVehicle(IDMVehicle):
        def step(self, dt: float) -> None:
            move_unicycle([self], dt)

        def change_lane_policy(self) -> None:
            if self.speed >= 1.0 or self.lane_index != self.target_lane_index:
                return super().change_lane_policy()
            speed, self.speed = self.speed, 1.0  # MOBIL only considers moving vehicles
            try:
                return super().change_lane_policy()
            finally:
                self.speed = speed

        def steering_control(self, target_lane_index) -> float:
            steering = super().steering_control(target_lane_index)
            # bicycle model: yaw rate = v sin(beta) / (L / 2), tan(beta) = tan(steering) / 2
            sin_beta = min(1.0, MAX_YAW_RATE * self.LENGTH / 2 / max(self.speed, 1e-3))
            limit = float(np.arctan(2 * np.tan(np.arcsin(sin_beta))))
            return float(np.clip(steering, -limit, limit))

        def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
            acceleration = super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)
            if not getattr(ego_vehicle, "halting", False):
                return acceleration
            speed = max(float(ego_vehicle.speed), 0.0)
            comfort = -float(ego_vehicle.COMFORT_ACC_MIN)
            braking = comfort * min(1.0, max(speed, STOP_MIN_SPEED) / STOP_EASE_SPEED)
            return min(acceleration, -braking)

        def on_state_update(self) -> None:
            if not getattr(self.road, "lane_updates_deferred", False):
                super().on_state_update()

    return TrafficVehicle
