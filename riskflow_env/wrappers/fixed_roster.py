"""Fixed-roster view of ``riskflow_v0`` for multi-agent training libraries: every agent of
the roster is live from ``reset`` to the end of the episode, with padded, masked slots.

The default env is PettingZoo-clean: its agents are the vehicles of the scene (8-32 of 32
slots), and an agent leaves ``env.agents`` when it is done. Training libraries expect
more: RLlib's ``ParallelPettingZooEnv`` reads the agent ids once, from the first reset,
and ends an episode only when *all* agents are terminated or *all* truncated; TorchRL's
``PettingZooWrapper`` builds its specs, infos included, for every possible agent and
sends an action for every one of them; SuperSuit's ``pettingzoo_env_to_vec_env_v1`` wants
an observation for every possible agent at every step. This wrapper gives them that.

==================  ==============================================================
Import              ``riskflow_env.wrappers.FixedRosterEnv(...)``
Agents              ``roster`` (default: every slot, ``ego``, ``agent_1`` ...);
                    ``agents == possible_agents == roster`` from ``reset`` until the
                    episode ends, then ``[]``
Action space        as the parallel env (identical for every agent); the actions of
                    padded agents are ignored (``ignore_inactive_actions=True``)
Observation space   as the parallel env; a padded agent observes zeros
Reward              the parallel env's; 0 for a padded agent
Infos               flat, fixed keys and shapes (below); ``info["live"]`` is the mask
Episode end         together for the whole roster (below)
Other vehicles      the live vehicles outside the roster are driven by ``policy``
                    (default :class:`~riskflow_env.agents.IDMPolicy`)
==================  ==============================================================

**Padded, masked slots.** An agent is *live* at a step when its vehicle was live when
the step began (its action moved it; its observation and reward are real). A roster agent
whose slot is empty in this scene, or whose vehicle is already done (collided with
``terminate_on_collision``, left with ``leave_when_log_ends``) while the episode goes
on, is *padded*: zero observation, zero reward, ``info["live"] == False``, neither
terminated nor truncated until the episode ends (SuperSuit's "black death" convention,
``supersuit.black_death_v3``), and its action is ignored.

**Flat infos** (every value a numpy scalar or array of fixed shape, as TorchRL's specs
need): ``live`` bool; ``collided`` bool; ``collided_with`` ``(max_agents,)`` bool, the
slots it overlaps; ``offroad_fraction`` float; ``sdf_depth`` [m] float;
``reward_terms`` ``(5,)`` float32 in :data:`~riskflow_env.rewards.REWARD_TERMS` order
(speed, collision, offroad, risk, comfort). Padded agents get zeros.

**Episode end.** The episode ends when no roster agent is live any more (the parallel
env's end: time limit, the ego's end with ``end_with_ego``; or the roster's vehicles
all done). Every roster agent then gets the same flag: *terminated* when some vehicle
terminated at that last step (e.g. the ego crashed: the game is over for everyone, no
value is bootstrapped), *truncated* otherwise (time limit). One flag for all is what
RLlib's ``ParallelPettingZooEnv`` (``__all__`` = all terminated or all truncated),
SuperSuit's vector env (reset when all are done) and TorchRL's ``PettingZooWrapper``
(done on any) need to close the episode.

Arguments (``FixedRosterEnv(config=None, scenarios=None, policy=None, render_mode=None,
env=None, *, roster=None, ignore_inactive_actions=True)``): ``config``, ``scenarios``,
``render_mode`` build the parallel env as :func:`riskflow_env.parallel_env` does, unless
``env`` passes one in; ``roster`` the agent names the library controls (slot order);
``policy`` a :class:`~riskflow_env.view.ScenePolicy` for the slots outside the roster;
with ``ignore_inactive_actions=False`` an action for a padded agent raises ValueError
instead of being ignored.

Version history:

* v0: initial release.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from riskflow_env.agents.base import check_policy, policy_actions, restart_policy
from riskflow_env.agents.idm import IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.env import RiskFlowParallelEnv, wrapped_env
from riskflow_env.rewards import REWARD_TERMS
from riskflow_env.scenarios import Scenario, ScenarioSource
from riskflow_env.view import ScenePolicy

INFO_KEYS = ("live", "collided", "collided_with", "offroad_fraction", "sdf_depth", "reward_terms")


class FixedRosterEnv(ParallelEnv):
    """``riskflow_v0`` with a fixed roster of agents (see the module docstring).

    Args:
        config: env configuration (used when ``env`` is None).
        scenarios: scenario source (used when ``env`` is None).
        policy: drives the live vehicles outside ``roster``; default IDM traffic. Not
            used when the roster holds every slot.
        render_mode: ``None``, ``"rgb_array"`` or ``"human"`` (used when ``env`` is None).
        env: an existing parallel env to wrap instead of building one.
        roster: the agents the training library controls, a subset of the env's
            ``possible_agents``; default all of them.
        ignore_inactive_actions: actions for padded agents are ignored (True) or raise
            ValueError (False: give actions for exactly the live roster agents).
    """

    metadata = {**RiskFlowParallelEnv.metadata, "name": "riskflow_fixed_roster_v0"}

    def __init__(
        self,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None = None,
        policy: ScenePolicy | None = None,
        render_mode: str | None = None,
        env: RiskFlowParallelEnv | None = None,
        *,
        roster: Sequence[str] | None = None,
        ignore_inactive_actions: bool = True,
    ) -> None:
        env = wrapped_env(env, config, scenarios, render_mode)
        self.env = env
        self.possible_agents = _check_roster(roster, env.possible_agents)
        if not isinstance(ignore_inactive_actions, bool):
            raise TypeError(
                "ignore_inactive_actions must be a bool, got "
                f"{type(ignore_inactive_actions).__name__}"
            )
        self.ignore_inactive_actions = ignore_inactive_actions
        outside = [agent for agent in env.possible_agents if agent not in self.possible_agents]
        if policy is None and outside:
            policy = IDMPolicy(controlled=tuple(outside), dynamics=env.config.dynamics)
        self.policy = check_policy(policy) if policy is not None else None
        self.render_mode = env.render_mode
        self.observation_spaces = {a: env.observation_space(a) for a in self.possible_agents}
        self.action_spaces = {a: env.action_space(a) for a in self.possible_agents}
        self.state_space = env.state_space
        self.agents: list[str] = []
        self._in_roster = frozenset(self.possible_agents)
        self._index = {agent: index for index, agent in enumerate(self.possible_agents)}
        env_slot = {agent: index for index, agent in enumerate(env.possible_agents)}
        self._slots = np.array([env_slot[agent] for agent in self.possible_agents])
        self._observation_size = self.observation_spaces[self.possible_agents[0]].shape[0]

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        """Observation space of ``agent`` (the parallel env's, identical for every agent)."""
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        """Action space of ``agent``: (accel [m/s^2], yaw rate [rad/s])."""
        return self.action_spaces[self._check_agent(agent)]

    # ------------------------------------------------------------------- API
    def reset(
        self, seed: int | None = None, options: Mapping[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode (arguments as :meth:`RiskFlowParallelEnv.reset`); a seeded
        reset reseeds the scene policy too, so it repeats the episode bit for bit."""
        observations, infos = self.env.reset(seed=seed, options=options)
        if self.policy is not None:
            restart_policy(self.policy, self.env.view(), seed)
        self.agents = list(self.possible_agents)
        padded_observations, _, padded_infos = self._padded(observations, {}, infos)
        return padded_observations, padded_infos

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Advance 0.1 s.

        Args:
            actions: ``{agent: (accel [m/s^2], yaw_rate [rad/s])}`` for every live roster
                agent; padded agents' actions may be given (ignored) or left out.
        """
        if not self.agents:
            raise RuntimeError("step() called after the episode ended: call reset() first")
        env = self.env
        live = [agent for agent in env.agents if agent in self._in_roster]
        env_actions = self._live_actions(actions, live)
        others = [agent for agent in env.agents if agent not in self._in_roster]
        if others:
            view = env.view()
            env_actions.update(policy_actions(self.policy, view, others, "outside the roster"))
        observations, rewards, terminations, _, infos = env.step(env_actions)
        padded_observations, padded_rewards, padded_infos = self._padded(
            observations, rewards, infos
        )
        over = not any(agent in self._in_roster for agent in env.agents)
        terminated = over and any(terminations.values())
        truncated = over and not terminated
        flags = (
            dict.fromkeys(self.possible_agents, terminated),
            dict.fromkeys(self.possible_agents, truncated),
        )
        if over:
            self.agents = []
        return padded_observations, padded_rewards, *flags, padded_infos

    def live_mask(self) -> np.ndarray:
        """(len(roster),) bool: the roster agents whose vehicles are live now."""
        return self.env.scene.active[self._slots].copy()

    def state(self) -> np.ndarray:
        """The parallel env's global state (9 * max_agents,) float32."""
        return self.env.state()

    def render(self) -> np.ndarray | None:
        """Render the whole scene (see :meth:`RiskFlowParallelEnv.render`)."""
        return self.env.render()

    def close(self) -> None:
        """Close the parallel env."""
        self.env.close()

    # --------------------------------------------------------------- internals
    def _check_agent(self, agent: str) -> str:
        if agent not in self._in_roster:
            raise ValueError(f"unknown agent {agent!r}; the roster is {self.possible_agents}")
        return agent

    def _live_actions(self, actions: Mapping[str, Any], live: list[str]) -> dict[str, Any]:
        """The actions the parallel env gets: those of the ``live`` roster agents."""
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"actions must be a dict {{agent: action}}, got {type(actions).__name__}"
            )
        outside = sorted(set(actions) - self._in_roster, key=str)
        if outside:
            raise ValueError(
                f"actions given for agents outside the roster {self.possible_agents}: "
                f"{outside} (the scene policy drives the other vehicles)"
            )
        if not self.ignore_inactive_actions:
            return dict(actions)  # the parallel env names padded or missing agents
        return {agent: actions[agent] for agent in live if agent in actions}

    def _padded(
        self, observations: dict, rewards: dict, infos: dict
    ) -> tuple[dict[str, np.ndarray], dict[str, float], dict[str, dict]]:
        """Observations, rewards and flat infos of every roster agent; zeros for those
        the parallel env did not report (padded)."""
        reported = [agent for agent in self.possible_agents if agent in observations]
        rows = [self._index[agent] for agent in reported]
        count, max_agents = len(self.possible_agents), self.env.config.max_agents
        observation = np.zeros((count, self._observation_size), np.float32)
        reward = np.zeros(count)
        live = np.zeros(count, dtype=bool)
        collided_with = np.zeros((count, max_agents), dtype=bool)
        scalars = np.zeros((count, 2))  # offroad fraction, sdf depth
        terms = np.zeros((count, len(REWARD_TERMS)), np.float32)
        if reported:
            observation[rows] = np.stack([observations[agent] for agent in reported])
            reward[rows] = [rewards.get(agent, 0.0) for agent in reported]
            live[rows] = True
            slots = self._slots[rows]
            events = self.env.last_events
            collided_with[rows] = events.collisions[slots]
            scalars[rows, 0] = events.offroad_fraction[slots]
            scalars[rows, 1] = events.sdf_depth[slots]
            terms[rows] = [
                [infos[agent]["reward_terms"][name] for name in REWARD_TERMS] for agent in reported
            ]
        collided = collided_with.any(axis=1)
        names = self.possible_agents
        return (
            dict(zip(names, observation, strict=True)),
            dict(zip(names, reward.tolist(), strict=True)),
            {
                agent: {
                    "live": live[i],
                    "collided": collided[i],
                    "collided_with": collided_with[i],
                    "offroad_fraction": scalars[i, 0],
                    "sdf_depth": scalars[i, 1],
                    "reward_terms": terms[i],
                }
                for i, agent in enumerate(names)
            },
        )


def _check_roster(roster: Sequence[str] | None, possible_agents: list[str]) -> list[str]:
    """The roster in slot order; ValueError naming what is wrong."""
    if roster is None:
        return list(possible_agents)
    if isinstance(roster, str) or not isinstance(roster, Sequence):
        raise TypeError(
            f"roster must be a sequence of agent names, got {type(roster).__name__} "
            f"({roster!r:.40})"
        )
    unknown = [agent for agent in roster if agent not in possible_agents]
    if unknown:
        raise ValueError(
            f"roster has unknown agents {unknown}; possible agents are 'ego' and "
            f"'agent_1'..'agent_{len(possible_agents) - 1}'"
        )
    if not roster or len(set(roster)) != len(roster):
        raise ValueError(f"roster must name at least one agent, each once, got {list(roster)}")
    return [agent for agent in possible_agents if agent in set(roster)]
