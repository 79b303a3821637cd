"""Pure simulator functions: ``reset(scenario) -> SceneState`` and
``transition(state, actions) -> (state, Transition)``, the one step sequence of the env
and of batched stepping:

1. :func:`step`: the unicycle moves the live agents (:func:`advance`), the history rolls;
2. vehicles whose log has ended leave, when asked (``log_end``);
3. :func:`evaluate`: risk features, collision / off-road events, observations, rewards;
4. :func:`episode_end`: which live agents terminate or are truncated; they become
   inactive (they stay in the scene as standing obstacles).

The env (:mod:`riskflow_env.env`) is a thin stateful shell over these;
:mod:`riskflow_env.batched` runs them over a batch of scenes. Every function takes a
:class:`SceneState` with leading dims ``(..., A)``, as numpy arrays or torch tensors.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, partial
from typing import Any

import numpy as np

from riskflow_env import compiled, dynamics
from riskflow_env._array import Array, asarray_like, namespace
from riskflow_env.config import DynamicsConfig, EnvConfig
from riskflow_env.dynamics import SPEED, STATE_DIM, YAW
from riskflow_env.events import FrameEvents, detect
from riskflow_env.geometry import NUM_FOOTPRINT_POINTS, footprint_points
from riskflow_env.maps import DrivableMap
from riskflow_env.observations import observe, sample_points
from riskflow_env.rewards import reward_terms
from riskflow_env.risk import pair_risk, pairwise_features
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.state import HISTORY_STEPS, SceneState

RISK_INDEX = -1  # the risk weight is the last pair feature
_SPEED_COLUMN = np.arange(STATE_DIM) == SPEED


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


def log_end_steps(scenario: Scenario, rows: np.ndarray, max_agents: int) -> np.ndarray:
    """(A,) int: per slot, the last episode step at which its logged reference is valid.

    Step k of an episode is scenario step ``current_index + k``. The ego (slot 0) and
    empty slots get a step no episode reaches; an agent whose log has no valid step
    after the current one gets 0.

    Args:
        scenario: the scene the episode started from.
        rows: (n,) scenario rows in the slots, ego first (:func:`select_agents`).
        max_agents: number of slots A.
    """
    never = np.iinfo(np.int64).max
    ends = np.full(max_agents, never, dtype=np.int64)
    future = scenario.valid[rows, scenario.current_index :]  # (n, F), step 0 = now
    last = future.shape[1] - 1 - np.argmax(future[:, ::-1], axis=1)
    ends[: rows.size] = np.where(future.any(axis=1), last, 0)
    ends[0] = never
    return ends


def advance(
    current: Array, present: Array, active: Array, actions: Array, config: DynamicsConfig
) -> tuple[Array, Array]:
    """Next states of all slots: active agents follow the unicycle model under
    ``actions``; present but inactive agents (done) stand still where they are (speed 0);
    empty slots keep their state. A vehicle done at step k (e.g. at a collision) thus
    keeps its pose of step k, and the speed it had then (the impact speed the event log
    reports), and is at rest from step k + 1 on.

    Args:
        current: (..., A, 4) states (x [m], y [m], v [m/s], psi [rad]).
        present: (..., A) bool, the slot holds a vehicle.
        active: (..., A) bool, the vehicle is still controlled.
        actions: (..., A, 2) (accel [m/s^2], yaw rate [rad/s]); rows of inactive slots
            are ignored. Actions are clipped to the dynamics bounds by the model.
        config: dynamics bounds and time step.

    Returns:
        new: (..., A, 4) the states ``dt`` later.
        applied: (..., A, 2) the actions applied (clipped; zeros for inactive slots).

    numpy float64 states run compiled where numba is installed
    (:mod:`riskflow_env.compiled`; equal to this reference to float rounding).
    """
    if compiled.accepts_advance(current, present, active, actions):
        return compiled.advance(current, present, active, actions, config)
    xp = namespace(current, actions)
    live = active[..., None]
    applied = xp.where(live, dynamics.clip_actions(actions, config), 0.0)
    moved = dynamics.step(current, applied, config, clip=False)  # clipped once, above
    halt = present[..., None] & asarray_like(_SPEED_COLUMN, present)  # zero a done car's speed
    return xp.where(live, moved, xp.where(halt, 0.0, current)), applied


def step(state: SceneState, actions: np.ndarray, config: DynamicsConfig) -> SceneState:
    """Advance every agent by one time step (see :func:`advance`).

    Args:
        state: the current scene state (leading dims ``(..., A)``).
        actions: (..., A, 2) float (accel [m/s^2], yaw rate [rad/s]); rows of inactive slots
            are ignored. Actions are clipped to the dynamics bounds by the model.
        config: dynamics bounds and time step.
    """
    new, applied = advance(state.current, state.present, state.active, actions, config)
    xp = namespace(new)
    history = xp.concat([state.history[..., 1:, :], new[..., None, :]], axis=-2)
    history_valid = xp.concat([state.history_valid[..., 1:], state.present[..., None]], axis=-1)
    return state.replace(
        history=history, history_valid=history_valid, last_action=applied, step=state.step + 1
    )


@dataclass(frozen=True)
class Evaluation:
    """Everything the env reports about one state (leading dims ``(..., A)``).

    Attributes:
        features: :attr:`pair_features`, or a function of no argument that computes
            them (the compiled step, whose observations need only each agent's nearest
            pairs: computed on first access).
        pair_mask: (..., A, A) bool, observed pairs.
        events: collisions and off-road flags.
        observations: (..., A, D) float32, or None when not requested.
        reward_terms: term name -> (..., A) weighted reward term.
        reward: (..., A) the sum of the terms.
    """

    features: Array | Callable[[], Array] | None
    pair_mask: Array
    events: FrameEvents
    observations: Array | None
    reward_terms: dict[str, Array]
    reward: Array

    @cached_property
    def pair_features(self) -> Array | None:
        """(..., A, A, 8) from :func:`riskflow_env.risk.pairwise_features`, or None when
        the observations were not requested (only the risk channel is computed then, for
        the rewards)."""
        return self.features() if callable(self.features) else self.features


def _pair_features(state: Any) -> Array:
    """:func:`riskflow_env.risk.pairwise_features` of ``state``'s present vehicles."""
    return pairwise_features(state.current, state.length, state.width, state.present)[0]


