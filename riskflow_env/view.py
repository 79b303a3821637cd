"""``SceneView``, the read-only window through which policies see a scene, and
``ScenePolicy``, the protocol of what drives vehicles through it.

Policies never touch env internals: they get a frozen view whose arrays are read-only
(writing to them raises), built from the env's current state. Every traffic model (the
env's own agents in :mod:`riskflow_env.agents`, the learned adversaries in ``policies``)
implements :class:`ScenePolicy`, so one harness drives and compares them all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from riskflow_env.maps import DrivableMap
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import SceneState


def _read_only(array: np.ndarray) -> np.ndarray:
    view = array.view()
    view.flags.writeable = False
    return view


@dataclass(frozen=True)
class SceneView:
    """What a scene policy may see.

    Attributes:
        history: (A, H, 4) last H states (x [m], y [m], v [m/s], psi [rad]), current last.
        history_valid: (A, H) bool.
        length: (A,) [m].
        width: (A,) [m].
        present: (A,) bool, the slot holds a vehicle.
        active: (A,) bool, the vehicle is still controlled (its agent is live).
        agent_names: (A,) slot names; slot 0 is ``"ego"``.
        map: the drivable map (lanes included).
        step: env steps since reset.
        dt: time step [s].
        scenario: the scenario the episode started from (reference future included).
        scenario_rows: (A,) row of each slot in ``scenario.states`` (-1 for empty slots).
    """

    history: np.ndarray
    history_valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    present: np.ndarray
    active: np.ndarray
    agent_names: tuple[str, ...]
    map: DrivableMap
    step: int
    dt: float
    scenario: Scenario
    scenario_rows: np.ndarray

    @classmethod
    def from_state(
        cls,
        state: SceneState,
        scenario: Scenario,
        scenario_rows: np.ndarray,
        agent_names: tuple[str, ...],
        dt: float,
    ) -> SceneView:
        """A read-only view of ``state``."""
        return cls(
            history=_read_only(state.history),
            history_valid=_read_only(state.history_valid),
            length=_read_only(state.length),
            width=_read_only(state.width),
            present=_read_only(state.present),
            active=_read_only(state.active),
            agent_names=tuple(agent_names),
            map=scenario.map,
            step=state.step,
            dt=dt,
            scenario=scenario,
            scenario_rows=_read_only(scenario_rows),
        )

    @property
    def current(self) -> np.ndarray:
        """(A, 4) current states."""
        return self.history[:, -1]

    @property
    def num_agents(self) -> int:
        """Number of slots A."""
        return self.history.shape[0]

    def slot(self, agent: str) -> int:
        """Slot index of ``agent``."""
        try:
            return self.agent_names.index(agent)
        except ValueError:
            raise ValueError(f"unknown agent {agent!r}; known: {self.agent_names}") from None

    @property
    def live_agents(self) -> tuple[str, ...]:
        """Names of the active (live) agents."""
        return tuple(self.agent_names[i] for i in np.flatnonzero(self.active))


@runtime_checkable
class ScenePolicy(Protocol):
    """Drives a set of vehicles in a scene.

    ``reset(view)`` is called once at the start of an episode, then ``act(view)`` every
    env step; ``act`` returns ``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for the live
    agents it controls. Policies see only the read-only :class:`SceneView`. A stochastic
    policy may also have ``reseed(seed)``, which ``EgoEnv.reset(seed=...)`` calls.
    """

    def reset(self, view: SceneView) -> None:
        """Prepare for a new episode."""
        ...

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        """Actions of the live agents this policy controls."""
        ...
