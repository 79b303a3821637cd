"""Naturalistic traffic: highway-env IDM/MOBIL simulations recorded at 10 Hz.

:func:`record_traffic` builds the road of a family with highway-env (the same env ids as
:func:`riskflow_env.maps.from_highway_env`), fills it with IDM/MOBIL vehicles — every
vehicle is a traffic vehicle, there is no controlled one — and steps it by 0.1 s
(``simulation_frequency=10``) with :class:`~riskflow_env.scenarios.road_stepper.RoadStepper`
(highway-env's ``road.act()`` / ``road.step()``, faster; right of way at the intersection
and the roundabout entries), recording every vehicle's (x, y, speed, heading) at each
step. The IDM/MOBIL commands move the vehicles through the simulator's own unicycle
(:func:`~riskflow_env.scenarios.road_stepper.move_unicycle`), not highway-env's
bicycle, so the heading is the direction of travel and every recorded track, rolled out
from its logged actions, reproduces itself: the generator's training targets are
reachable by the dynamics it plans with. The recorder's unicycle has no turning radius
(``DynamicsConfig.turn_radius_min = 0``), as when the shipped banks were recorded, so
that ``riskflow-data generate`` makes them again; about 2% of their logged steps turn
tighter than the simulator's 5 m radius allows (slow vehicles in curves).

Per recording it draws a traffic density; per vehicle a kind (car, or truck in
``TRUCK_FAMILIES``) and size, a desired speed and its IDM/MOBIL parameters (ranges in
:class:`DriverConfig`), set as instance attributes (highway-env's intersection env
overwrites some class defaults, so nothing relies on them).

Vehicles enter at the network's entry roads (start nodes without incoming road; for the
intersection the outer nodes ``o0``-``o3``), Poisson arrivals when the lane start is
clear, and leave when their front reaches the end of an exit road (end nodes without
outgoing road, the intersection's outer nodes) or of a lane cut by the map (highway).
Vehicles that crash or whose centre leaves the drivable area are removed and flagged.
Validity masks carry all of this: a vehicle's row is valid from its first to its last
recorded step. Speeds stay >= 0 and yaw rates within 1 rad/s
(:func:`~riskflow_env.scenarios.road_stepper.traffic_vehicle_class`).

:mod:`riskflow_env.scenarios.naturalistic` cuts recordings into :class:`Scenario` windows.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from riskflow_env.config import _finite, _require
from riskflow_env.geometry import pairwise_overlap
from riskflow_env.maps import DrivableMap, RoadFamily, from_highway_env, road_family
from riskflow_env.maps.highway import ENV_IDS
from riskflow_env.scenarios.road_stepper import DT, RoadStepper, traffic_vehicle_class

MAP_LENGTH = {"highway": 1000.0}  # [m] lane cut of the family's map; others 600 m
DEFAULT_MAP_LENGTH = 600.0  # [m]
BOUNDARY_NODES = {"intersection": ("o0", "o1", "o2", "o3")}  # besides the network's dead ends
CLEARANCE_WIDTH = 0.4  # [m] extra width of the boxes that must not overlap at placement
TRUCK_FAMILIES = ("highway", "merge", "exit")  # trucks do not fit the tight curves of others
REGULATED_FAMILIES = ("intersection", "roundabout")  # right of way at crossings / entries
STANDING_SPEED = 0.05  # [m/s] a stopping vehicle at or below this counts as standing
# DriverConfig's (min, max) ranges whose min must be > 0 (the others' >= 0)
POSITIVE_RANGES = ("speed_fraction", "comfort_accel", "comfort_decel", "delta")
POSITIVE_RANGES += ("car_length", "car_width", "truck_length", "truck_width")


@dataclass(frozen=True)
class DriverConfig:
    """Ranges, each (min, max) drawn uniformly, of the recorded traffic.

    Attributes:
        extra_headway: per recording, mean headway beyond each driver's time gap [s];
            lower is denser traffic (initial spacing and entry flow).
        speed_fraction: desired speed as a share of the lane speed limit.
        time_gap: IDM desired time gap [s].
        min_gap: IDM jam distance, bumper to bumper [m].
        comfort_accel: IDM comfortable acceleration [m/s^2].
        comfort_decel: IDM comfortable deceleration (positive) [m/s^2].
        delta: IDM acceleration exponent.
        politeness: MOBIL politeness factor.
        lane_change_gain: MOBIL acceleration gain threshold [m/s^2].
        lane_change_max_braking: MOBIL largest braking imposed on the new follower [m/s^2].
        car_length, car_width: car sizes [m].
        truck_fraction: share of trucks (probability per vehicle) in ``TRUCK_FAMILIES``.
        truck_length, truck_width: truck sizes [m].
        truck_speed_factor: trucks' desired speed is scaled by this.
        default_speed_limit: speed limit of lanes that carry none [m/s].
        stop_share: probability per vehicle that it makes one stop in its lane (a
            breakdown, a drop-off, the head of a queue): it brakes to a standstill and
            waits, so the vehicles behind queue up or change lanes around it. 0 (the
            default) draws nothing, so banks made without stops keep their exact bits.
        stop_start: when the stop begins, after the vehicle appears [s].
        stop_duration: how long it stands, braking time not included [s].
    """

    extra_headway: tuple[float, float] = (0.2, 2.0)
    speed_fraction: tuple[float, float] = (0.75, 1.0)
    time_gap: tuple[float, float] = (1.0, 2.0)
    min_gap: tuple[float, float] = (2.0, 4.0)
    comfort_accel: tuple[float, float] = (1.2, 3.0)
    comfort_decel: tuple[float, float] = (2.5, 5.0)
    delta: tuple[float, float] = (3.5, 4.5)
    politeness: tuple[float, float] = (0.0, 0.5)
    lane_change_gain: tuple[float, float] = (0.1, 0.4)
    lane_change_max_braking: tuple[float, float] = (1.5, 3.0)
    car_length: tuple[float, float] = (3.8, 5.2)
    car_width: tuple[float, float] = (1.7, 2.0)
    truck_fraction: float = 0.06
    truck_length: tuple[float, float] = (7.5, 12.0)
    truck_width: tuple[float, float] = (2.3, 2.6)
    truck_speed_factor: float = 0.85
    default_speed_limit: float = 20.0
    stop_share: float = 0.0
    stop_start: tuple[float, float] = (0.0, 25.0)
    stop_duration: tuple[float, float] = (3.0, 20.0)

    def __post_init__(self) -> None:
        for field in fields(self):
            name, value = field.name, getattr(self, field.name)
            if not isinstance(field.default, tuple):  # a number
                object.__setattr__(self, name, _finite(f"DriverConfig.{name}", value))
                continue
            if isinstance(value, list):  # e.g. read from JSON
                object.__setattr__(self, name, value := tuple(value))
            pair = isinstance(value, tuple) and len(value) == 2
            _require(pair, f"DriverConfig.{name} must be a (min, max) pair, got {value!r}")
            low, high = (_finite(f"DriverConfig.{name}", bound) for bound in value)
            object.__setattr__(self, name, value := (low, high))
            positive = name in POSITIVE_RANGES
            _require(
                (low > 0 if positive else low >= 0) and low <= high,
                f"DriverConfig.{name}: need 0 {'<' if positive else '<='} min <= max, got {value}",
            )
        for name in ("truck_fraction", "stop_share"):
            share = getattr(self, name)
            _require(0 <= share <= 1, f"DriverConfig.{name} must be in [0, 1], got {share}")
        for name in ("truck_speed_factor", "default_speed_limit"):
            value = getattr(self, name)
            _require(value > 0, f"DriverConfig.{name} must be > 0, got {value}")


@dataclass(frozen=True)
class Recording:
    """Every vehicle of one simulation, at 10 Hz.

    Attributes:
        family: the highway-env road family.
        map: its drivable map (lanes cut at ``MAP_LENGTH``).
        states: (V, T, 4) float64 (x [m], y [m], v [m/s], psi [rad]); psi unwrapped
            over each vehicle's valid steps; 0 where invalid.
        valid: (V, T) bool, one contiguous run of True per vehicle.
        crashed: (V,) bool, the vehicle was removed because it crashed (its last valid
            step is the one before the crash).
        length: (V,) [m]. width: (V,) [m].
        kinds: (V,) ``"car"`` or ``"truck"``.
        dt: step [s].
    """

    family: str
    map: DrivableMap
    states: np.ndarray
    valid: np.ndarray
    crashed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    kinds: tuple[str, ...]
    dt: float = DT


def family_map(family: str | RoadFamily, resolution: float = 0.5) -> DrivableMap:
    """The map recordings of ``family`` use (cached by :func:`from_highway_env`)."""
    family = road_family(family)
    return from_highway_env(
        family, resolution=resolution, max_length=MAP_LENGTH.get(family, DEFAULT_MAP_LENGTH)
    )


def record_traffic(
    family: str | RoadFamily,
    rng: np.random.Generator,
    steps: int,
    warmup_steps: int = 50,
    config: DriverConfig | None = None,
    resolution: float = 0.5,
) -> Recording:
    """Simulate ``warmup_steps`` unrecorded, then record ``steps`` states of every vehicle.

    Deterministic given ``rng``'s state (highway-env's own generator is seeded from it).

    Args:
        family: a :class:`riskflow_env.maps.RoadFamily` or its name.
        rng: source of every random draw.
        steps: recorded steps T (>= 1), 0.1 s apart.
        warmup_steps: simulated steps before the first recorded one (initial placement
            transients settle).
        config: driver and traffic ranges.
        resolution: map raster resolution [m/px].
    """
    import gymnasium
    import highway_env  # noqa: F401  (registers the envs)

    if steps < 1 or warmup_steps < 0:
        raise ValueError(f"steps must be >= 1 and warmup_steps >= 0, got {steps}, {warmup_steps}")
    cfg = config or DriverConfig()
    family = road_family(family)
    drivable_map = family_map(family, resolution)
    env = gymnasium.make(
        ENV_IDS[family],
        config={"simulation_frequency": 10, "neighbour_vehicles_connected_lanes": True},
    ).unwrapped
    env.reset(seed=int(rng.integers(2**31)))
    road = env.road
    road.vehicles.clear()
    traffic = _Traffic(road, drivable_map, family, rng, cfg)
    traffic.populate()
    rows: list[list[tuple[int, float, float, float, float]]] = []
    for step in range(warmup_steps + steps):
        if step >= warmup_steps:
            rows.append(traffic.snapshot())
        traffic.step()
    env.close()
    return traffic.to_recording(rows)


class _Traffic:
    """The vehicles of one simulation: placement, entries, exits, bookkeeping."""

    def __init__(self, road, drivable_map: DrivableMap, family: str, rng, cfg: DriverConfig):
        self.road, self.map, self.family, self.rng, self.cfg = road, drivable_map, family, rng, cfg
        self.extra_headway = rng.uniform(*cfg.extra_headway)
        graph = road.network.graph
        incoming = {end for ends in graph.values() for end in ends}
        boundary = set(BOUNDARY_NODES.get(family, ()))
        self.entries = [
            (start, end, index)
            for start, ends in graph.items()
            for end, lanes in ends.items()
            for index in range(len(lanes))
            if start not in incoming or start in boundary
        ]
        cut = MAP_LENGTH.get(family, DEFAULT_MAP_LENGTH)
        self.exit_at: dict[tuple, float] = {}  # lane index -> arclength where vehicles leave
        for start, ends in graph.items():
            for end, lanes in ends.items():
                for index, lane in enumerate(lanes):
                    if end not in graph or end in boundary or lane.length > cut:
                        self.exit_at[(start, end, index)] = min(cut, lane.length)
        self.meta: list[tuple[float, float, str]] = []  # per row: length, width, kind
        self.crashed: set[int] = set()
        self.stepper = RoadStepper(road, regulated=family in REGULATED_FAMILIES)

    def new_vehicle(self, lane_index: tuple, s: float, speed_share: tuple[float, float]):
        """An IDM vehicle with drawn parameters on ``lane_index`` at arclength ``s`` [m]."""
        rng, cfg = self.rng, self.cfg
        lane = self.road.network.get_lane(lane_index)
        truck = self.family in TRUCK_FAMILIES and rng.random() < cfg.truck_fraction
        limit = lane.speed_limit or cfg.default_speed_limit
        desired = rng.uniform(*cfg.speed_fraction) * limit
        desired *= cfg.truck_speed_factor if truck else 1.0
        vehicle = traffic_vehicle_class()(
            self.road,
            lane.position(s, 0.0),
            lane.heading_at(s),
            desired * rng.uniform(*speed_share),
            target_lane_index=lane_index,
            target_speed=desired,
        )
        vehicle.LENGTH = rng.uniform(*(cfg.truck_length if truck else cfg.car_length))
        vehicle.WIDTH = rng.uniform(*(cfg.truck_width if truck else cfg.car_width))
        vehicle.diagonal = float(np.hypot(vehicle.LENGTH, vehicle.WIDTH))
        vehicle.kind = "truck" if truck else "car"
        vehicle.TIME_WANTED = rng.uniform(*cfg.time_gap)
        vehicle.DISTANCE_WANTED = rng.uniform(*cfg.min_gap) + vehicle.LENGTH  # centre to centre
        vehicle.COMFORT_ACC_MAX = rng.uniform(*cfg.comfort_accel)
        vehicle.COMFORT_ACC_MIN = -rng.uniform(*cfg.comfort_decel)
        vehicle.DELTA = rng.uniform(*cfg.delta)
        vehicle.POLITENESS = rng.uniform(*cfg.politeness)
        vehicle.LANE_CHANGE_MIN_ACC_GAIN = rng.uniform(*cfg.lane_change_gain)
        vehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED = rng.uniform(*cfg.lane_change_max_braking)
        vehicle.ACC_MAX = 6.0  # [m/s^2] highway-env's default
        vehicle.LANE_CHANGE_DELAY = 1.0  # [s] highway-env's default
        vehicle.desired_speed = desired
        vehicle.is_yielding = False
        vehicle.row = -1
        vehicle.halting = False
        vehicle.stop_at, vehicle.stand_left = 0, 0  # its stop: first step, steps at rest
        if cfg.stop_share > 0.0 and rng.random() < cfg.stop_share:
            vehicle.stop_at = self.stepper.steps + round(rng.uniform(*cfg.stop_start) / DT)
            vehicle.stand_left = max(1, round(rng.uniform(*cfg.stop_duration) / DT))
        return vehicle

    def gap(self, vehicle) -> float:
        """Headway-based spacing behind ``vehicle`` [m]: jam gap + v * (T + Exp(extra))."""
        headway = vehicle.TIME_WANTED + self.rng.exponential(self.extra_headway)
        return vehicle.DISTANCE_WANTED + vehicle.speed * headway

    def populate(self) -> None:
        """Initial traffic: every lane filled at drawn headways, overlaps rejected."""
        candidates = []
        for start, ends in self.road.network.graph.items():
            for end, lanes in ends.items():
                for index, lane in enumerate(lanes):
                    lane_index = (start, end, index)
                    stop = self.exit_at.get(lane_index, lane.length)
                    s = self.rng.uniform(0.0, 20.0)
                    while s < stop - 5.0:
                        vehicle = self.new_vehicle(lane_index, s, (0.8, 1.0))
                        candidates.append(vehicle)
                        s += self.gap(vehicle)
        if not candidates:
            return
        xy = np.array([v.position for v in candidates])
        yaw = np.array([v.heading for v in candidates])
        length = np.array([v.DISTANCE_WANTED for v in candidates])  # own length + jam gap
        width = np.array([v.WIDTH + CLEARANCE_WIDTH for v in candidates])
        conflict = pairwise_overlap(xy, yaw, length, width)
        accepted: list[int] = []
        for index in self.rng.permutation(len(candidates)):
            if not conflict[index, accepted].any():
                accepted.append(int(index))
        self.road.vehicles.extend(candidates[i] for i in sorted(accepted))

    def spawn(self) -> None:
        """Poisson arrivals at the entry lanes, when the lane start is clear."""
        for lane_index in self.entries:
            if self.rng.random() >= DT / (1.5 + self.extra_headway):
                continue
            lane = self.road.network.get_lane(lane_index)
            vehicle = self.new_vehicle(lane_index, 0.0, (0.8, 1.0))
            clear = vehicle.DISTANCE_WANTED + vehicle.speed * vehicle.TIME_WANTED
            for other in self.road.vehicles:
                s, lateral = lane.local_coordinates(other.position)
                if (
                    abs(lateral) < 0.75 * lane.width_at(s)
                    and -other.LENGTH < s < clear + other.LENGTH
                ):
                    break
            else:
                self.road.vehicles.append(vehicle)

    def step(self) -> None:
        """Entries, stops, one 0.1 s road step, then exits and removals."""
        self.spawn()
        if self.cfg.stop_share > 0.0:
            now = self.stepper.steps
            for vehicle in self.road.vehicles:  # highway-env's vehicles are objects
                vehicle.halting = vehicle.stand_left > 0 and now >= vehicle.stop_at
                if vehicle.halting and vehicle.speed <= STANDING_SPEED:
                    vehicle.stand_left -= 1
        self.stepper.step()
        self.remove_leaving()

    def remove_leaving(self) -> None:
        """Drop vehicles that crashed, reached an exit, or left the drivable area."""
        kept = []
        positions = np.array([v.position for v in self.road.vehicles]).reshape(-1, 2)
        off_map = self.map.sdf_at(positions) > 0.0
        for vehicle, outside in zip(self.road.vehicles, off_map, strict=True):
            end = self.exit_at.get(vehicle.lane_index)
            leaving = end is not None and (
                vehicle.lane.local_coordinates(vehicle.position)[0] + vehicle.LENGTH / 2 >= end
            )
            if vehicle.crashed and vehicle.row >= 0:
                self.crashed.add(vehicle.row)
            if not (vehicle.crashed or leaving or outside):
                kept.append(vehicle)
        self.road.vehicles[:] = kept

    def snapshot(self) -> list[tuple[int, float, float, float, float]]:
        """(row, x, y, speed, heading) of every vehicle now; rows given on first sight."""
        out = []
        for vehicle in self.road.vehicles:
            if vehicle.row < 0:
                vehicle.row = len(self.meta)
                self.meta.append((vehicle.LENGTH, vehicle.WIDTH, vehicle.kind))
            x, y = vehicle.position
            out.append((vehicle.row, float(x), float(y), float(vehicle.speed), vehicle.heading))
        return out

    def to_recording(self, rows: list[list[tuple]]) -> Recording:
        count, steps = len(self.meta), len(rows)
        states = np.zeros((count, steps, 4))
        valid = np.zeros((count, steps), dtype=bool)
        for step, snapshot in enumerate(rows):
            if snapshot:
                data = np.array(snapshot)
                index = data[:, 0].astype(int)
                states[index, step] = data[:, 1:]
                valid[index, step] = True
        for row in range(count):  # unwrap headings over the (contiguous) valid run
            run = np.flatnonzero(valid[row])
            states[row, run, 3] = np.unwrap(states[row, run, 3])
        crashed = np.zeros(count, dtype=bool)
        crashed[sorted(self.crashed)] = True
        return Recording(
            family=self.family,
            map=self.map,
            states=states,
            valid=valid,
            crashed=crashed,
            length=np.array([m[0] for m in self.meta], dtype=float).reshape(count),
            width=np.array([m[1] for m in self.meta], dtype=float).reshape(count),
            kinds=tuple(m[2] for m in self.meta),
        )
