"""``Scenario``: what an episode starts from.

A scenario is a map, the agents' sizes, which agent is the ego, and a recorded (or
synthesised) track of every agent: ``history_steps`` states up to and including the
current one, then a reference future, each with a per-step validity mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from riskflow_env.config import is_number, plain_number
from riskflow_env.dynamics import STATE_DIM
from riskflow_env.maps import DrivableMap
from riskflow_env.state import HISTORY_STEPS

MAX_COORDINATE = 1e6  # [m] largest |x|, |y| of a valid track state
MAX_SPEED = 100.0  # [m/s] largest logged speed
MAX_HEADING = 1e4  # [rad] largest |psi| (headings are unwrapped along time)
MAX_SIZE = 50.0  # [m] largest vehicle length or width
MAX_TRACKS = 10_000  # [-] agents N of one scene
MAX_STEPS = 20_000  # [-] steps T of one scene's tracks (2000 s at 10 Hz)
DT_RANGE = (1e-3, 1.0)  # [s] track time steps a scene may have


@dataclass(frozen=True)
class Scenario:
    """One scene: map, agents and their tracks at 10 Hz.

    Attributes:
        map: the drivable area (with lane centrelines where the source has them).
        states: (N, T, 4) float64 tracks (x [m], y [m], v [m/s], psi [rad]); the first
            ``history_steps`` entries are the history (the last of them is the current
            state), the rest is the reference future. At valid steps: positions within
            +-``MAX_COORDINATE``, speeds in [0, ``MAX_SPEED``], headings within
            +-``MAX_HEADING``; N <= ``MAX_TRACKS``, T <= ``MAX_STEPS``.
        valid: (N, T) bool, whether each track state was observed.
        length: (N,) vehicle lengths [m], in (0, ``MAX_SIZE``].
        width: (N,) vehicle widths [m], in (0, ``MAX_SIZE``].
        ego_index: row of ``states`` that is the ego (the agent under test).
        agent_ids: (N,) names of the agents in the source data (for traceability).
        name: a short identifier of the scene (source, family, seed...).
        dt: track time step [s], in ``DT_RANGE``: a number (a numpy int or float scalar
            too, not a bool), stored as a Python float.
        history_steps: number of history states, the current one included.
        kinds: (N,) agent categories (e.g. ``"car"``, ``"truck"``), or empty when unknown.
        source: where the scene comes from (e.g. ``"highway-env-idm"``, a dataset name).
        family: road family or location label (e.g. ``"roundabout"``), or empty.
    """

    map: DrivableMap
    states: np.ndarray
    valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    ego_index: int = 0
    agent_ids: tuple[str, ...] = field(default=())
    name: str = ""
    dt: float = 0.1
    history_steps: int = HISTORY_STEPS
    kinds: tuple[str, ...] = field(default=())
    source: str = ""
    family: str = ""

    def __post_init__(self) -> None:
        states = self.states
        if not isinstance(states, np.ndarray) or states.ndim != 3 or states.shape[2] != STATE_DIM:
            got = getattr(states, "shape", type(states).__name__)
            raise ValueError(f"Scenario.states must have shape (N, T, {STATE_DIM}), got {got}")
        num_agents, num_steps = states.shape[:2]
        if num_agents == 0:
            raise ValueError("Scenario.states holds no agent (N = 0)")
        if num_agents > MAX_TRACKS or num_steps > MAX_STEPS:
            raise ValueError(
                f"Scenario.states of shape {states.shape} exceeds MAX_TRACKS = {MAX_TRACKS} "
                f"agents or MAX_STEPS = {MAX_STEPS} steps"
            )
        for name, shape in (
            ("valid", (num_agents, num_steps)),
            ("length", (num_agents,)),
            ("width", (num_agents,)),
        ):
            value = getattr(self, name)
            if not isinstance(value, np.ndarray) or value.shape != shape:
                got = getattr(value, "shape", type(value).__name__)
                raise ValueError(f"Scenario.{name} must have shape {shape}, got {got}")
        if self.valid.dtype != np.bool_:  # 0/1 ints would index rows, not mask them
            raise ValueError(f"Scenario.valid must be a bool array, got dtype {self.valid.dtype}")
        for name in ("ego_index", "history_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"Scenario.{name} must be an int, got {value!r}")
        if not 0 < self.history_steps <= num_steps:
            raise ValueError(
                f"Scenario.history_steps must be in [1, {num_steps}], got {self.history_steps}"
            )
        if not 0 <= self.ego_index < num_agents:
            raise ValueError(
                f"Scenario.ego_index must be in [0, {num_agents}), got {self.ego_index}"
            )
        if not self.valid[self.ego_index, self.history_steps - 1]:
            raise ValueError("Scenario: the ego must be valid at the current step")
        if not np.all(np.isfinite(states[self.valid])):
            raise ValueError("Scenario.states has NaN or inf at valid steps")
        observed = states[self.valid]
        if np.any(np.abs(observed[:, :2]) > MAX_COORDINATE):
            raise ValueError(
                f"Scenario.states has a position beyond +-{MAX_COORDINATE:g} m at a valid step"
            )
        speeds = observed[:, 2]
        if np.any(speeds < 0) or np.any(speeds > MAX_SPEED):
            raise ValueError(
                f"Scenario.states has a speed outside [0, {MAX_SPEED:g}] m/s at a valid step "
                f"(got {float(speeds.min()):g} .. {float(speeds.max()):g})"
            )
        if np.any(np.abs(observed[:, 3]) > MAX_HEADING):
            raise ValueError(f"Scenario.states has a heading beyond +-{MAX_HEADING:g} rad")
        for name in ("length", "width"):
            size = getattr(self, name)
            bad = np.flatnonzero(~((size > 0) & (size <= MAX_SIZE)))  # NaN fails both
            if bad.size:
                raise ValueError(
                    f"Scenario.{name} must be finite, > 0 and <= {MAX_SIZE:g} m, got "
                    f"{size[bad[0]]!r} for agent {bad[0]} ({bad.size} agent(s) out of range)"
                )
        dt = self.dt
        if not is_number(dt) or not DT_RANGE[0] <= plain_number(dt) <= DT_RANGE[1]:
            raise ValueError(
                f"Scenario.dt must be a number in [{DT_RANGE[0]:g}, {DT_RANGE[1]:g}] s, got {dt!r}"
            )
        object.__setattr__(self, "dt", float(plain_number(dt)))
        if self.agent_ids and len(self.agent_ids) != num_agents:
            raise ValueError(
                f"Scenario.agent_ids must name all {num_agents} agents, got {len(self.agent_ids)}"
            )
        if self.kinds and len(self.kinds) != num_agents:
            raise ValueError(
                f"Scenario.kinds must give all {num_agents} agents a kind, got {len(self.kinds)}"
            )
        for name in ("agent_ids", "kinds"):
            values = getattr(self, name)
            if not all(isinstance(value, str) for value in values):
                raise ValueError(f"Scenario.{name} must hold strings, got {values!r}")
            object.__setattr__(self, name, tuple(values))
        for name in ("name", "source", "family"):
            if not isinstance(getattr(self, name), str):
                raise ValueError(f"Scenario.{name} must be a string, got {getattr(self, name)!r}")

    @property
    def num_agents(self) -> int:
        """Number of agents N."""
        return self.states.shape[0]

    @property
    def current_index(self) -> int:
        """Index of the current step in ``states``."""
        return self.history_steps - 1

    @property
    def future_steps(self) -> int:
        """Length of the reference future."""
        return self.states.shape[1] - self.history_steps