def evaluate(
    state: Any, drivable_map: DrivableMap, config: EnvConfig, observations: bool = True
) -> Evaluation:
    """Risk features, events, observations and rewards of ``state``.

    Args:
        state: a :class:`SceneState` (leading dims ``(..., A)``: a batch of scenes
            shares ``drivable_map``).
        drivable_map: the map.
        config: observation, reward and dynamics settings.
        observations: compute the observations (skip them for pure simulation).

    numpy float64 scenes run compiled where numba is installed
    (:mod:`riskflow_env.compiled`; equal to this reference to float rounding).
    """
    if compiled.accepts_evaluate(state, drivable_map):
        features = partial(_pair_features, state) if observations else None
        return Evaluation(features, *compiled.evaluate(state, drivable_map, config, observations))
    current = state.current
    xp = namespace(current)
    if observations:
        features, mask = pairwise_features(current, state.length, state.width, state.present)
        risk = features[..., RISK_INDEX]
    else:  # the rewards need the risk channel only
        features = None
        risk, mask = pair_risk(current, state.length, state.width, state.present)
    # One map lookup for the footprints (events) and the SDF samples (observations).
    points = footprint_points(current[..., :2], current[..., YAW], state.length, state.width)
    if observations:
        points = xp.concat([points, sample_points(current, config.observation)], axis=-2)
    sdf = drivable_map.sdf_at(points)
    events = detect(state, drivable_map, footprint_sdf=sdf[..., :NUM_FOOTPRINT_POINTS])
    rows = None
    if observations:
        sdf = sdf[..., NUM_FOOTPRINT_POINTS:]
        rows = observe(state, features, mask, drivable_map, config.observation, sdf=sdf)
    terms = reward_terms(state, events, risk, config.reward, config.dynamics)
    return Evaluation(features, mask, events, rows, terms, sum(terms.values()))


