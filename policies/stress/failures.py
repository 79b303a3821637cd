"""Failure analysis: what kind of collision each ego collision is, whether the ego could
have avoided it, and whether the vehicle that struck it drove like a human.

:func:`analyse` reads one :class:`~policies.harness.EpisodeRecord` and returns a
:class:`Failure` per ``collision_start`` event that involves the ego:

* **type** (:func:`collision_type`, from the geometry at the first contact and 1.5 s
  before it): ``struck_from_behind`` (the other's front into the ego's rear, same
  direction), ``striking_from_behind`` (the ego's front into the other's rear),
  ``cut_in`` (the other ahead of the ego after coming from beside it: more than
  ``LANE_HALF_WIDTH`` to the side 1.5 s earlier), ``side_swipe`` (same direction, side
  contact), ``head_on`` (headings more than 135 degrees apart), ``crossing`` (45 to 135
  degrees), ``other``; with the impact's relative speed, the ego's speed, whether the ego
  was standing (below ``STANDING_SPEED``) and the guided vehicles within ``NEARBY`` of the
  ego (box separation) at impact.
* **avoidability** (:mod:`policies.stress.escape`): the other vehicles' executed
  trajectories held fixed (and continued at constant speed and heading past the end of
  the record), the ego's actions are searched from the *reaction point* to
  ``AFTER_COLLISION`` past the impact. The reaction point is ``REACTION_TIME`` after the
  first step the colliding vehicle was guided (the episode's start when that was less
  than ``REACTION_TIME`` in, or when it was never guided). A reaction point at or after
  the impact leaves no time: not avoidable, no search.
* **attacker plausibility**: the colliding vehicle's p99 |acceleration|, |jerk| and |yaw
  rate| up to its first contact with any vehicle (a vehicle in contact is frozen by the
  env, a stop that is the env's rule, not driving), from its first guided step or the
  last ``REACTION_TIME`` before that contact, whichever is earlier, against
  :data:`HUMAN_BOUNDS`.
* **wreck**: the other vehicle had already collided with a third one before the impact
  (the ego ran into, or was hit by, a wreck).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policies.harness import EGO, EpisodeRecord
from policies.learned.guidance_losses import HUMAN_ACCEL, HUMAN_YAW_RATE
from policies.stress.escape import Escape, EscapeSearch, Obstacles, find_escape
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW, wrap_angle
from riskflow_env.geometry import separation, to_frame
from riskflow_env.wrappers.event_contact import contact_kind, contact_point

FAILURE_TYPES = (
    "struck_from_behind", "striking_from_behind", "cut_in", "side_swipe", "head_on",
    "crossing", "other",
)  # fmt: skip
STANDING_SPEED = 0.5  # [m/s] an ego slower than this at impact is standing
NEARBY = 5.0  # [m] box separation within which a guided vehicle counts at impact
REACTION_TIME = 1.0  # [s] from the attack's start to the reaction point
AFTER_COLLISION = 2.0  # [s] the escape must stay clear this long past the impact
LOOK_BACK = 1.5  # [s] how far before the impact a cut-in is recognised
LANE_HALF_WIDTH = 1.75  # [m] lateral offset that puts a vehicle in the next lane


@dataclass(frozen=True)
class KinematicBounds:
    """p99 of |acceleration| [m/s^2], |jerk| [m/s^3] and |yaw rate| [rad/s]."""

    accel: float
    jerk: float
    yaw_rate: float
    source: str = ""

    def admit(self, p99: dict[str, float]) -> bool:
        """Whether every p99 of ``p99`` (keys ``accel``, ``jerk``, ``yaw_rate``) is within
        its bound, to float rounding: a vehicle held to a bound exactly (the guided
        attacker's and the braking fallback's acceleration) reads a hair over it from
        finite differences of its states (6.000000000000004 for 6)."""
        return all(value <= getattr(self, name) * (1 + 1e-9) for name, value in p99.items())


# Measured by :func:`kinematic_bounds` on the reference futures of the shipped training
# bank (``shipped_bank("train")``, highway-env IDM/MOBIL traffic: the kind of data the
# shipped generator learned from); tests/policies/stress/test_failures.py re-measures them.
HUMAN_BOUNDS = KinematicBounds(
    accel=HUMAN_ACCEL, jerk=27.79, yaw_rate=HUMAN_YAW_RATE,
    source="p99 of shipped_bank('train') futures",
)  # fmt: skip


@dataclass(frozen=True)
class Failure:
    """One ego collision, analysed.

    Attributes:
        scenario: scenario name.
        step: env step of the first contact (index into the record's states).
        time: [s] of the first contact.
        attacker: name of the other vehicle.
        type: one of :data:`FAILURE_TYPES`.
        relative_speed: [m/s] norm of the velocity difference at impact.
        ego_speed, attacker_speed: [m/s] at impact.
        standing_ego: the ego was slower than ``STANDING_SPEED``.
        attacker_guided: the attacker was guided at some step before the impact.
        guided_nearby: guided vehicles within ``NEARBY`` of the ego at impact.
        attack_start: [s] first step the attacker was guided (None: never).
        reaction_time: [s] where the escape search started.
        avoidable: an escape was found (the witness keeps clear and on the road).
        searched: the search ran (False: no reaction time before the impact).
        attacker_p99: p99 {"accel", "jerk", "yaw_rate"} of the attacker over the attack.
        plausible: ``attacker_p99`` within :data:`HUMAN_BOUNDS`, all three.
        wreck: the attacker had collided with another vehicle before the impact.
        escape: the search's result (its ``states`` are the witness when avoidable).
    """

    scenario: str
    step: int
    time: float
    attacker: str
    type: str
    relative_speed: float
    ego_speed: float
    attacker_speed: float
    standing_ego: bool
    attacker_guided: bool
    guided_nearby: int
    attack_start: float | None
    reaction_time: float
    avoidable: bool
    searched: bool
    attacker_p99: dict[str, float] = field(default_factory=dict)
    plausible: bool = True
    wreck: bool = False
    escape: Escape | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (the witness as a list of states when there is one)."""
        row = {name: getattr(self, name) for name in self.__dataclass_fields__}
        escape = row.pop("escape")
        row["witness"] = escape.states.round(4).tolist() if self.avoidable else None
        row["escape_clearance"] = None if escape is None else escape.clearance
        return row


def analyse(
    record: EpisodeRecord,
    dynamics: DynamicsConfig | None = None,
    search: EscapeSearch | None = None,
    bounds: KinematicBounds = HUMAN_BOUNDS,
) -> tuple[Failure, ...]:
    """Every ego collision of ``record``, analysed (module docstring).

    Args:
        record: a closed-loop episode (``guided`` from a policy with ``controllable``).
        dynamics: the ego's bounds (default ``DynamicsConfig()``, the env's default).
        search: the escape search's budget.
        bounds: the attacker's plausibility bounds.
    """
    if not isinstance(record, EpisodeRecord):
        raise TypeError(f"record must be an EpisodeRecord, got {type(record).__name__}")
    dynamics, search = dynamics or DynamicsConfig(), search or EscapeSearch()
    slots = {name: index for index, name in enumerate(record.agent_names)}
    failures = []
    for event in record.events:
        if event["event"] != "collision_start" or not event["ego_involved"]:
            continue
        other = next(name for name in event["agents"] if name != EGO)
        failures.append(
            _failure(record, int(event["step"]), slots[other], dynamics, search, bounds)
        )
    return tuple(failures)


def _failure(record, step, other, dynamics, search, bounds) -> Failure:
    states, dt = record.states, record.dt
    ego, attacker = states[0, step], states[other, step]
    length, width = np.asarray(record.scenario.length), np.asarray(record.scenario.width)
    size = np.array([[length[row], width[row]] for row in record.scenario_rows[[0, other]]])
    guided = record.guided
    attack = None if guided is None else np.flatnonzero(guided[other, :step])
    attack_step = int(attack[0]) if attack is not None and attack.size else None
    reaction = reaction_step(attack_step, dt)
    escape = None
    if reaction < step:
        escape = find_escape(
            states[0, reaction], tuple(size[0]),
            obstacles(record, reaction, step + round(AFTER_COLLISION / dt)),
            record.scenario.map, dynamics, search,
        )  # fmt: skip
    contact = first_contact(record, record.agent_names[other], step)
    end = min(step, contact) + 1  # driving, not the freeze that follows a contact
    last_second = end - 1 - round(REACTION_TIME / dt)
    start = last_second if attack_step is None else min(attack_step, last_second)
    p99 = kinematic_p99(states[other, max(0, start) : end], dt)
    return Failure(
        scenario=record.scenario.name,
        step=step,
        time=step * dt,
        attacker=record.agent_names[other],
        type=collision_type(states[0, : step + 1], states[other, : step + 1], size, dt),
        relative_speed=float(np.linalg.norm(_velocity(ego) - _velocity(attacker))),
        ego_speed=float(ego[SPEED]),
        attacker_speed=float(attacker[SPEED]),
        standing_ego=bool(ego[SPEED] < STANDING_SPEED),
        attacker_guided=attack_step is not None,
        guided_nearby=guided_nearby(record, step, size[0]),
        attack_start=None if attack_step is None else attack_step * dt,
        reaction_time=reaction * dt,
        avoidable=bool(escape is not None and escape.found),
        searched=escape is not None,
        attacker_p99=p99,
        plausible=bounds.admit(p99),
        wreck=contact < step,
        escape=escape,
    )


def first_contact(record: EpisodeRecord, name: str, step: int) -> int:
    """The first step, up to ``step``, at which vehicle ``name`` began a contact with any
    vehicle (``step`` when none began before it)."""
    steps = [
        int(event["step"])
        for event in record.events
        if event["event"] == "collision_start" and name in event["agents"]
    ]
    return min([step, *steps])


def reaction_step(attack_step: int | None, dt: float) -> int:
    """The step the escape search starts from (module docstring)."""
    delay = round(REACTION_TIME / dt)
    if attack_step is None or attack_step < delay:
        return 0
    return attack_step + delay


def obstacles(record: EpisodeRecord, start: int, end: int) -> Obstacles:
    """The other vehicles at steps ``start + 1 .. end``, held at constant speed and
    heading past the record's last step."""
    states, dt = record.states, record.dt
    last = states.shape[1] - 1
    others = np.flatnonzero(record.present)
    others = others[others != 0]
    steps = np.arange(start + 1, end + 1)
    beyond = np.maximum(steps - last, 0) * dt  # (H,) [s] past the record
    held = states[others][:, np.minimum(steps, last)]  # (N, H, 4)
    xy = held[..., :2] + beyond[None, :, None] * _velocity(held)
    rows = record.scenario_rows[others]
    return Obstacles(
        xy=xy,
        yaw=held[..., YAW],
        length=np.asarray(record.scenario.length)[rows],
        width=np.asarray(record.scenario.width)[rows],
        present=record.in_scene[others][:, np.minimum(steps, last)],
    )


def collision_type(ego: np.ndarray, other: np.ndarray, size: np.ndarray, dt: float) -> str:
    """The kind of collision (module docstring) from the two vehicles' states.

    Args:
        ego, other: (S, 4) states up to and including the first contact (the last row).
        size: (2, 2) (length, width) [m] of the ego and the other.
        dt: [s] time step.
    """
    e, o = ego[-1], other[-1]
    turn = abs(float(wrap_angle(np.asarray(o[YAW] - e[YAW]))))
    if turn > np.radians(135):
        return "head_on"
    if turn > np.radians(45):
        return "crossing"
    pair = np.stack((e, o))
    point = contact_point(pair[:, :2], pair[:, YAW], size[:, 0], size[:, 1])
    ego_kind = contact_kind(point, e[:2], e[YAW], *size[0])
    other_kind = contact_kind(point, o[:2], o[YAW], *size[1])
    if ego_kind == "rear" and other_kind == "front":
        return "struck_from_behind"
    before = max(0, len(ego) - 1 - round(LOOK_BACK / dt))
    ahead, _ = _offset(e, o)
    _, beside = _offset(ego[before], other[before])
    if ego_kind == "front" and ahead > 0 and abs(beside) > LANE_HALF_WIDTH:
        return "cut_in"
    if ego_kind == "front" and other_kind == "rear":
        return "striking_from_behind"
    if "side" in (ego_kind, other_kind):
        return "side_swipe"
    return "other"


def guided_nearby(record: EpisodeRecord, step: int, ego_size: np.ndarray) -> int:
    """Guided vehicles (at the step before ``step``) within ``NEARBY`` of the ego."""
    if record.guided is None:
        return 0
    guided = record.guided[:, max(step - 1, 0)] & record.in_scene[:, step]
    guided[0] = False
    if not guided.any():
        return 0
    states, rows = record.states[guided, step], record.scenario_rows[guided]
    gap = separation(
        record.states[0, step, :2], record.states[0, step, YAW], ego_size[0], ego_size[1],
        states[:, :2], states[:, YAW], np.asarray(record.scenario.length)[rows],
        np.asarray(record.scenario.width)[rows],
    )  # fmt: skip
    return int((gap <= NEARBY).sum())


def kinematic_p99(states: np.ndarray, dt: float) -> dict[str, float]:
    """p99 of |acceleration|, |jerk| and |yaw rate| of one vehicle's states (S, 4)
    (0 where there are too few steps to difference)."""
    rates = _rates(states[None], np.ones((1, len(states)), dtype=bool), dt)
    return {name: _p99(values) for name, values in rates.items()}


def kinematic_bounds(scenarios, source: str = "") -> KinematicBounds:
    """p99 of |acceleration|, |jerk| and |yaw rate| over the valid reference futures of
    ``scenarios`` (runs of consecutive valid steps), the bounds attackers are held to."""
    parts: dict[str, list[np.ndarray]] = {"accel": [], "jerk": [], "yaw_rate": []}
    for scenario in scenarios:
        future = slice(scenario.current_index, None)
        rates = _rates(scenario.states[:, future], scenario.valid[:, future], scenario.dt)
        for name, values in rates.items():
            parts[name].append(values)
    p99 = {name: _p99(np.concatenate(values)) for name, values in parts.items()}
    return KinematicBounds(**p99, source=source)


def _rates(states: np.ndarray, valid: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Acceleration, jerk and yaw rate of tracks (N, S, 4) by finite differences, where
    every step they difference is ``valid`` (N, S): flat arrays."""
    accel = np.diff(states[..., SPEED], axis=1) / dt
    yaw_rate = np.diff(np.unwrap(states[..., YAW], axis=1), axis=1) / dt
    both = valid[:, 1:] & valid[:, :-1]
    return {
        "accel": accel[both],
        "jerk": (np.diff(accel, axis=1) / dt)[both[:, 1:] & both[:, :-1]],
        "yaw_rate": yaw_rate[both],
    }


def _p99(values: np.ndarray) -> float:
    """p99 of |values| (0 for none)."""
    return float(np.percentile(np.abs(values), 99)) if values.size else 0.0


def _velocity(state: np.ndarray) -> np.ndarray:
    """(..., 2) [m/s] velocity of states (..., 4)."""
    heading = np.stack((np.cos(state[..., YAW]), np.sin(state[..., YAW])), axis=-1)
    return state[..., SPEED, None] * heading


def _offset(ego: np.ndarray, other: np.ndarray) -> tuple[float, float]:
    """The other's centre in the ego's frame: (ahead [m], left [m])."""
    dx, dy = other[:2] - ego[:2]
    ahead, left = to_frame(dx, dy, np.cos(ego[YAW]), np.sin(ego[YAW]))
    return float(ahead), float(left)


__all__ = [
    "FAILURE_TYPES",
    "HUMAN_BOUNDS",
    "Failure",
    "KinematicBounds",
    "analyse",
    "collision_type",
    "kinematic_bounds",
    "kinematic_p99",
    "obstacles",
    "reaction_step",
]
