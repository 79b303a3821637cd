"""Batched stepping: B scenes x A agents per call, through the env's own transition.

The PettingZoo env steps one scene and builds per-agent dicts; for rollouts of many
scenes at once (data generation, evaluation sweeps, RL with vectorised scenes) this
module steps a whole batch with one call of :func:`riskflow_env.simulator.transition`
over a :class:`~riskflow_env.state.SceneState` with a leading scene dimension: the same
code as the env, so a batch gives each scene's observations and rewards bit for bit.

Conventions and limits:

* All scenes of a batch share one :class:`~riskflow_env.maps.DrivableMap` (e.g. many
  traffic draws on the same road network); batch different maps separately.
* The batch keeps the current state only (a history of one step): policies that need
  the history use the env or keep it themselves.
* Scenes step in lockstep (one ``step`` counter); done agents stand still as obstacles
  (as in the env) and resetting finished scenes is the caller's choice.
* Arrays are numpy (float64, as in the env) or, after :meth:`SceneState.convert`, torch
  tensors on any device (the map's rasters are copied to the device once).
"""

from __future__ import annotations

from collections.abc import Sequence

from riskflow_env import simulator
from riskflow_env._array import Array, namespace
from riskflow_env.config import EnvConfig
from riskflow_env.maps import DrivableMap
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.simulator import Transition
from riskflow_env.state import SceneState


def reset_batch(scenarios: Sequence[Scenario], max_agents: int) -> SceneState:
    """Initial batch state of ``scenarios`` (they must share one map), slots filled as in
    :func:`riskflow_env.simulator.reset`; ``history`` (B, A, 1, 4)."""
    if not scenarios:
        raise ValueError("reset_batch needs at least one Scenario")
    if any(scenario.map is not scenarios[0].map for scenario in scenarios):
        raise ValueError(
            "reset_batch: all scenarios of a batch must share one DrivableMap (the same "
            "object); batch scenes of different maps separately"
        )
    states = [simulator.reset(scenario, max_agents) for scenario in scenarios]
    return SceneState.stack(states, history_steps=1)


def step_batch(
    state: SceneState,
    actions: Array,
    drivable_map: DrivableMap,
    config: EnvConfig,
    observations: bool = True,
) -> tuple[SceneState, Transition]:
    """Advance every scene of the batch by ``config.dynamics.dt``
    (:func:`riskflow_env.simulator.transition`).

    Args:
        state: the batch (numpy or torch, see :meth:`SceneState.convert`).
        actions: (B, A, 2) (accel [m/s^2], yaw rate [rad/s]), same backend; rows of
            inactive slots are ignored; clipped to the dynamics bounds.
        drivable_map: the map shared by the scenes.
        config: the env configuration (dynamics, observation, reward, termination).
        observations: compute the observations (skip them for pure simulation).

    Returns:
        The next state (agents done at this step made inactive) and the step's report.
    """
    if len(state.batch_shape) != 1:
        raise ValueError(f"state must be a batch (B, A, ...), got batch shape {state.batch_shape}")
    expected = (*state.current.shape[:-1], 2)
    if tuple(actions.shape) != expected:
        raise ValueError(f"actions must have shape (B, A, 2) = {expected}, got {actions.shape}")
    if not namespace(actions).isdtype(actions.dtype, ("real floating", "integral")):
        raise ValueError(f"actions must hold real numbers, got dtype {actions.dtype}")
    return simulator.transition(state, actions, drivable_map, config, observations=observations)