def episode_end(
    active: Array,
    events: FrameEvents,
    terminate_on_collision: Array,
    terminate_on_offroad: Array,
    time_up: bool | Array,
    end_with_ego: bool,
) -> tuple[Array, Array]:
    """Which live agents terminate or are truncated at this step.

    Args:
        active: (..., A) bool, agents live before the step.
        events: the events after the step.
        terminate_on_collision: (A,) bool, agents that terminate when they collide.
        terminate_on_offroad: (A,) bool, agents that terminate when off the road.
        time_up: the episode length is reached (bool, or (..., 1) bool per scene).
        end_with_ego: when the ego (slot 0) is done, truncate every other live agent.

    Returns:
        terminated, truncated: (..., A) bool, disjoint, both within ``active``.
    """
    terminated = active & (
        (events.collided & terminate_on_collision) | (events.offroad & terminate_on_offroad)
    )
    truncated = active & ~terminated & time_up
    if end_with_ego:
        ego_done = (terminated[..., 0] | truncated[..., 0])[..., None]
        truncated = truncated | (ego_done & active & ~terminated)
    return terminated, truncated


@dataclass(frozen=True)
class Transition:
    """What one step reports (the arrays behind the env's per-agent dicts).

    Attributes:
        evaluation: features, events, observations and rewards after the step.
        terminated: (..., A) bool, live agents that terminated at this step.
        truncated: (..., A) bool, live agents truncated at this step (time up, the
            ego's episode ended, or their log ended).
    """

    evaluation: Evaluation
    terminated: Array
    truncated: Array

    @property
    def observations(self) -> Array | None:
        """(..., A, D) float32 (zeros for empty slots), or None if not requested."""
        return self.evaluation.observations

    @property
    def rewards(self) -> Array:
        """(..., A) reward of every slot (meaningful for the live ones)."""
        return self.evaluation.reward

    @property
    def reward_terms(self) -> dict[str, Array]:
        """Term name -> (..., A) weighted reward term."""
        return self.evaluation.reward_terms

    @property
    def events(self) -> FrameEvents:
        """Collisions (..., A, A) and off-road flags (..., A)."""
        return self.evaluation.events


def termination_masks(config: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """(A,) bool slots that terminate on a collision, and on leaving the road."""
    return (
        np.array(config.selects("terminate_on_collision")),
        np.array(config.selects("terminate_on_offroad")),
    )


def transition(
    state: SceneState,
    actions: Array,
    drivable_map: DrivableMap,
    config: EnvConfig,
    *,
    observations: bool = True,
    log_end: Array | None = None,
    masks: tuple[Array, Array] | None = None,
) -> tuple[SceneState, Transition]:
    """Advance ``state`` by ``config.dynamics.dt`` (the module docstring's sequence).

    Args:
        state: one scene or a batch sharing ``drivable_map`` (numpy or torch).
        actions: (..., A, 2) (accel [m/s^2], yaw rate [rad/s]), same backend; rows of
            inactive slots are ignored; clipped to the dynamics bounds.
        drivable_map: the map.
        config: the env configuration (dynamics, observation, reward, termination).
        observations: compute the observations (skip them for pure simulation).
        log_end: (..., A) int, the last step of each vehicle's log: a live vehicle leaves
            the scene (not present, truncated) once ``state.step`` passes it, before this
            step's events are detected (``EnvConfig.leave_when_log_ends``); None: never.
        masks: :func:`termination_masks` of ``config``, precomputed (None: computed).

    Returns:
        The next state (agents done at this step made inactive) and the step's report.
    """
    moved = step(state, actions, config.dynamics)
    live = moved.active
    left = None
    if log_end is not None:
        left = live & (moved.step > log_end)
        moved = moved.replace(present=moved.present & ~left, active=live & ~left)
    evaluation = evaluate(moved, drivable_map, config, observations=observations)
    collision, offroad = termination_masks(config) if masks is None else masks
    terminated, truncated = episode_end(
        live,
        evaluation.events,
        asarray_like(collision, live),
        asarray_like(offroad, live),
        moved.step >= config.episode_steps,
        config.end_with_ego,
    )
    if left is not None:
        truncated = truncated | (left & ~terminated)
    done = terminated | truncated
    return moved.replace(active=live & ~done), Transition(evaluation, terminated, truncated)
