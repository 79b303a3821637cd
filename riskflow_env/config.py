"""Frozen, validated configuration dataclasses. Every field carries its unit."""

from __future__ import annotations

import functools
import math
import typing
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from riskflow_env.untrusted import brief


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


MAX_MAGNITUDE = 1e6  # largest |value| of a real-valued config field (float32-safe)


def is_number(value: object) -> bool:
    """A real number: a Python int or float, or a numpy integer or float scalar of any
    dtype (``np.float32(0.1)``); bools (Python and numpy) are not numbers."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


def is_integer(value: object) -> bool:
    """An integer: a Python int or a numpy integer scalar; bools are not integers."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def plain_number(value: float) -> float:
    """A number as a Python one: numpy integers -> int, numpy float scalars -> float; a
    float16/float32 one by its shortest decimal (``np.float32(0.1)`` -> 0.1, not
    0.10000000149011612, so that it matches a float64 0.1, e.g. a scenario's ``dt``)."""
    if isinstance(value, (np.float16, np.float32)):  # numpy's print options do not matter
        return float(np.format_float_scientific(value, unique=True))
    if isinstance(value, np.floating):
        return float(value)
    return int(value) if isinstance(value, np.integer) else value


def _finite(name: str, value: float) -> float:
    """``value`` as a Python number (:func:`plain_number`), or a ValueError naming ``name``
    unless it is a finite number (:func:`is_number`) within +-``MAX_MAGNITUDE``."""
    number = plain_number(value) if is_number(value) else None
    _require(  # NaN and inf fail the comparison; a huge int compares without overflow
        number is not None and abs(number) <= MAX_MAGNITUDE,
        f"{name} must be a finite number within +-{MAX_MAGNITUDE:g}, got {value!r}",
    )
    return number


def _set_finite(config: object, names: Iterable[str]) -> None:
    """Checks the fields ``names`` of the frozen dataclass ``config`` with :func:`_finite`
    (errors name ``Class.field``) and stores them as Python numbers."""
    for name in names:
        value = _finite(f"{type(config).__name__}.{name}", getattr(config, name))
        object.__setattr__(config, name, value)


def _integer(name: str, value: int, minimum: int, maximum: int = 1_000_000) -> int:
    """``value`` as a Python int, or a ValueError naming ``name`` unless it is an int
    (Python or numpy; bools are not ints) in [minimum, maximum]."""
    _require(
        is_integer(value) and minimum <= value <= maximum,
        f"{name} must be an int in [{minimum}, {maximum}] (booleans are not ints), got {value!r}",
    )
    return int(value)


def _set_integer(config: object, name: str, minimum: int, maximum: int = 1_000_000) -> None:
    """Checks the field ``name`` of the frozen dataclass ``config`` with :func:`_integer`
    (the error names ``Class.field``) and stores it as a Python int."""
    value = _integer(f"{type(config).__name__}.{name}", getattr(config, name), minimum, maximum)
    object.__setattr__(config, name, value)


_KINDS = {bool: "true or false", int: "an int", float: "a number"}


def _is_bool(value: object) -> bool:
    return isinstance(value, (bool, np.bool_))


_FITS = {bool: _is_bool, int: is_integer, float: is_number}


def check_field_types(config: object, name_of: Callable[[str], str] | None = None) -> None:
    """ValueError naming the first ``int``, ``float`` or ``bool`` field of the dataclass
    ``config`` (``X | None`` ones may be None) whose value is not of its type: an int for an
    int (numpy integers too), a number for a float (any int or numpy number; bools are
    neither), a bool for a bool. Values are stored as Python ones (:func:`plain_number`),
    a float field's as float. ``name_of(field)`` names a field (default ``Class.field``)."""
    hints = _type_hints(type(config))
    for item in fields(config):
        hint, value = hints[item.name], getattr(config, item.name)
        args = typing.get_args(hint)
        if type(None) in args:
            if value is None:
                continue
            hint = next((arg for arg in args if arg is not type(None)), hint)
        if hint not in _FITS:
            continue
        kind = _KINDS[hint]
        try:
            fits = _FITS[hint](value)
            typed = hint(value if hint is bool else plain_number(value)) if fits else None
        except OverflowError:  # a float field's int too large for a float (10**400)
            fits, kind = False, "a finite number"
        if not fits:
            name = name_of(item.name) if name_of else f"{type(config).__name__}.{item.name}"
            raise ValueError(f"{name} must be {kind}, got {brief(value)}")
        object.__setattr__(config, item.name, typed)


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """The resolved field annotations of a dataclass (read once per class)."""
    return typing.get_type_hints(cls)


MAX_EPISODE_STEPS = 10_000_000  # [-] longest episode (EnvConfig.episode_steps)


