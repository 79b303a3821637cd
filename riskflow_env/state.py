"""``SceneState``: the whole simulator state as one frozen dataclass of arrays.

Every array has the agent slot ``A`` (slot 0 is the ego) after optional leading batch
dimensions: the env holds one scene (``history`` (A, H, 4)), batched stepping B scenes
(``history`` (B, A, H, 4), :meth:`SceneState.stack`), as numpy arrays or, after
:meth:`SceneState.convert`, torch tensors. Nothing mutates a state;
:func:`riskflow_env.simulator.transition` returns a new one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env._array import Array
from riskflow_env.dynamics import STATE_DIM

HISTORY_STEPS = 31  # states kept per agent, the current one included (3.0 s at 10 Hz)


@dataclass(frozen=True)
class SceneState:
    """Simulator state of one scene, or of a batch of scenes (leading dims ``...``).

    Attributes:
        history: (..., A, H, 4) float64, the last H states (x [m], y [m], v [m/s],
            psi [rad]); ``history[..., -1, :]`` is the current state.
        history_valid: (..., A, H) bool, whether each history state was observed.
        length: (..., A) float64 vehicle length [m].
        width: (..., A) float64 vehicle width [m].
        present: (..., A) bool, the slot holds a vehicle in this scene.
        active: (..., A) bool, the vehicle is still controlled (present and not done). An
            inactive present vehicle stands still where it stopped: it stays an obstacle.
        last_action: (..., A, 2) float64, the action applied at the last step
            (accel [m/s^2], yaw rate [rad/s]) clipped to the action bounds, zeros at reset
            and for inactive slots. It is the command, not the motion: the speed bounds
            and the turning radius act inside the dynamics, so a car at rest that is told
            to brake keeps that braking here while its speed stays 0.
        step: number of env steps taken since reset: an int (the scenes of a batch step in
            lockstep), or a (B, 1) int array, one count per scene (scenes that reset on
            their own, :class:`~riskflow_env.scene_batch.SceneBatch`).
    """

    history: Array
    history_valid: Array
    length: Array
    width: Array
    present: Array
    active: Array
    last_action: Array
    step: int | np.ndarray = 0

    def __post_init__(self) -> None:
        shape = tuple(getattr(self.history, "shape", ()))
        if len(shape) < 3 or shape[-1] != STATE_DIM:
            got = shape if hasattr(self.history, "shape") else type(self.history).__name__
            raise ValueError(f"SceneState.history must have shape (..., A, H, 4), got {got}")
        lead, steps = shape[:-2], shape[-2]
        expected = {
            "history_valid": (*lead, steps),
            "length": lead,
            "width": lead,
            "present": lead,
            "active": lead,
            "last_action": (*lead, 2),
        }
        for name, want in expected.items():
            value = getattr(self, name)
            got = getattr(value, "shape", None)
            if got is None or tuple(got) != want:
                raise ValueError(
                    f"SceneState.{name} must have shape {want}, "
                    f"got {type(value).__name__ if got is None else tuple(got)}"
                )
        if bool((self.active & ~self.present).any()):
            raise ValueError("SceneState.active must be False wherever present is False")

    @property
    def num_agents(self) -> int:
        """Number of agent slots A."""
        return self.history.shape[-3]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading dims before the agent slot: ``()`` for one scene, ``(B,)`` for a batch."""
        return tuple(self.history.shape[:-3])

    @property
    def current(self) -> Array:
        """(..., A, 4) current states."""
        return self.history[..., -1, :]

    @classmethod
    def stack(cls, states: Sequence[SceneState], history_steps: int | None = None) -> SceneState:
        """Single-scene states (same slot count, same step) stacked into a batch (numpy).

        Args:
            states: the scenes.
            history_steps: keep the last this many history states (None: all); batched
                stepping keeps 1, the current state.
        """
        if not states:
            raise ValueError("SceneState.stack needs at least one SceneState")
        if len({state.num_agents for state in states}) != 1:
            raise ValueError("SceneState.stack: every SceneState must have the same slot count")
        if len({state.step for state in states}) != 1:
            raise ValueError("SceneState.stack: every SceneState must be at the same step")
        keep = slice(None) if history_steps is None else slice(-history_steps, None)
        history = np.stack([state.history[..., keep, :] for state in states])
        valid = np.stack([state.history_valid[..., keep] for state in states])
        arrays = {
            name: np.stack([getattr(state, name) for state in states])
            for name in ("length", "width", "present", "active", "last_action")
        }
        return cls(history=history, history_valid=valid, step=states[0].step, **arrays)

    def convert(self, convert: Callable[[Array], Array]) -> SceneState:
        """The same state with every array passed through ``convert``, e.g.
        ``lambda a: torch.as_tensor(a, device="cuda")``."""
        arrays = {
            field.name: convert(getattr(self, field.name))
            for field in dataclasses.fields(self)
            if field.name != "step"
        }
        return dataclasses.replace(self, **arrays)

    def replace(self, **changes) -> SceneState:
        """A copy with ``changes`` applied (the state itself is never mutated)."""
        return dataclasses.replace(self, **changes)
