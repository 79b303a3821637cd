"""``RolloutRecord``: one closed-loop rollout and its logged reference, as arrays.

Every metric in :mod:`riskflow_env.metrics` is a pure function of one record (or of a
list of them). A record holds ``T`` time steps of ``A`` agent slots:

* ``states`` / ``valid``: what the simulation produced;
* ``reference`` / ``reference_valid``: the logged future of the same slots (ADE, FDE,
  KDD's reference distribution, WOSAC's logged values);
* the first ``num_context`` steps are context, not scored: logged history prepended
  so that finite differences (speeds, accelerations, jerk) are defined from the first
  scored step on, and the reset state itself. Metrics count only steps
  ``t >= num_context``; finite differences may reach back into the context.

Values at invalid steps are ignored; the stored copy holds zeros there, so array
arithmetic on them never raises floating-point warnings.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env.config import plain_number
from riskflow_env.dynamics import STATE_DIM
from riskflow_env.maps import DrivableMap
from riskflow_env.scenarios.scenario import Scenario

NO_EGO = -1  # ego_index of a record without an ego slot


def _stack(values: np.ndarray | Sequence[np.ndarray], name: str) -> np.ndarray:
    """A (A, T, ...) array from an array or a sequence of T per-step (A, ...) arrays."""
    if isinstance(values, np.ndarray):
        return values
    steps = [np.asarray(v) for v in values]
    if not steps:
        raise ValueError(f"{name} holds no time step")
    return np.stack(steps, axis=1)


def _bools(value: object, name: str) -> np.ndarray:
    """``value`` as a numpy bool array (not copied if it is one); a ValueError naming
    ``name`` unless it holds bools (0/1 ints and floats such as 0.5 are refused, not read
    as True/False)."""
    array = np.asarray(value)
    if array.dtype != np.bool_:
        raise ValueError(f"{name} must hold bools (a bool array), got dtype {array.dtype}")
    return array


@dataclass(frozen=True, eq=False)
class RolloutRecord:
    """One rollout of ``A`` agent slots over ``T`` steps, with its logged reference.

    Inputs are copied (float64 / bool) and made read-only. Equality is identity.

    Attributes:
        states: (A, T, 4) simulated (x [m], y [m], v [m/s], psi [rad]).
        valid: (A, T) bool, the slot holds a vehicle at that step. The masks (``valid``,
            ``reference_valid``, ``evaluated``) must hold bools: other dtypes are refused.
        length: (A,) vehicle lengths [m].
        width: (A,) vehicle widths [m].
        reference: (A, T, 4) logged states of the same slots at the same steps.
        reference_valid: (A, T) bool, the log has the state.
        dt: time step [s], > 0.
        ego_index: slot of the ego, or ``NO_EGO`` (-1).
        drivable_map: the scene's map (needed by ORR and WOSAC's map features).
        evaluated: (A,) bool, the agents scored by the per-agent metrics (ORR, ADE/FDE,
            KDD, WOSAC). Collisions (SCR) count every valid agent. Default: all.
        num_context: leading steps that are context, not scored; ``0 <= num_context < T``.
        scene_id: the scene's name; rollouts of one scene share it (WOSAC groups by it).
    """

    states: np.ndarray
    valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    reference: np.ndarray
    reference_valid: np.ndarray
    dt: float = 0.1
    ego_index: int = NO_EGO
    drivable_map: DrivableMap | None = None
    evaluated: np.ndarray | None = None
    num_context: int = 0
    scene_id: str = ""

    def __post_init__(self) -> None:
        states = np.array(self.states, dtype=np.float64)
        if states.ndim != 3 or states.shape[2] != STATE_DIM or 0 in states.shape[:2]:
            raise ValueError(
                f"RolloutRecord.states must have shape (A, T, {STATE_DIM}) with A, T >= 1, "
                f"got {states.shape}"
            )
        num_agents, num_steps = states.shape[:2]
        arrays = {"states": states}
        for name, shape, dtype in (
            ("valid", (num_agents, num_steps), np.bool_),
            ("length", (num_agents,), np.float64),
            ("width", (num_agents,), np.float64),
            ("reference", states.shape, np.float64),
            ("reference_valid", (num_agents, num_steps), np.bool_),
            ("evaluated", (num_agents,), np.bool_),
        ):
            value = getattr(self, name)
            if value is None and name == "evaluated":
                value = np.ones(num_agents, dtype=bool)
            if dtype is np.bool_:
                value = _bools(value, f"RolloutRecord.{name}")
            value = np.array(value, dtype=dtype)
            if value.shape != shape:
                raise ValueError(f"RolloutRecord.{name} must have shape {shape}, got {value.shape}")
            arrays[name] = value
        for track, mask in (("states", "valid"), ("reference", "reference_valid")):
            values, observed = arrays[track], arrays[mask]
            if not np.all(np.isfinite(values[observed])):
                raise ValueError(f"RolloutRecord.{track} has NaN or inf at {mask} steps")
            values[~observed] = 0.0
        if not (np.all(arrays["length"] >= 0) and np.all(arrays["width"] >= 0)):
            raise ValueError("RolloutRecord.length and width must be >= 0 m")
        for name, kind in (("dt", numbers.Real), ("num_context", numbers.Integral),
                           ("ego_index", numbers.Integral)):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, kind):
                expected = "a number" if kind is numbers.Real else "an int"
                raise ValueError(f"RolloutRecord.{name} must be {expected}, got {value!r}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"RolloutRecord.dt must be a finite time step > 0 s, got {self.dt}")
        if not 0 <= self.num_context < num_steps:
            raise ValueError(
                f"RolloutRecord.num_context must be in [0, {num_steps}), got {self.num_context}"
            )
        if not (self.ego_index == NO_EGO or 0 <= self.ego_index < num_agents):
            raise ValueError(
                f"RolloutRecord.ego_index must be a slot in [0, {num_agents}) or {NO_EGO}, "
                f"got {self.ego_index}"
            )
        if self.drivable_map is not None and not isinstance(self.drivable_map, DrivableMap):
            raise ValueError("RolloutRecord.drivable_map must be a DrivableMap or None")
        for name, value in arrays.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "dt", float(plain_number(self.dt)))  # np.float32(0.1) -> 0.1
        object.__setattr__(self, "ego_index", int(self.ego_index))
        object.__setattr__(self, "num_context", int(self.num_context))

    @property
    def num_agents(self) -> int:
        """Number of agent slots A."""
        return self.states.shape[0]

    @property
    def num_steps(self) -> int:
        """Number of steps T, context included."""
        return self.states.shape[1]

    @property
    def scored_steps(self) -> np.ndarray:
        """(T,) bool, the steps metrics count: ``t >= num_context``."""
        return np.arange(self.num_steps) >= self.num_context

    def scored(self, valid: np.ndarray | None = None) -> np.ndarray:
        """(A, T) bool: ``valid`` (default ``self.valid``) at scored steps of evaluated agents."""
        valid = self.valid if valid is None else valid
        return valid & self.scored_steps[None, :] & self.evaluated[:, None]

    @classmethod
    def from_scenario(
        cls,
        scenario: Scenario,
        states: np.ndarray | Sequence[np.ndarray],
        valid: np.ndarray | Sequence[np.ndarray] | None = None,
        rows: np.ndarray | None = None,
        *,
        history: int = 2,
        evaluated: np.ndarray | None = None,
        scene_id: str | None = None,
    ) -> RolloutRecord:
        """A record of an env episode started at ``scenario``'s current step.

        The reference is the scenario's log of ``rows``; its history is prepended to
        both tracks as context, and the reset state is context too, so
        ``num_context = history + 1`` and the scored steps are the simulated ones.

        Args:
            scenario: the scene the episode was reset from.
            states: (A, T, 4), or T per-step (A, 4) arrays (e.g. ``SceneState.current``
                after reset and after each env step): ``states[:, 0]`` is the state at
                the scenario's current step, ``states[:, k]`` the state ``k`` steps later.
            valid: (A, T) bool, T per-step (A,) arrays (e.g. ``SceneState.present``),
                or one (A,) array for every step, of bools (other dtypes are refused);
                default: the slots that hold a row.
            rows: (n,) scenario row of slots 0..n-1, n <= A, -1 for an empty slot (as
                :func:`riskflow_env.simulator.reset` fills them, or the harness's
                ``scenario_rows``); default :func:`riskflow_env.simulator.select_agents`
                with ``A`` slots.
            history: logged states before the current step to prepend (>= 0). Two make
                WOSAC's central-difference accelerations defined at the first
                simulated step; steps before the log starts are invalid.
            evaluated: (A,) bool, the agents the per-agent metrics score; default all.
            scene_id: default ``scenario.name``.
        """
        from riskflow_env.simulator import select_agents  # the env's own slot order

        simulated = _stack(states, "states").astype(np.float64)
        if simulated.ndim != 3 or simulated.shape[2] != STATE_DIM:
            raise ValueError(f"states must have shape (A, T, {STATE_DIM}), got {simulated.shape}")
        num_agents, num_steps = simulated.shape[:2]
        rows = select_agents(scenario, num_agents) if rows is None else np.asarray(rows, int)
        if rows.ndim != 1 or rows.size > num_agents:
            raise ValueError(f"rows must be (n,) with n <= {num_agents} slots, got {rows.shape}")
        slots, rows = np.flatnonzero(rows >= 0), rows[rows >= 0]  # filled slots, their rows
        if valid is None:
            valid = np.zeros(num_agents, dtype=bool)
            valid[slots] = True
        valid = _bools(_stack(valid, "valid"), "valid")
        if valid.shape == (num_agents,):
            valid = np.repeat(valid[:, None], num_steps, axis=1)
        if history < 0:
            raise ValueError(f"history must be >= 0 steps, got {history}")

        now = scenario.current_index
        total = history + num_steps
        log = np.zeros((num_agents, total, STATE_DIM))
        log_valid = np.zeros((num_agents, total), dtype=bool)
        first = now - history  # scenario step of record step 0
        lo, hi = max(first, 0), min(first + total, scenario.states.shape[1])
        span = slice(lo - first, hi - first)
        log[slots, span] = scenario.states[rows, lo:hi]
        log_valid[slots, span] = scenario.valid[rows, lo:hi]

        track = np.concatenate([log[:, :history], simulated], axis=1)
        track_valid = np.concatenate([log_valid[:, :history], valid], axis=1)
        length, width = np.ones(num_agents), np.ones(num_agents)
        length[slots], width[slots] = scenario.length[rows], scenario.width[rows]
        ego = slots[rows == scenario.ego_index]
        return cls(
            states=track,
            valid=track_valid,
            length=length,
            width=width,
            reference=log,
            reference_valid=log_valid,
            dt=scenario.dt,
            ego_index=int(ego[0]) if ego.size else NO_EGO,
            drivable_map=scenario.map,
            evaluated=evaluated,
            num_context=history + 1,
            scene_id=scenario.name if scene_id is None else scene_id,
        )
