"""Learned RL adversaries against a fixed ego: the parallel env with SuperSuit parameter
sharing and SB3 (the counterpart of the generative RiskFlow adversary).

:class:`FixedEgoParallelEnv` is a PettingZoo ``ParallelEnv`` over ``riskflow_v0`` whose
agents are the *other* vehicles: a fixed :class:`~policies.planners.EgoPlanner` (IDM by
default) drives the ego inside it, and each agent's reward is
:func:`adversary_reward` instead of the env's driving reward (which rewards speed and
punishes collisions: the opposite of an adversary's job).

:func:`marl_vec_env` turns it into an SB3 vector env with SuperSuit: every agent of every
scene is one row of the batch, and one shared policy acts for all of them (parameter
sharing; the spaces are identical across agents). SuperSuit's plain conversion needs an
observation for every agent at every step, so the scenes always fill every slot
(:class:`~riskflow_env.scenarios.HighwayTrafficSource` with ``num_vehicles = (slots,
slots)``) and nobody finishes early (``terminate_on_* = "none"``): episodes end for all
agents at once, by truncation, and the vector env resets them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from policies.planners.base import EgoPlanner, as_action, reset_planner
from riskflow_env.config import EnvConfig, _set_finite
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.wrappers.vector import sb3_vec_env

EGO = "ego"


@dataclass(frozen=True)
class AdversaryRewardConfig:
    """Per-step reward of a learned adversary (each term in ``info["adversary_terms"]``).

    reward = ego_collision * [overlaps the ego] + other_collision * [overlaps another
    non-ego vehicle] + closeness * max(0, 1 - d / closeness_radius) + offroad * [off road]

    with ``d`` the centre distance to the ego [m].

    Attributes:
        ego_collision: reward while overlapping the ego [reward / step] (> 0: the goal).
        other_collision: reward while overlapping another adversary [reward / step]
            (< 0: pile-ups among themselves are no success).
        closeness: weight of the closeness term [reward / step] (dense shaping).
        closeness_radius: distance at which closeness drops to 0 [m].
        offroad: reward while any footprint point is off the road [reward / step] (< 0:
            the adversary must stay realistic).
    """

    ego_collision: float = 5.0
    other_collision: float = -1.0
    closeness: float = 0.05
    closeness_radius: float = 30.0
    offroad: float = -1.0

    def __post_init__(self) -> None:
        _set_finite(self, (field.name for field in fields(self)))  # every term a number
        if not self.closeness_radius > 0:
            raise ValueError(
                f"AdversaryRewardConfig.closeness_radius must be > 0 m, got {self.closeness_radius}"
            )


def adversary_reward(
    info: dict[str, Any], distance_to_ego: float, config: AdversaryRewardConfig
) -> tuple[float, dict[str, float]]:
    """One adversary's reward and its terms.

    Args:
        info: the agent's env info (``collided_with``, ``offroad_fraction``).
        distance_to_ego: centre distance to the ego [m].
        config: weights.
    """
    partners = info["collided_with"]
    terms = {
        "ego_collision": config.ego_collision * float(EGO in partners),
        "other_collision": config.other_collision * float(any(p != EGO for p in partners)),
        "closeness": config.closeness * max(0.0, 1.0 - distance_to_ego / config.closeness_radius),
        "offroad": config.offroad * float(info["offroad_fraction"] > 0),
    }
    return sum(terms.values()), terms


class FixedEgoParallelEnv(ParallelEnv):
    """``riskflow_v0`` without the ego among its agents (module docstring).

    Args:
        env: the parallel env (its ego is driven by ``planner``).
        planner: the fixed ego planner; default :class:`~policies.planners.IDMPlanner`.
        reward: the adversaries' reward weights.
    """

    metadata = {"name": "riskflow_fixed_ego_v0", "render_modes": ["rgb_array", "human"]}

    def __init__(
        self,
        env: RiskFlowParallelEnv,
        planner: EgoPlanner | None = None,
        reward: AdversaryRewardConfig | None = None,
    ) -> None:
        if planner is None:
            from policies.planners import IDMPlanner

            planner = IDMPlanner(dynamics=env.config.dynamics)
        self.env, self.planner = env, planner
        self.reward = reward or AdversaryRewardConfig()
        self.possible_agents = [agent for agent in env.possible_agents if agent != EGO]
        self.agents: list[str] = []
        self.render_mode = env.render_mode
        self._ego_observation: np.ndarray | None = None

    def observation_space(self, agent: str):
        return self.env.observation_space(agent)

    def action_space(self, agent: str):
        return self.env.action_space(agent)

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        observations, infos = self.env.reset(seed=seed, options=options)
        self._ego_observation = observations.pop(EGO)
        infos.pop(EGO, None)
        reset_planner(self.planner, self.env.view())
        self.agents = [agent for agent in self.env.agents if agent != EGO]
        return observations, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        env = self.env
        actions = dict(actions)
        if EGO in env.agents:
            actions[EGO] = as_action(self.planner(self._ego_observation, env.view()), "planner")
        observations, _, terminations, truncations, infos = env.step(actions)
        self._ego_observation = observations.pop(EGO, self._ego_observation)
        for done in (terminations, truncations, infos):
            done.pop(EGO, None)
        view = env.view()
        ego_xy = view.current[0, :2]
        rewards = {}
        for agent, info in infos.items():
            distance = float(np.hypot(*(view.current[view.slot(agent), :2] - ego_xy)))
            rewards[agent], info["adversary_terms"] = adversary_reward(info, distance, self.reward)
            info["ego_collision"] = EGO in info["collided_with"]
        self.agents = [agent for agent in env.agents if agent != EGO]
        return observations, rewards, terminations, truncations, infos

    def render(self):
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    def state(self) -> np.ndarray:
        return self.env.state()


class FullRosterSource:
    """Highway-env highway traffic with exactly ``slots`` vehicles (a ``ScenarioSource``).

    :func:`~riskflow_env.scenarios.traffic.place_traffic` places *up to* the requested
    count (it drops candidates that would overlap), and SuperSuit's plain vector env fails
    on a scene with an empty slot, so a short draw is replaced by the next draw from the
    same generator (deterministic given its state).

    Args:
        slots: vehicles per scene, the ego included.
        attempts: draws before giving up with an error.
    """

    def __init__(self, slots: int, attempts: int = 100) -> None:
        from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig

        self.slots, self.attempts = slots, attempts
        config = TrafficConfig(families=("highway",), num_vehicles=(slots, slots))
        self.source = HighwayTrafficSource(config)

    def sample(self, rng: np.random.Generator, max_agents: int | None = None):
        """The first draw with all ``slots`` vehicles."""
        for _ in range(self.attempts):
            scenario = self.source.sample(rng, max_agents)
            if scenario.num_agents == self.slots:
                return scenario
        raise RuntimeError(
            f"FullRosterSource: no highway scene with {self.slots} vehicles in "
            f"{self.attempts} draws; lower slots"
        )


def full_roster_env(slots: int, episode_steps: int, **config: Any) -> RiskFlowParallelEnv:
    """A parallel env whose scenes fill all ``slots`` (ego included, :class:`FullRosterSource`)
    and in which nobody finishes early: what SuperSuit's plain vector env needs (module
    docstring)."""
    env_config = EnvConfig(
        max_agents=slots,
        episode_steps=episode_steps,
        terminate_on_collision="none",
        terminate_on_offroad="none",
        **config,
    )
    return RiskFlowParallelEnv(config=env_config, scenarios=FullRosterSource(slots))


def marl_vec_env(
    slots: int = 6,
    num_envs: int = 1,
    episode_steps: int = 100,
    planner: EgoPlanner | None = None,
    reward: AdversaryRewardConfig | None = None,
):
    """An SB3 ``VecEnv`` of ``num_envs`` scenes x ``slots - 1`` learned adversaries each
    (:func:`riskflow_env.wrappers.sb3_vec_env`: SuperSuit ``pettingzoo_env_to_vec_env_v1``
    + ``concat_vec_envs_v1``, in process, with the seed SB3 calls)."""
    env = FixedEgoParallelEnv(full_roster_env(slots, episode_steps), planner, reward)
    return sb3_vec_env(env, num_envs)


def rollout_ego_collisions(
    env: FixedEgoParallelEnv, act, episodes: int, seed: int = 0
) -> list[bool]:
    """Run ``episodes`` episodes with ``act(observations: (N, D)) -> (N, 2)`` driving every
    adversary; per episode, whether any adversary collided with the ego."""
    outcomes = []
    for episode in range(episodes):
        observations, _ = env.reset(seed=seed + episode)
        hit = False
        while env.agents:
            agents = list(env.agents)
            batch = np.stack([observations[agent] for agent in agents])
            actions = dict(zip(agents, np.asarray(act(batch)), strict=True))
            observations, _, _, _, infos = env.step(actions)
            hit = hit or any(info["ego_collision"] for info in infos.values())
        outcomes.append(hit)
    return outcomes
