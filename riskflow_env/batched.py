"""Batched stepping: B scenes x A agents per call, through the env's own pure functions.

The PettingZoo env steps one scene and builds per-agent dicts; for rollouts of many
scenes at once (data generation, evaluation sweeps, RL with vectorised scenes) this
module steps a whole batch with one call of :func:`riskflow_env.simulator.advance`,
:func:`~riskflow_env.simulator.evaluate` and :func:`~riskflow_env.simulator.episode_end`
over a leading scene dimension: the same code as the env, so a batch of one scene gives
the env's observations and rewards bit for bit.

Conventions and limits:

* All scenes of a batch share one :class:`~riskflow_env.maps.DrivableMap` (e.g. many
  traffic draws on the same road network); batch different maps separately.
* The batch keeps the current state only (no 31-step history): policies that need the
  history use the env or keep it themselves.
* Scenes step in lockstep (one ``step`` counter); done agents stand still as obstacles
  (as in the env) and resetting finished scenes is the caller's choice.
* Arrays are numpy (float64, as in the env) or, after :meth:`BatchState.convert`, torch
  tensors on any device (the map's rasters are copied to the device once).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env import simulator
from riskflow_env._array import Array, asarray_like
from riskflow_env.config import EnvConfig
from riskflow_env.events import FrameEvents
from riskflow_env.maps import DrivableMap
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import SceneState


@dataclass(frozen=True)
class BatchState:
    """State of B scenes with A agent slots each (slot 0 of every scene is its ego).

    Attributes:
        current: (B, A, 4) states (x [m], y [m], v [m/s], psi [rad]).
        last_action: (B, A, 2) actions applied at the last step (accel [m/s^2], yaw rate
            [rad/s]); zeros at reset.
        length: (B, A) vehicle lengths [m].
        width: (B, A) vehicle widths [m].
        present: (B, A) bool, the slot holds a vehicle.
        active: (B, A) bool, the vehicle is still controlled (present and not done).
        step: steps taken since reset (the same for every scene).
    """

    current: Array
    last_action: Array
    length: Array
    width: Array
    present: Array
    active: Array
    step: int = 0

    def __post_init__(self) -> None:
        batch = tuple(self.current.shape[:-1])
        expected = {
            "current": (*batch, 4),
            "last_action": (*batch, 2),
            "length": batch,
            "width": batch,
            "present": batch,
            "active": batch,
        }
        if len(batch) != 2:
            raise ValueError(f"BatchState.current must have shape (B, A, 4), got {batch + (4,)}")
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"BatchState.{name} must have shape {shape}, got {got}")

    @property
    def num_scenes(self) -> int:
        """Number of scenes B."""
        return self.current.shape[0]

    @property
    def num_agents(self) -> int:
        """Number of agent slots A per scene."""
        return self.current.shape[1]

    @classmethod
    def stack(cls, states: Sequence[SceneState]) -> BatchState:
        """Stack single-scene states (same slot count) into a batch (numpy)."""
        if not states:
            raise ValueError("BatchState.stack needs at least one SceneState")
        if len({state.num_agents for state in states}) != 1:
            raise ValueError("BatchState.stack: every SceneState must have the same slot count")
        if len({state.step for state in states}) != 1:
            raise ValueError("BatchState.stack: every SceneState must be at the same step")

        def stacked(name: str) -> np.ndarray:
            return np.stack([getattr(state, name) for state in states])

        return cls(
            current=np.stack([state.current for state in states]),
            last_action=stacked("last_action"),
            length=stacked("length"),
            width=stacked("width"),
            present=stacked("present"),
            active=stacked("active"),
            step=states[0].step,
        )

    def convert(self, convert: Callable[[Array], Array]) -> BatchState:
        """The same state with every array passed through ``convert``, e.g.
        ``lambda a: torch.as_tensor(a, device="cuda")``."""
        arrays = {
            field.name: convert(getattr(self, field.name))
            for field in dataclasses.fields(self)
            if field.name != "step"
        }
        return dataclasses.replace(self, **arrays)


@dataclass(frozen=True)
class BatchStep:
    """What one batched step reports (the arrays behind the env's per-agent dicts).

    Attributes:
        observations: (B, A, D) float32 (zeros for empty slots), or None if not requested.
        rewards: (B, A) reward of every slot (meaningful for the live ones).
        reward_terms: term name -> (B, A).
        terminated: (B, A) bool, live agents that terminated at this step.
        truncated: (B, A) bool, live agents truncated at this step.
        events: collisions (B, A, A) and off-road flags (B, A).
    """

    observations: Array | None
    rewards: Array
    reward_terms: dict[str, Array]
    terminated: Array
    truncated: Array
    events: FrameEvents


def reset_batch(scenarios: Sequence[Scenario], max_agents: int) -> BatchState:
    """Initial batch state of ``scenarios`` (they must share one map), slots filled as in
    :func:`riskflow_env.simulator.reset`."""
    if not scenarios:
        raise ValueError("reset_batch needs at least one Scenario")
    if any(scenario.map is not scenarios[0].map for scenario in scenarios):
        raise ValueError(
            "reset_batch: all scenarios of a batch must share one DrivableMap (the same "
            "object); batch scenes of different maps separately"
        )
    return BatchState.stack([simulator.reset(scenario, max_agents) for scenario in scenarios])


def step_batch(
    state: BatchState,
    actions: Array,
    drivable_map: DrivableMap,
    config: EnvConfig,
    observations: bool = True,
) -> tuple[BatchState, BatchStep]:
    """Advance every scene of the batch by ``config.dynamics.dt``.

    Args:
        state: the batch (numpy or torch, see :meth:`BatchState.convert`).
        actions: (B, A, 2) (accel [m/s^2], yaw rate [rad/s]), same backend; rows of
            inactive slots are ignored; clipped to the dynamics bounds.
        drivable_map: the map shared by the scenes.
        config: the env configuration (dynamics, observation, reward, termination).
        observations: compute the observations (skip them for pure simulation).

    Returns:
        The next state (agents done at this step made inactive) and the step's report.
    """
    expected = (*state.current.shape[:-1], 2)
    if tuple(actions.shape) != expected:
        raise ValueError(f"actions must have shape (B, A, 2) = {expected}, got {actions.shape}")
    current, applied = simulator.advance(
        state.current, state.present, state.active, actions, config.dynamics
    )
    moved = dataclasses.replace(state, current=current, last_action=applied, step=state.step + 1)
    evaluation = simulator.evaluate(moved, drivable_map, config, observations=observations)
    terminated, truncated = simulator.episode_end(
        state.active,
        evaluation.events,
        asarray_like(np.array(config.selects("terminate_on_collision")), state.active),
        asarray_like(np.array(config.selects("terminate_on_offroad")), state.active),
        moved.step >= config.episode_steps,
        config.end_with_ego,
    )
    moved = dataclasses.replace(moved, active=state.active & ~(terminated | truncated))
    report = BatchStep(
        observations=evaluation.observations,
        rewards=evaluation.reward,
        reward_terms=evaluation.reward_terms,
        terminated=terminated,
        truncated=truncated,
        events=evaluation.events,
    )
    return moved, report