@dataclass(frozen=True)
class DynamicsConfig:
    """Unicycle model bounds and time step (docs/explanation/architecture.md).

    Attributes:
        dt: integration step [s].
        accel_min: strongest braking allowed [m/s^2] (negative).
        accel_max: strongest acceleration allowed [m/s^2].
        yaw_rate_max: bound on |yaw rate| [rad/s].
        speed_min: lowest speed [m/s], >= 0 (vehicles never reverse); above 0 they never stop.
        speed_max: highest speed [m/s]. The env clamps the speed after every step; a
            plan's rollout (:func:`riskflow_env.dynamics.rollout`, vectorised over time)
            does the same exactly unless the plan reaches both speed bounds, which takes
            at least ``(speed_max - speed_min) / max(-accel_min, accel_max)`` seconds
            (5 s with these defaults, against 5.2 s plans whose first step would have to
            push at ``speed_max``); then its speeds stay within the bounds but can drift from
            step-by-step clamping. Narrow the speed range with that in mind.
        turn_radius_min: tightest turn [m]: over each step ``|yaw rate| <= v_mean /
            turn_radius_min`` (``v_mean`` the step's mean speed), the bound of a
            kinematic bicycle at full lock, so a vehicle turns only while it rolls; 0
            removes it (a vehicle may turn in place).
    """

    dt: float = 0.1
    accel_min: float = -8.0
    accel_max: float = 5.0
    yaw_rate_max: float = 1.0
    speed_min: float = 0.0
    speed_max: float = 40.0
    turn_radius_min: float = 5.0

    def __post_init__(self) -> None:
        _set_finite(self, (
            "dt", "accel_min", "accel_max", "yaw_rate_max", "speed_min", "speed_max",
            "turn_radius_min",
        ))  # fmt: skip
        _require(self.dt > 0, f"DynamicsConfig.dt must be > 0 s, got {self.dt}")
        _require(
            self.accel_min < 0 < self.accel_max,
            "DynamicsConfig needs accel_min < 0 < accel_max [m/s^2], "
            f"got accel_min={self.accel_min}, accel_max={self.accel_max}",
        )
        _require(
            self.yaw_rate_max > 0,
            f"DynamicsConfig.yaw_rate_max must be > 0 rad/s, got {self.yaw_rate_max}",
        )
        _require(
            0 <= self.speed_min < self.speed_max,
            "DynamicsConfig needs 0 <= speed_min < speed_max [m/s], "
            f"got speed_min={self.speed_min}, speed_max={self.speed_max}",
        )
        _require(
            self.turn_radius_min >= 0,
            f"DynamicsConfig.turn_radius_min must be >= 0 m, got {self.turn_radius_min}",
        )


AGENT_GROUPS = ("all", "ego", "none")
MAX_AGENTS = 1024  # [-] largest EnvConfig.max_agents (pairwise state grows with its square)
MAX_RAY_DISTANCE = 1e4  # [m] farthest SDF sample of an observation ray


@dataclass(frozen=True)
class ObservationConfig:
    """What each agent observes (identical layout for every agent).

    Attributes:
        num_neighbors: nearest other vehicles observed, in the agent's frame.
        ray_directions: number of equally spaced directions of map SDF samples.
        ray_distances: distances of the SDF samples along each direction [m].
    """

    num_neighbors: int = 8
    ray_directions: int = 12
    ray_distances: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0)

    def __post_init__(self) -> None:
        _set_integer(self, "num_neighbors", 0, 1024)
        _set_integer(self, "ray_directions", 0, 1024)
        if isinstance(self.ray_distances, list):
            object.__setattr__(self, "ray_distances", tuple(self.ray_distances))
        _require(
            isinstance(self.ray_distances, tuple)
            and len(self.ray_distances) <= 1024
            and all(
                is_number(d) and math.isfinite(d) and 0 < d <= MAX_RAY_DISTANCE
                for d in self.ray_distances
            ),
            "ObservationConfig.ray_distances must be a tuple of positive metres <= "
            f"{MAX_RAY_DISTANCE:g}, got {self.ray_distances!r}",
        )
        object.__setattr__(self, "ray_distances", tuple(map(plain_number, self.ray_distances)))


