"""Gymnasium single-agent view of ``riskflow_v0``: the ego learns, a scene policy drives
everyone else (``RiskFlowEgo-v0``).

==================  ==============================================================
Import              ``gymnasium.make("RiskFlowEgo-v0", **kwargs)`` or
                    ``riskflow_env.wrappers.EgoEnv(...)``
Observation space   the ego's observation space of the parallel env:
                    ``Box(low, high, (D,), float32)``, D = 142 by default,
                    bounded where a physical bound holds (speed, last action,
                    neighbour offsets, angles, risk, presence; not SDF values)
Action space        the ego's action space: ``Box([accel_min, -yaw_rate_max],
                    [accel_max, yaw_rate_max])`` (acceleration [m/s^2], yaw rate
                    [rad/s]), default [-8, 5] x [-1, 1]
Reward              the ego's reward; ``info["reward_terms"]`` breaks it into terms
Termination         the ego terminates (collision / off-road, per ``EnvConfig``) or is
                    truncated (``episode_steps``, default 100 = 10 s)
Other vehicles      a :class:`~riskflow_env.view.ScenePolicy` (default
                    :class:`~riskflow_env.agents.IDMPolicy` with
                    ``controlled="others"``: IDM car following and lane keeping);
                    by default two that collide stop there, as obstacles
==================  ==============================================================

Arguments (``EgoEnv(config=None, scenarios=None, policy=None, render_mode=None,
env=None)``): ``config``, ``scenarios`` and ``render_mode`` build the parallel env as
:func:`riskflow_env.parallel_env` does, unless ``env`` passes one in. Every step the
policy gets ``env.view()`` and must return an action for every live agent but the ego.

Version history:

* v0: initial release.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np

from riskflow_env.agents.base import check_policy, policy_actions, restart_policy
from riskflow_env.agents.idm import IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.env import RiskFlowParallelEnv, check_reset_arguments, wrapped_env
from riskflow_env.scenarios import Scenario, ScenarioSource
from riskflow_env.view import ScenePolicy

EGO = "ego"


class EgoEnv(gymnasium.Env):
    """The ego's Gymnasium env over a :class:`RiskFlowParallelEnv` (see the module docstring).

    Args:
        config: env configuration (used when ``env`` is None).
        scenarios: scenario source (used when ``env`` is None).
        policy: drives every live agent but the ego; default IDM traffic.
        render_mode: ``None``, ``"rgb_array"`` or ``"human"`` (used when ``env`` is None).
        env: an existing parallel env to wrap instead of building one.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(
        self,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None = None,
        policy: ScenePolicy | None = None,
        render_mode: str | None = None,
        env: RiskFlowParallelEnv | None = None,
    ) -> None:
        env = wrapped_env(env, config, scenarios, render_mode)
        if policy is None:
            policy = IDMPolicy(controlled="others", dynamics=env.config.dynamics)
        self.parallel_env = env
        self.policy = check_policy(policy)
        self.render_mode = env.render_mode
        self.observation_space = env.observation_space(EGO)
        self.action_space = env.action_space(EGO)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode (``options`` as :meth:`RiskFlowParallelEnv.reset`). With a
        ``seed``, a policy that has ``reseed(seed)`` (the learned adversaries) is reseeded
        too, so two resets with the same seed give the same episode."""
        seed, options = check_reset_arguments(seed, options)
        super().reset(seed=seed)
        observations, infos = self.parallel_env.reset(seed=seed, options=options)
        restart_policy(self.policy, self.parallel_env.view(), seed)
        return observations[EGO], infos[EGO]

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Advance 0.1 s: the ego takes ``action`` (accel [m/s^2], yaw rate [rad/s]),
        the policy drives the others."""
        env = self.parallel_env
        if EGO not in env.agents:
            raise RuntimeError("step() called after the ego's episode ended: call reset() first")
        others = [agent for agent in env.agents if agent != EGO]
        proposed = policy_actions(self.policy, env.view(), others, "other than the ego")
        actions = {EGO: action, **proposed}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        return (
            observations[EGO],
            rewards[EGO],
            terminations[EGO],
            truncations[EGO],
            infos[EGO],
        )

    def render(self) -> np.ndarray | None:
        """Render the whole scene (see :meth:`RiskFlowParallelEnv.render`)."""
        return self.parallel_env.render()

    def close(self) -> None:
        """Close the parallel env."""
        self.parallel_env.close()
