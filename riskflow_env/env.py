"""RiskFlow traffic env (``riskflow_v0``): a PettingZoo ``ParallelEnv``.

Vehicles with unicycle dynamics drive on a rasterised drivable-area map. Each step
detects box-box collisions and off-road footprints, computes TTC risk features, and
returns per-agent observations and rewards. The game logic lives in pure functions
(:mod:`~riskflow_env.simulator`, :mod:`~riskflow_env.events`,
:mod:`~riskflow_env.observations`, :mod:`~riskflow_env.rewards`); this class is plumbing.

==================  ==============================================================
Import              ``riskflow_env.parallel_env(...)``
Agents              ``ego``, ``agent_1`` ... ``agent_{max_agents-1}`` (``possible_agents``,
                    fixed); each scene fills a subset, the ego always
Action space        ``Box([accel_min, -yaw_rate_max], [accel_max, yaw_rate_max])``:
                    (acceleration [m/s^2], yaw rate [rad/s]), default
                    [-8, 5] x [-1, 1]; identical for every agent
Observation space   ``Box(low, high, (D,), float32)``, identical for every agent,
                    bounded where a physical bound holds
                    (:func:`~riskflow_env.observations.observation_bounds`);
                    D = 142 by default (layout in :mod:`riskflow_env.observations`)
State space         ``Box(-inf, inf, (9 * max_agents,), float32)``: per slot
                    (present, active, x - x_ego, y - y_ego, v, cos psi, sin psi,
                    length, width)
Time step           0.1 s; episodes truncate after ``episode_steps`` (100 = 10 s)
==================  ==============================================================

Arguments (``parallel_env(config=None, scenarios=None, render_mode=None)``):

* ``config``: :class:`~riskflow_env.config.EnvConfig` (slots, episode length,
  termination rules, action clipping, dynamics bounds, observation and reward settings).
* ``scenarios``: a :class:`~riskflow_env.scenarios.Scenario`, a sequence of them, a
  ``ScenarioSource``, or a folder (:func:`~riskflow_env.scenarios.folders.open_scenes`:
  a ScenarioNet dataset, read lazily, or RiskFlow ``.npz`` scenes); default: the shipped
  naturalistic bank's evaluation split (:func:`~riskflow_env.scenarios.shipped_bank`,
  highway-env IDM/MOBIL recordings on 7 road families). ``reset(seed)`` draws the scene
  from the seeded generator; ``reset(options={"scenario": s})`` starts from a given one.
* ``render_mode``: ``None``, ``"rgb_array"`` or ``"human"``.

Termination: an agent terminates when it collides (or drives off the road) and
``config.terminate_on_collision`` (``terminate_on_offroad``) selects it; a done vehicle
stops where it is and stays on the map as an obstacle. By default both vehicles of every
collision terminate at the first contact, so a pair freezes where it touched and its
boxes never sink further into each other; ``terminate_on_collision="ego"`` lets the other
vehicles drive on through their contacts. With ``end_with_ego`` the whole episode ends
when the ego is done. ``info[agent]["reward_terms"]`` breaks each reward
into its terms.

Version history:

* v0: initial release.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from riskflow_env import events as event_detection
from riskflow_env import simulator
from riskflow_env.action_input import ActionInput
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import YAW
from riskflow_env.maps import DrivableMap
from riskflow_env.observations import observation_bounds
from riskflow_env.rewards import REWARD_TERMS
from riskflow_env.scenarios import Scenario, ScenarioSource, as_source, shipped_bank
from riskflow_env.state import SceneState
from riskflow_env.view import SceneView

STATE_FEATURES = 9


class RiskFlowParallelEnv(ParallelEnv):
    """Multi-agent traffic on a drivable-area raster (see the module docstring)."""

    metadata = {
        "name": "riskflow_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Sequence[Scenario] | Scenario | str | os.PathLike | None = None,
        render_mode: str | None = None,
    ) -> None:
        if config is not None and not isinstance(config, EnvConfig):
            raise TypeError(f"config must be an EnvConfig, got {type(config).__name__}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, "
                f"got {render_mode!r}"
            )
        self.config = config or EnvConfig()
        self.render_mode = render_mode
        if isinstance(scenarios, (str, os.PathLike)):
            from riskflow_env.scenarios.folders import open_scenes  # lazy: loaders of files

            scenarios = open_scenes(scenarios)
        self.source = as_source(scenarios) if scenarios is not None else shipped_bank("eval")
        self.possible_agents = list(self.config.agent_names)
        self._slot = {name: index for index, name in enumerate(self.possible_agents)}
        self._termination_masks = simulator.termination_masks(self.config)

        dynamics = self.config.dynamics
        self._action_low = np.array([dynamics.accel_min, -dynamics.yaw_rate_max])
        self._action_high = np.array([dynamics.accel_max, dynamics.yaw_rate_max])
        low, high = observation_bounds(self.config.observation, dynamics)
        self.observation_spaces = {
            agent: gymnasium.spaces.Box(low, high, dtype=np.float32)
            for agent in self.possible_agents
        }
        self.action_spaces = {
            agent: gymnasium.spaces.Box(
                self._action_low.astype(np.float32), self._action_high.astype(np.float32)
            )
            for agent in self.possible_agents
        }
        self.action_input = ActionInput(
            self.possible_agents, self._action_low, self._action_high, self.config.clip_actions
        )
        self.state_space = gymnasium.spaces.Box(
            -np.inf, np.inf, (STATE_FEATURES * self.config.max_agents,), np.float32
        )

        self.agents: list[str] = []
        self._rng = np.random.default_rng()
        self._scene: SceneState | None = None
        self._scenario: Scenario | None = None
        self._events: event_detection.FrameEvents | None = None
        self._scenario_rows = np.full(self.config.max_agents, -1)
        self._log_end = np.zeros(self.config.max_agents, dtype=np.int64)
        self._renderer: Any = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        """Observation space of ``agent`` (the same Box for every agent)."""
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        """Action space of ``agent``: (accel [m/s^2], yaw rate [rad/s])."""
        return self.action_spaces[self._check_agent(agent)]

    # ------------------------------------------------------------- read-only views
    @property
    def scene(self) -> SceneState:
        """The current :class:`SceneState` (frozen; never mutated in place)."""
        if self._scene is None:
            raise RuntimeError("the env has not been reset yet: call reset() first")
        return self._scene

    @property
    def scenario(self) -> Scenario:
        """The scenario the current episode started from."""
        if self._scenario is None:
            raise RuntimeError("the env has not been reset yet: call reset() first")
        return self._scenario

    @property
    def map(self) -> DrivableMap:
        """The current episode's drivable map."""
        return self.scenario.map

    def view(self) -> SceneView:
        """A read-only :class:`SceneView` of the current scene, for scene policies."""
        return SceneView.from_state(
            self.scene,
            self.scenario,
            self._scenario_rows,
            tuple(self.possible_agents),
            self.config.dynamics.dt,
        )

    @property
    def last_events(self) -> event_detection.FrameEvents:
        """Collisions and off-road flags at the current step."""
        if self._events is None:
            raise RuntimeError("the env has not been reset yet: call reset() first")
        return self._events

    # ------------------------------------------------------------------- API
    def reset(
        self, seed: int | None = None, options: Mapping[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode.

        Args:
            seed: seeds the env's generator (scenario draws); the same seed gives the
                same episode.
            options: ``{"scenario": Scenario}`` starts from that scene.
        """
        seed, options = check_reset_arguments(seed, options)
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        unknown = sorted(set(options) - {"scenario"})
        if unknown:  # tolerated (the PettingZoo API test passes extra keys), but reported
            gymnasium.logger.warn(f"reset(options=...) ignores unknown keys {unknown}")
        scenario = options.get("scenario")
        if scenario is None:
            scenario = self.source.sample(self._rng, self.config.max_agents)
        if not isinstance(scenario, Scenario):
            raise TypeError(
                "reset(options={'scenario': ...}) needs a Scenario, "
                f"got {type(scenario).__name__}"
            )
        if not math.isclose(scenario.dt, self.config.dynamics.dt, rel_tol=1e-9):
            raise ValueError(
                f"scenario {scenario.name!r} is logged at dt = {scenario.dt} s but the env "
                f"steps dt = {self.config.dynamics.dt} s (EnvConfig.dynamics.dt): give both "
                "the same time step"
            )
        self._scenario = scenario
        rows = simulator.select_agents(scenario, self.config.max_agents)
        self._scenario_rows = np.full(self.config.max_agents, -1)
        self._scenario_rows[: rows.size] = rows
        self._scene = simulator.reset(scenario, self.config.max_agents, rows)
        self._log_end = simulator.log_end_steps(scenario, rows, self.config.max_agents)
        self.agents = [self.possible_agents[i] for i in np.flatnonzero(self._scene.present)]
        evaluation = simulator.evaluate(self._scene, self.map, self.config)
        self._events = evaluation.events
        observations, _, infos = self._agent_dicts(evaluation, self.agents)
        if self._renderer is not None:
            self._renderer.reset(self)
        return observations, infos

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Advance every live agent by 0.1 s.

        Args:
            actions: ``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for exactly the live
                agents (``env.agents``).
        """
        if self._scene is None:
            raise RuntimeError("step() called before reset(): call reset() first")
        if not self.agents:
            raise RuntimeError("step() called after the episode ended: call reset() first")
        action_array = self.action_input.to_array(actions, self.agents)
        self._scene, transition = simulator.transition(
            self._scene,
            action_array,
            self.map,
            self.config,
            log_end=self._log_end if self.config.leave_when_log_ends else None,
            masks=self._termination_masks,
        )
        self._events = transition.events
        agents = self.agents
        observations, rewards, infos = self._agent_dicts(transition.evaluation, agents)
        slot = self._slot
        terminated, truncated = transition.terminated, transition.truncated
        done = (terminated | truncated).tolist()
        terminated, truncated = terminated.tolist(), truncated.tolist()
        terminations = {agent: terminated[slot[agent]] for agent in agents}
        truncations = {agent: truncated[slot[agent]] for agent in agents}
        self.agents = [agent for agent in agents if not done[slot[agent]]]
        if self._renderer is not None:
            self._renderer.record(self)
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """Global state for centralised critics: (9 * max_agents,) float32, ego-centred."""
        scene = self.scene
        current = scene.current
        ego_xy = current[0, :2]
        features = np.stack(
            [
                scene.present,
                scene.active,
                current[:, 0] - ego_xy[0],
                current[:, 1] - ego_xy[1],
                current[:, 2],
                np.cos(current[:, YAW]),
                np.sin(current[:, YAW]),
                scene.length,
                scene.width,
            ],
            axis=-1,
        )
        return np.where(scene.present[:, None], features, 0.0).astype(np.float32).reshape(-1)

    def render(self) -> np.ndarray | None:
        """Draw the scene: an RGB array for ``"rgb_array"``, a window for ``"human"``."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; returning None")
            return None
        from riskflow_env.render import SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(self.render_mode)
            self._renderer.reset(self)
        return self._renderer.render(self)

    def close(self) -> None:
        """Release the renderer's window, if any."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # --------------------------------------------------------------- internals
    def _check_agent(self, agent: str) -> str:
        if agent not in self._slot:
            raise self.action_input.unknown_agent_error(agent)
        return agent

    def _agent_dicts(
        self, evaluation: simulator.Evaluation, agents: Sequence[str]
    ) -> tuple[dict, dict, dict]:
        """Per-agent observations, rewards and infos of ``agents`` (present slots)."""
        events = evaluation.events
        slots = [self._slot[agent] for agent in agents]
        rows = evaluation.observations
        reward = evaluation.reward.tolist()
        # One tuple of (speed, collision, offroad, risk, comfort) per slot.
        columns = [evaluation.reward_terms[name].tolist() for name in REWARD_TERMS]
        term_rows = list(zip(*columns, strict=True))
        collided = events.collided.tolist()
        offroad = events.offroad_fraction.tolist()
        depth = events.sdf_depth.tolist()
        partners = _collision_partners(events.collisions, self.possible_agents)
        pairs = list(zip(agents, slots, strict=True))
        observations = {agent: rows[i] for agent, i in pairs}
        rewards = {agent: reward[i] for agent, i in pairs}
        infos = {
            agent: {
                "reward_terms": dict(zip(REWARD_TERMS, term_rows[i], strict=True)),
                "collided": collided[i],
                "collided_with": partners.get(i, []),
                "offroad_fraction": offroad[i],
                "sdf_depth": depth[i],
            }
            for agent, i in pairs
        }
        return observations, rewards, infos


def wrapped_env(
    env: RiskFlowParallelEnv | None,
    config: EnvConfig | None,
    scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None,
    render_mode: str | None,
) -> RiskFlowParallelEnv:
    """The parallel env a wrapper runs on: ``env`` when given (then the other arguments
    must be None), else one built from ``config``, ``scenarios`` and ``render_mode``."""
    if env is None:
        return RiskFlowParallelEnv(config=config, scenarios=scenarios, render_mode=render_mode)
    if not isinstance(env, RiskFlowParallelEnv):
        raise TypeError(f"env must be a RiskFlowParallelEnv, got {type(env).__name__}")
    if config is not None or scenarios is not None or render_mode is not None:
        raise ValueError("pass either env or (config, scenarios, render_mode), not both")
    return env


def check_reset_arguments(seed: Any, options: Any) -> tuple[int | None, dict[str, Any]]:
    """``reset``'s arguments checked: ``seed`` None or an int >= 0 (gymnasium's seeding
    rule; a bool is not an int), ``options`` None or a dict. Returns ``(seed as a Python
    int or None, options as a new dict)``; TypeError / ValueError naming the argument."""
    if seed is not None:
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
            raise TypeError(
                f"reset(seed=...) must be None or an int >= 0, got {type(seed).__name__} "
                f"({seed!r:.40})"
            )
        if seed < 0:
            raise ValueError(f"reset(seed=...) must be None or an int >= 0, got {seed}")
        seed = int(seed)
    if options is not None and not isinstance(options, Mapping):
        raise TypeError(
            "reset(options=...) must be None or a dict such as {'scenario': Scenario}, "
            f"got {type(options).__name__} ({options!r:.40})"
        )
    return seed, dict(options or {})


def _collision_partners(collisions: np.ndarray, names: Sequence[str]) -> dict[int, list[str]]:
    """slot -> names of the vehicles it overlaps (only slots that collide appear)."""
    partners: dict[int, list[str]] = {}
    if collisions.any():
        for i, j in np.argwhere(collisions).tolist():
            partners.setdefault(i, []).append(names[j])
    return partners