@dataclass(frozen=True)
class RewardConfig:
    """Per-step reward terms (each reported separately in ``info["reward_terms"]``).

    reward = speed * min(v, target_speed) / target_speed
           + collision * [in collision] + offroad * [footprint off the road]
           + risk * max_j risk_ij + comfort * ((a / accel_max)^2 + (omega / yaw_rate_max)^2)

    Any finite weight is taken; "(negative)" marks the terms that are penalties by default.

    Attributes:
        target_speed: speed at which the speed term saturates [m/s].
        speed: weight of the normalised speed term [reward / step].
        collision: reward while overlapping another vehicle [reward / step] (negative).
        offroad: reward while any footprint point is off the road [reward / step] (negative).
        risk: weight of the largest TTC risk weight towards any other vehicle (negative).
        comfort: weight of the normalised squared action (negative).
    """

    target_speed: float = 25.0
    speed: float = 0.1
    collision: float = -5.0
    offroad: float = -5.0
    risk: float = -0.05
    comfort: float = -0.01

    def __post_init__(self) -> None:
        _set_finite(self, ("target_speed", "speed", "collision", "offroad", "risk", "comfort"))
        _require(
            self.target_speed > 0,
            f"RewardConfig.target_speed must be > 0 m/s, got {self.target_speed}",
        )


@dataclass(frozen=True)
class EnvConfig:
    """Configuration of :class:`riskflow_env.env.RiskFlowParallelEnv`.

    Attributes:
        max_agents: number of agent slots, the ego included (``possible_agents``); at
            most ``MAX_AGENTS`` (1024).
        episode_steps: steps before truncation (100 steps of 0.1 s = 10 s).
        terminate_on_collision: which agents terminate when they collide: "all" (the
            default: both vehicles of every collision stop where they touched and stay
            as obstacles), "ego" (the other vehicles drive on through their contacts),
            "none", or a tuple of agent names.
        terminate_on_offroad: same, for driving off the road.
        end_with_ego: when the ego is done, truncate every other agent too.
        leave_when_log_ends: an agent other than the ego leaves the scene (truncated,
            no longer present: no obstacle, no events) at the first step after its
            logged reference ends (``Scenario.valid`` False from there on), as log
            validity masks do in Waymax; for recorded scenes whose vehicles enter and
            leave. False keeps every agent for the whole episode.
        clip_actions: clip actions to the action space (the dynamics bounds); when False,
            an out-of-bounds action raises ValueError instead.
        dynamics: unicycle bounds and time step.
        observation: observation layout.
        reward: reward weights.
    """

    max_agents: int = 32
    episode_steps: int = 100
    terminate_on_collision: str | tuple[str, ...] = "all"
    terminate_on_offroad: str | tuple[str, ...] = "ego"
    end_with_ego: bool = True
    leave_when_log_ends: bool = False
    clip_actions: bool = True
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)

    def __post_init__(self) -> None:
        _set_integer(self, "max_agents", 1, MAX_AGENTS)
        _set_integer(self, "episode_steps", 1, MAX_EPISODE_STEPS)
        for name in ("end_with_ego", "leave_when_log_ends", "clip_actions"):
            _require(
                isinstance(getattr(self, name), bool),
                f"EnvConfig.{name} must be a bool, got {getattr(self, name)!r}",
            )
        for name, kind in (
            ("dynamics", DynamicsConfig),
            ("observation", ObservationConfig),
            ("reward", RewardConfig),
        ):
            value = getattr(self, name)
            _require(
                isinstance(value, kind),
                f"EnvConfig.{name} must be a {kind.__name__}, got {type(value).__name__}",
            )
        names = set(agent_names(self.max_agents))
        for option in ("terminate_on_collision", "terminate_on_offroad"):
            value = getattr(self, option)
            expected = f"EnvConfig.{option} must be one of {AGENT_GROUPS} or a tuple of agent names"
            if isinstance(value, str):
                _require(value in AGENT_GROUPS, f"{expected}, got {value!r}")
                continue
            _require(
                isinstance(value, (tuple, list, set, frozenset))
                and all(isinstance(v, str) for v in value),
                f"{expected}, got {value!r}",
            )  # stored as a tuple (hashable); a set in sorted order
            ordered = tuple(value) if isinstance(value, (tuple, list)) else tuple(sorted(value))
            object.__setattr__(self, option, ordered)
            unknown = sorted(set(value) - names)
            _require(not unknown, f"EnvConfig.{option} names unknown agents {unknown}")

    @property
    def agent_names(self) -> tuple[str, ...]:
        """Fixed agent names: ``ego`` then ``agent_1`` ... ``agent_{max_agents - 1}``."""
        return agent_names(self.max_agents)

    def selects(self, option: str) -> tuple[bool, ...]:
        """Per-slot mask of the agents selected by a termination option."""
        value = getattr(self, option)
        names = self.agent_names
        if value == "all":
            return (True,) * len(names)
        if value == "none":
            return (False,) * len(names)
        if value == "ego":
            return (True,) + (False,) * (len(names) - 1)
        return tuple(name in value for name in names)


def agent_names(max_agents: int) -> tuple[str, ...]:
    """``("ego", "agent_1", ..., "agent_{max_agents - 1}")``."""
    return ("ego",) + tuple(f"agent_{i}" for i in range(1, max_agents))
