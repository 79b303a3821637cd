"""The traffic of a vector env: one object that drives the other vehicles of N scenes.

:func:`batched_traffic` turns the scene policy given to
:class:`~policies.rl.vector_env.EgoVectorEnv` into an object with

* ``reset_scene(index, view, seed)``: a new episode in scene ``index`` (reseeded with
  ``seed`` when it is not None, as ``EgoEnv.reset(seed=...)`` reseeds its policy);
* ``act_array(views, running=None)``: (N, A, 2) actions (accel [m/s^2], yaw rate
  [rad/s]) of every live non-ego vehicle of the running scenes (all by default), zeros
  elsewhere, what batched stepping takes;
* ``scenes``: the per-scene policies (for curriculum stages).

A learned adversary (a :class:`~policies.pipeline.policy.PipelinePolicy`) becomes a
:class:`~policies.pipeline.batched.BatchedAdversary`: every scene due to re-plan
is planned in one call. Any other :class:`~riskflow_env.view.ScenePolicy` (IDM traffic,
log replay) is copied per scene and asked scene by scene (:class:`SceneLoop`), its
actions checked as ``EgoEnv`` checks them.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np

from policies.pipeline.batched import BatchedAdversary
from policies.pipeline.policy import PipelinePolicy
from riskflow_env.action_input import ActionInput
from riskflow_env.agents.base import check_policy, policy_actions, restart_policy
from riskflow_env.config import EnvConfig
from riskflow_env.view import ScenePolicy, SceneView
from riskflow_env.wrappers.ego_env import EGO


class SceneLoop:
    """A copy of ``policy`` per scene, asked one scene after the other.

    Args:
        policy: the scene policy (deep-copied N times; it is not used itself).
        num_scenes: N.
        config: the env configuration (agent names, action bounds, clipping).
    """

    def __init__(self, policy: ScenePolicy, num_scenes: int, config: EnvConfig) -> None:
        self.scenes = tuple(copy.deepcopy(check_policy(policy)) for _ in range(num_scenes))
        dynamics = config.dynamics
        low = np.array([dynamics.accel_min, -dynamics.yaw_rate_max])
        high = np.array([dynamics.accel_max, dynamics.yaw_rate_max])
        self._input = ActionInput(list(config.agent_names), low, high, config.clip_actions)
        self._slots = config.max_agents

    def reset_scene(self, index: int, view: SceneView, seed: int | None = None) -> None:
        """A new episode in scene ``index``."""
        restart_policy(self.scenes[index], view, seed)

    def act_array(
        self, views: Sequence[SceneView], running: np.ndarray | None = None
    ) -> np.ndarray:
        """(N, A, 2) the scenes' actions (module docstring); ``running``: (N,) bool, the
        scenes to ask (None: all), the others get zeros."""
        arrays = np.zeros((len(self.scenes), self._slots, 2))
        for index, (policy, view) in enumerate(zip(self.scenes, views, strict=True)):
            if running is not None and not running[index]:
                continue
            others = [agent for agent in view.live_agents if agent != EGO]
            if others:
                proposed = policy_actions(policy, view, others, "other than the ego")
                arrays[index] = self._input.to_array(proposed, others)
        return arrays


def batched_traffic(
    policy: ScenePolicy, num_scenes: int, config: EnvConfig
) -> BatchedAdversary | SceneLoop:
    """The traffic of ``num_scenes`` scenes driven by ``policy`` (module docstring)."""
    if isinstance(policy, PipelinePolicy):
        return BatchedAdversary(policy, num_scenes)
    return SceneLoop(policy, num_scenes, config)


__all__ = ["SceneLoop", "batched_traffic"]
