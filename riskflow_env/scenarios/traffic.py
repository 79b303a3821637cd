"""Seeded synthetic traffic on highway-env road networks (the default scenario source).

Vehicles are dropped on lane centrelines at plausible speeds, with time-headway gaps and
no overlap (checked with the same oriented-box test the simulator uses). Their history
and reference future follow the lane at constant speed. This is the embedded default
until recorded traffic (IDM/MOBIL rollouts, real data) is loaded instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from riskflow_env.config import (
    _finite,
    _integer,
    _require,
    _set_finite,
    _set_integer,
    check_field_types,
)
from riskflow_env.geometry import footprint_points, pairwise_overlap
from riskflow_env.maps import FAMILIES, DrivableMap, from_highway_env
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import HISTORY_STEPS


@dataclass(frozen=True)
class TrafficConfig:
    """How :class:`HighwayTrafficSource` places vehicles.

    Attributes:
        families: highway-env road families to draw from (see ``riskflow_env.maps.FAMILIES``).
        num_vehicles: (min, max) vehicles per scene, ego included (inclusive); fewer are
            placed when the road cannot hold that many without breaking the gaps.
        speed_fraction: (min, max) initial speed as a share of the lane speed limit.
        default_speed_limit: speed limit for lanes that carry none [m/s].
        length_range: (min, max) vehicle length [m].
        width_range: (min, max) vehicle width [m].
        time_headway: gap kept behind and ahead of every vehicle, in seconds of its speed [s].
        min_gap: smallest bumper-to-bumper gap [m].
        radius: vehicles are placed within this distance of the ego [m].
        future_steps: length of the constant-speed reference future [steps of dt].
        map_resolution: raster resolution of the built maps [m/px].
        dt: time step of the tracks [s].
    """

    families: tuple[str, ...] = FAMILIES
    num_vehicles: tuple[int, int] = (8, 16)
    speed_fraction: tuple[float, float] = (0.6, 1.0)
    default_speed_limit: float = 20.0
    length_range: tuple[float, float] = (4.2, 5.2)
    width_range: tuple[float, float] = (1.8, 2.1)
    time_headway: float = 1.0
    min_gap: float = 3.0
    radius: float = 120.0
    future_steps: int = 100
    map_resolution: float = 0.5
    dt: float = 0.1

    def __post_init__(self) -> None:
        check_field_types(self)
        unknown = sorted(set(self.families) - set(FAMILIES))
        _require(
            len(self.families) > 0 and not unknown,
            f"TrafficConfig.families must be a non-empty subset of {FAMILIES}, got {self.families}",
        )
        for name in ("num_vehicles", "speed_fraction", "length_range", "width_range"):
            pair = getattr(self, name)
            field = f"TrafficConfig.{name}"
            _require(
                isinstance(pair, (tuple, list)) and len(pair) == 2,
                f"{field} must be a pair (min, max), got {pair!r}",
            )
            if name == "num_vehicles":  # stored as Python numbers
                pair = tuple(_integer(field, value, 1) for value in pair)
            else:
                pair = tuple(_finite(field, value) for value in pair)
            object.__setattr__(self, name, pair)
            _require(
                (pair[0] >= 1 if name == "num_vehicles" else pair[0] > 0) and pair[0] <= pair[1],
                f"{field} must satisfy {'1 <=' if name == 'num_vehicles' else '0 <'} min <= max,"
                f" got {tuple(pair)}",
            )
        positive = ("time_headway", "min_gap", "radius", "map_resolution", "dt")
        _set_finite(self, positive)
        for name in positive:
            value = getattr(self, name)
            _require(value > 0, f"TrafficConfig.{name} must be > 0, got {value}")
        _set_integer(self, "future_steps", 1)


class HighwayTrafficSource:
    """Draws a fresh :class:`Scenario` per reset from a seeded generator.

    Args:
        config: placement parameters.
    """

    def __init__(self, config: TrafficConfig | None = None) -> None:
        self.config = config or TrafficConfig()

    def sample(self, rng: np.random.Generator, max_agents: int | None = None) -> Scenario:
        """A scenario on a random family; deterministic given ``rng``'s state.

        Args:
            rng: the random generator (the env's, seeded at reset).
            max_agents: cap on the number of vehicles (the env's slot count).
        """
        cfg = self.config
        family = cfg.families[int(rng.integers(len(cfg.families)))]
        drivable_map = from_highway_env(family, resolution=cfg.map_resolution)
        low, high = cfg.num_vehicles
        if max_agents is not None:
            high = min(high, max_agents)
            low = min(low, high)
        count = int(rng.integers(low, high + 1))
        return place_traffic(drivable_map, count, rng, cfg, name=f"{family}")


def place_traffic(
    drivable_map: DrivableMap,
    count: int,
    rng: np.random.Generator,
    config: TrafficConfig | None = None,
    name: str = "",
) -> Scenario:
    """Place up to ``count`` non-overlapping vehicles on ``drivable_map``'s lanes.

    Candidates are drawn uniformly along the lanes, filtered to those whose footprint is
    on the road and that lie within ``config.radius`` of the first one (the ego), then
    accepted greedily in random order when their headway-inflated box overlaps no
    accepted one.
    """
    cfg = config or TrafficConfig()
    lanes = drivable_map.lanes
    if not lanes:
        raise ValueError(f"place_traffic: map {drivable_map.name!r} has no lane centrelines")
    lane_lengths = np.array([lane.length for lane in lanes])
    num_candidates = max(64, 12 * count)
    lane_index = rng.choice(len(lanes), size=num_candidates, p=lane_lengths / lane_lengths.sum())
    arc = rng.uniform(0.0, 1.0, size=num_candidates) * lane_lengths[lane_index]
    length = rng.uniform(*cfg.length_range, size=num_candidates)
    width = rng.uniform(*cfg.width_range, size=num_candidates)
    speed_limit = np.array(
        [lane.speed_limit or cfg.default_speed_limit for lane in lanes], dtype=float
    )[lane_index]
    speed = rng.uniform(*cfg.speed_fraction, size=num_candidates) * speed_limit

    offsets = np.arange(-(HISTORY_STEPS - 1), cfg.future_steps + 1) * cfg.dt
    track_arc = arc[:, None] + speed[:, None] * offsets[None, :]  # (C, T)
    xy = np.zeros((num_candidates, offsets.size, 2))
    heading = np.zeros((num_candidates, offsets.size))
    for index, lane in enumerate(lanes):  # a loop over lanes, not agents
        rows = lane_index == index
        if np.any(rows):
            xy[rows], heading[rows] = lane.position(track_arc[rows])
    valid = (track_arc >= 0.0) & (track_arc <= lane_lengths[lane_index][:, None])
    now = HISTORY_STEPS - 1

    centre, yaw = xy[:, now], heading[:, now]
    on_road = _footprint_on_road(drivable_map, centre, yaw, length, width)
    near_ego = np.linalg.norm(centre - centre[0], axis=-1) <= cfg.radius
    keep = np.flatnonzero(on_road & near_ego)
    if keep.size == 0 or keep[0] != 0:
        keep = np.concatenate([[0], keep[keep != 0]])  # candidate 0 is the ego, always kept
    gap = np.maximum(cfg.min_gap, cfg.time_headway * speed[keep])
    conflict = pairwise_overlap(
        centre[keep], yaw[keep], length[keep] + gap, width[keep] + 0.2 * np.ones(keep.size)
    )
    accepted: list[int] = []
    for candidate in range(keep.size):  # greedy acceptance at reset, bounded by 12 * count
        if not conflict[candidate, accepted].any():
            accepted.append(candidate)
            if len(accepted) == count:
                break
    chosen = keep[np.asarray(accepted)]

    states = np.concatenate(
        [xy[chosen], speed[chosen, None, None].repeat(offsets.size, 1), heading[chosen, :, None]],
        axis=-1,
    )
    states[:, :, 3] = np.unwrap(states[:, :, 3], axis=1)
    return Scenario(
        map=drivable_map,
        states=states,
        valid=valid[chosen],
        length=length[chosen],
        width=width[chosen],
        ego_index=0,
        agent_ids=tuple(f"vehicle_{i}" for i in range(chosen.size)),
        name=name,
        dt=cfg.dt,
        history_steps=HISTORY_STEPS,
    )


def _footprint_on_road(
    drivable_map: DrivableMap,
    xy: np.ndarray,
    yaw: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
) -> np.ndarray:
    points = footprint_points(xy, yaw, length, width)
    return np.all(drivable_map.sdf_at(points) <= 0.0, axis=-1)
