"""Pure simulator functions: ``reset(scenario) -> SceneState`` and ``step(state, actions)``.

The env (:mod:`riskflow_env.env`) is a thin stateful shell over these; they can be used
directly, e.g. to roll many scenes without the PettingZoo plumbing.
"""

from __future__ import annotations

import numpy as np

from riskflow_env import dynamics
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import HISTORY_STEPS, SceneState


def select_agents(scenario: Scenario, max_agents: int) -> np.ndarray:
    """Rows of ``scenario`` that get a slot: the ego first, then the other agents valid at
    the current step, nearest to the ego first, at most ``max_agents`` in all.

    Returns:
        (n,) int indices into ``scenario.states``.
    """
    now = scenario.current_index
    ego = scenario.ego_index
    others = np.flatnonzero(scenario.valid[:, now])
    others = others[others != ego]
    distance = np.linalg.norm(
        scenario.states[others, now, :2] - scenario.states[ego, now, :2], axis=-1
    )
    others = others[np.argsort(distance, kind="stable")]
    return np.concatenate([[ego], others[: max_agents - 1]]).astype(int)


def reset(scenario: Scenario, max_agents: int, rows: np.ndarray | None = None) -> SceneState:
    """Initial state of an episode that starts at ``scenario``'s current step.

    Args:
        scenario: the scene to start from.
        max_agents: number of slots A; slot 0 is the ego, slots 1..n-1 the selected
            agents, the rest are empty.
        rows: (n,) scenario rows to put in the slots, ego first; default
            :func:`select_agents`.
    """
    if rows is None:
        rows = select_agents(scenario, max_agents)
    count = rows.size
    now = scenario.current_index
    start = max(0, now + 1 - HISTORY_STEPS)
    kept = now + 1 - start  # history states available in the scenario (<= HISTORY_STEPS)

    history = np.zeros((max_agents, HISTORY_STEPS, 4))
    history_valid = np.zeros((max_agents, HISTORY_STEPS), dtype=bool)
    history[:count, HISTORY_STEPS - kept :] = scenario.states[rows, start : now + 1]
    history_valid[:count, HISTORY_STEPS - kept :] = scenario.valid[rows, start : now + 1]
    history[:count, : HISTORY_STEPS - kept] = history[:count, HISTORY_STEPS - kept, None]
    history[~history_valid] = (
        np.where(history_valid[:, -1, None], history[:, -1], 0.0)
        .repeat(HISTORY_STEPS, axis=0)
        .reshape(max_agents, HISTORY_STEPS, 4)[~history_valid]
    )

    length = np.ones(max_agents)
    width = np.ones(max_agents)
    length[:count] = scenario.length[rows]
    width[:count] = scenario.width[rows]
    present = np.zeros(max_agents, dtype=bool)
    present[:count] = True
    return SceneState(
        history=history,
        history_valid=history_valid,
        length=length,
        width=width,
        present=present,
        active=present.copy(),
        last_action=np.zeros((max_agents, 2)),
        step=0,
    )


def step(state: SceneState, actions: np.ndarray, config: DynamicsConfig) -> SceneState:
    """Advance every agent by one time step.

    Active agents follow the unicycle model under ``actions``; present but inactive
    agents (done) stand still where they are; empty slots stay empty.

    Args:
        state: the current scene state.
        actions: (A, 2) float (accel [m/s^2], yaw rate [rad/s]); rows of inactive slots
            are ignored. Actions are clipped to the dynamics bounds by the model.
        config: dynamics bounds and time step.
    """
    current = state.current
    active = state.active[:, None]
    applied = np.where(active, dynamics.clip_actions(actions, config), 0.0)
    moved = dynamics.step(current, applied, config)
    stopped = current.copy()
    stopped[:, SPEED] = 0.0
    new = np.where(active, moved, np.where(state.present[:, None], stopped, current))
    history = np.concatenate([state.history[:, 1:], new[:, None]], axis=1)
    history_valid = np.concatenate([state.history_valid[:, 1:], state.present[:, None]], axis=1)
    return state.replace(
        history=history, history_valid=history_valid, last_action=applied, step=state.step + 1
    )
