"""``SceneState``: the whole simulator state as one frozen dataclass of arrays.

Every array has the agent slot as its leading dimension ``A`` (slot 0 is the ego).
The env never mutates a state; :func:`riskflow_env.simulator.step` returns a new one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from riskflow_env.dynamics import STATE_DIM

HISTORY_STEPS = 31  # states kept per agent, the current one included (3.0 s at 10 Hz)


@dataclass(frozen=True)
class SceneState:
    """Simulator state of one scene.

    Attributes:
        history: (A, H, 4) float64, the last H states (x [m], y [m], v [m/s], psi [rad]);
            ``history[:, -1]`` is the current state.
        history_valid: (A, H) bool, whether each history state was observed.
        length: (A,) float64 vehicle length [m].
        width: (A,) float64 vehicle width [m].
        present: (A,) bool, the slot holds a vehicle in this scene.
        active: (A,) bool, the vehicle is still controlled (present and not done). An
            inactive present vehicle stands still where it stopped: it stays an obstacle.
        last_action: (A, 2) float64, the action applied at the last step
            (accel [m/s^2], yaw rate [rad/s]), zeros at reset.
        step: number of env steps taken since reset.
    """

    history: np.ndarray
    history_valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    present: np.ndarray
    active: np.ndarray
    last_action: np.ndarray
    step: int = 0

    def __post_init__(self) -> None:
        num_agents = self.history.shape[0]
        expected = {
            "history": (num_agents, self.history.shape[1], STATE_DIM),
            "history_valid": (num_agents, self.history.shape[1]),
            "length": (num_agents,),
            "width": (num_agents,),
            "present": (num_agents,),
            "active": (num_agents,),
            "last_action": (num_agents, 2),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if not isinstance(value, np.ndarray) or value.shape != shape:
                got = getattr(value, "shape", type(value).__name__)
                raise ValueError(f"SceneState.{name} must have shape {shape}, got {got}")
        if np.any(self.active & ~self.present):
            raise ValueError("SceneState.active must be False wherever present is False")

    @property
    def num_agents(self) -> int:
        """Number of agent slots A."""
        return self.history.shape[0]

    @property
    def current(self) -> np.ndarray:
        """(A, 4) current states."""
        return self.history[:, -1]

    def replace(self, **changes) -> SceneState:
        """A copy with ``changes`` applied (the state itself is never mutated)."""
        return dataclasses.replace(self, **changes)
