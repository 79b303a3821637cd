"""``EgoVectorEnv``: N ego episodes against the adversary, stepped as one batch (issue 18).

The Gymnasium vector env of the ego's training env (:class:`~policies.rl.envs.EgoTrainingEnv`
over ``RiskFlowEgo-v0``): N scenes, each its own episode drawn from the scenario source,

* stepped by **one** :func:`riskflow_env.simulator.transition` over all scenes and agents
  (:class:`~riskflow_env.scene_batch.SceneBatch`: each scene on its own map, with its own
  step count);
* with the traffic driven by **one** batched adversary: a learned adversary
  (``RiskFlowAdversary``, the unguided generator...) becomes a
  :class:`~policies.pipeline.batched.BatchedAdversary` that plans every scene due
  to re-plan in one call; any other scene policy (IDM traffic) drives a copy per scene
  (:class:`~policies.rl.vector_traffic.SceneLoop`);
* with the ego's observation, action, reward, termination and episode outcome of
  :class:`~policies.rl.envs.EgoTrainingEnv` (its :class:`~policies.rl.envs.EgoInterface`,
  one per scene; :func:`~policies.rl.envs.scale_action` on the whole batch when there is
  no base planner).

==================  ==============================================================
Spaces              ``single_observation_space`` / ``single_action_space`` are the
                    single env's; ``observation_space`` (N, D) and ``action_space``
                    (N, 2) (``MultiDiscrete`` with maneuver actions) are batched
Reset               ``reset(seed=s)``: scene ``b`` is reset with seed ``s + b`` (its
                    scenario draw and its adversary's noise), as a single env
                    ``reset(seed=s + b)``; a list gives each scene its seed
Autoreset           ``AutoresetMode.SAME_STEP`` (default): a scene whose ego terminates
                    or is truncated is reset in the same ``step`` (the next scenario
                    from its generator); ``infos["final_obs"]`` / ``infos["final_info"]``
                    (masks ``_final_obs`` / ``_final_info``) hold its last observation
                    and info, the returned observation is the new episode's.
                    ``NEXT_STEP`` (Gymnasium's default): the step that ends an episode
                    returns its last observation (the outcome in ``infos``); the next
                    ``step`` resets the scene, ignoring its action (reward 0)
Infos               per key an (N,) array and its mask ``_key``: ``reward_terms``,
                    ``collided``, ``collided_with``, ``offroad_fraction``, ``sdf_depth``;
                    the episode outcome ``ego_collision`` / ``ego_offroad`` in
                    ``final_info``; with maneuver actions ``action_mask`` (N, M) bool
                    (:meth:`~policies.rl.envs.EgoInterface.action_mask`)
Gymnasium           ``gymnasium.make_vec("RiskFlowEgo-v0", num_envs=N)`` builds one
                    (:func:`ego_vector_entry_point`: the single env's spaces)
==================  ==============================================================

Scene ``b`` with seed ``s + b`` follows the episode of ``EgoTrainingEnv`` reset with seed
``s + b`` and given the same actions, to float rounding (the batched map lookup and the
padded planning), until it resets (tests/policies/test_rl_vector.py); the same seed gives
the same rollout, bit for bit. SB3: :func:`policies.rl.sb3_vec_env.sb3_ego_vec_env`.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from policies.rl.adversary import AdversaryStage, apply_stage, make_traffic
from policies.rl.envs import (
    EgoEnvConfig,
    EgoInterface,
    interface_options,
    record_outcome,
    scale_action,
    training_scenes,
)
from policies.rl.vector_infos import step_infos
from policies.rl.vector_traffic import batched_traffic
from riskflow_env.agents.idm import IDMPolicy
from riskflow_env.config import EnvConfig
from riskflow_env.env import check_reset_arguments
from riskflow_env.scenarios import Scenario, ScenarioSource
from riskflow_env.scene_batch import SceneBatch
from riskflow_env.view import ScenePolicy, SceneView
from riskflow_env.wrappers.ego_env import EGO


class EgoVectorEnv(VectorEnv):
    """N ego episodes against one batched adversary (module docstring).

    Args:
        num_envs: N >= 1 scenes.
        config: the env configuration of every scene (None: ``EnvConfig()``).
        scenarios: the scenario source the scenes draw from (None: the shipped
            evaluation bank).
        policy: drives every vehicle but the ego (None: IDM traffic, as ``EgoEnv``).
        autoreset_mode: ``SAME_STEP`` or ``NEXT_STEP`` (module docstring).
        **interface: ``base_planner``, ``action_repeat``, ``maneuver_features``,
            ``maneuver_actions``, ``maneuver_set``: the ego's interface
            (:class:`~policies.rl.envs.EgoInterface`).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None = None,
        policy: ScenePolicy | None = None,
        *,
        autoreset_mode: AutoresetMode | str = AutoresetMode.SAME_STEP,
        **interface: Any,
    ) -> None:
        modes = (AutoresetMode.SAME_STEP, AutoresetMode.NEXT_STEP)
        if autoreset_mode not in modes and autoreset_mode not in [m.value for m in modes]:
            raise ValueError(
                f"autoreset_mode must be one of {[m.value for m in modes]}, got {autoreset_mode!r}"
            )
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        self.scenes = SceneBatch(num_envs, config, scenarios)
        self.num_envs = len(self.scenes)
        self.config = self.scenes.config
        dynamics = self.config.dynamics
        self.interfaces = tuple(EgoInterface(dynamics, **interface) for _ in range(self.num_envs))
        if policy is None:
            policy = IDMPolicy(controlled="others", dynamics=dynamics)
        self.traffic = batched_traffic(policy, self.num_envs, self.config)
        interface = self.interfaces[0]
        env_space = self.scenes.envs[0].observation_space(EGO)
        self.single_observation_space = interface.observation_space(env_space)
        self.single_action_space = interface.action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.action_repeat = interface.action_repeat
        self._discrete = interface.maneuvers is not None
        self._per_scene = interface.base is not None or self._discrete
        self._env_obs: np.ndarray | None = None  # (N, D) the env's ego observations
        self._views: list[SceneView] | None = None
        self._outcome = np.zeros((2, self.num_envs))  # ego_collision, ego_offroad so far
        self._autoreset = np.zeros(self.num_envs, dtype=bool)  # NEXT_STEP: reset next call

    # ------------------------------------------------------------------ API
    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode in every scene (``seed``: module docstring; ``options`` go to
        every scene's ``RiskFlowParallelEnv.reset``)."""
        seeds = self._seeds(seed)
        _, options = check_reset_arguments(None, options)
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            super().reset(seed=int(seed))
        self._env_obs = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        observations, infos = self._reset_scenes(list(range(self.num_envs)), seeds, options, {})
        return observations, self._with_masks(infos)

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """``action_repeat`` env steps of every scene with the ego's ``actions`` (N, 2) in
        ``[-1, 1]`` (N maneuver indices with maneuver actions); rewards are the sums over
        the repeat. Finished scenes are reset (module docstring)."""
        if self._env_obs is None or self._views is None:
            raise RuntimeError("step() called before reset(): call reset() first")
        actions = self._check_actions(actions)
        count = self.num_envs
        pending = self._autoreset  # NEXT_STEP: scenes that ended at the last call
        running = ~pending
        rewards = np.zeros(count)
        terminated = np.zeros(count, dtype=bool)
        truncated = np.zeros(count, dtype=bool)
        observations = np.zeros((count, *self.single_observation_space.shape), np.float32)
        env_obs, views, infos = self._env_obs, self._views, {}
        for substep in range(self.action_repeat if running.any() else 0):
            moves = self.traffic.act_array(views)
            moves[:, 0] = self._ego_actions(actions, env_obs, views, substep)
            transition = self.scenes.step(moves)
            views = self.scenes.views()
            env_obs = np.where(running[:, None], transition.observations[:, 0], env_obs)
            rewards = rewards + np.where(running, transition.rewards[:, 0], 0.0)
            infos = step_infos(transition, self.scenes.agent_names, running, infos)
            self._outcome = np.where(running, record_outcome(self._outcome, infos), self._outcome)
            ended = running & (transition.terminated[:, 0] | transition.truncated[:, 0])
            terminated |= ended & transition.terminated[:, 0]
            truncated |= ended & transition.truncated[:, 0]
            observations[ended] = self._observe(env_obs, views, ended)
            running &= ~ended
            if not running.any():
                break
        observations[running] = self._observe(env_obs, views, running)
        self._env_obs, self._views = env_obs, views
        done = terminated | truncated
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        self._autoreset = np.zeros(count, dtype=bool) if same_step else done
        extra: dict[str, Any] = {}
        if done.any():
            outcome = {
                "ego_collision": self._outcome[0].copy(),
                "ego_offroad": self._outcome[1].copy(),
                "_ego_collision": done.copy(),
                "_ego_offroad": done.copy(),
            }
            if same_step:
                final_info = {**copy.deepcopy(infos), **outcome}  # the reset writes into infos
                masks = {f"_{key}": done.copy() for key in infos if not key.startswith("_")}
                final_obs = np.full(count, None, dtype=object)
                for index in np.flatnonzero(done):
                    final_obs[index] = observations[index].copy()
                extra = {
                    "final_obs": final_obs,
                    "_final_obs": done.copy(),
                    "final_info": {**final_info, **masks},
                    "_final_info": done.copy(),
                }
            else:
                infos.update(outcome)
        reset = list(np.flatnonzero(done if same_step else pending))
        if reset:
            observations, infos = self._reset_scenes(
                reset, [None] * len(reset), {}, infos, observations
            )
        infos.update(extra)
        return observations, rewards, terminated, truncated, self._with_masks(infos)

    def set_adversary_stage(self, stage: AdversaryStage) -> None:
        """Set k, guidance weight and target of every scene's RiskFlow adversary."""
        for scene in self.traffic.scenes:
            apply_stage(scene, stage)

    def close_extras(self, **kwargs: Any) -> None:
        """Close the scenes' envs."""
        for env in self.scenes.envs:
            env.close()

    # ------------------------------------------------------------ internals
    def _with_masks(self, infos: dict[str, Any]) -> dict[str, Any]:
        """``infos`` with ``action_mask`` (N, M) bool and its mask, for maneuver actions:
        each scene's :meth:`~policies.rl.envs.EgoInterface.action_mask` for the
        observation returned."""
        if not self._discrete:
            return infos
        masks = [i.action_mask(view) for i, view in zip(self.interfaces, self._views, strict=True)]
        mask_of = np.ones(self.num_envs, dtype=bool)
        return {**infos, "action_mask": np.stack(masks), "_action_mask": mask_of}

    def _reset_scenes(
        self,
        indices: list[int],
        seeds: list[int | None],
        options: dict[str, Any],
        infos: dict[str, Any],
        observations: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset ``indices`` (env, traffic, ego interface, outcome) as ``EgoTrainingEnv.
        reset`` does; their observations and infos written into the batch's."""
        rows, agent_infos = self.scenes.reset_scenes(indices, seeds, options)
        views = self.scenes.views()
        if observations is None:
            observations = np.zeros((self.num_envs, *self.single_observation_space.shape))
            observations = observations.astype(np.float32)
        if self._env_obs is None:
            size = rows[0][EGO].shape[0]
            self._env_obs = np.zeros((self.num_envs, size), dtype=np.float32)
        self._env_obs = self._env_obs.copy()
        for index, seed, row, info in zip(indices, seeds, rows, agent_infos, strict=True):
            self.traffic.reset_scene(index, views[index], seed)
            self.interfaces[index].reset(views[index])
            self._env_obs[index] = row[EGO]
            observations[index] = self.interfaces[index].observe(row[EGO], views[index])
            infos = self._add_info(infos, info[EGO], index)
        self._outcome[:, indices] = 0.0
        self._views = views
        return observations, infos

    def _seeds(self, seed: Any) -> list[int | None]:
        """One seed per scene: ``seed + b``, the list given, or None each."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, (bool, np.bool_)):
            check_reset_arguments(seed, None)
            return [int(seed) + index for index in range(self.num_envs)]
        if not isinstance(seed, Sequence) or isinstance(seed, str) or len(seed) != self.num_envs:
            raise TypeError(
                f"reset(seed=...) must be None, an int >= 0 or a list of num_envs = "
                f"{self.num_envs} ints / None, got {seed!r:.60}"
            )
        return [check_reset_arguments(item, None)[0] for item in seed]

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``actions`` as an (N, 2) float64 (N int with maneuver actions) array, or a
        ValueError naming the argument."""
        array = np.asarray(actions)
        if self._discrete:
            count = self.single_action_space.n
            if array.shape != (self.num_envs,) or array.dtype.kind not in "iu":
                raise ValueError(
                    f"actions must be {self.num_envs} maneuver indices (ints of shape "
                    f"({self.num_envs},)), got shape {array.shape} dtype {array.dtype}"
                )
            if np.any((array < 0) | (array >= count)):
                raise ValueError(f"actions must be maneuver indices in [0, {count}), got {array}")
            return array.astype(np.int64)
        if array.shape != (self.num_envs, 2) or array.dtype.kind not in "fiu":
            raise ValueError(
                f"actions must be a numeric array of shape (num_envs, 2) = ({self.num_envs}, "
                f"2); got shape {array.shape} dtype {array.dtype}"
            )
        array = array.astype(np.float64)
        if not np.isfinite(array).all():
            raise ValueError(
                f"actions must be finite, got NaN/inf in rows "
                f"{np.flatnonzero(~np.isfinite(array).all(axis=1)).tolist()}"
            )
        return array

    def _ego_actions(
        self, actions: np.ndarray, env_obs: np.ndarray, views: list[SceneView], substep: int
    ) -> np.ndarray:
        """(N, 2) the ego's env actions (accel [m/s^2], yaw rate [rad/s])."""
        if not self._per_scene:  # the whole batch at once
            normalized = self.interfaces[0].normalize_actions
            return scale_action(actions, self.config.dynamics) if normalized else actions
        return np.stack(
            [
                interface.env_action(action, observation, view, substep)
                for interface, action, observation, view in zip(
                    self.interfaces, actions, env_obs, views, strict=True
                )
            ]
        )

    def _observe(self, env_obs: np.ndarray, views: list[SceneView], mask: np.ndarray) -> np.ndarray:
        """The policy's observations of the scenes in ``mask`` (the env's, with the maneuver
        features when enabled)."""
        indices = np.flatnonzero(mask)
        if self.interfaces[0].features is None:
            return env_obs[mask]
        if not indices.size:
            return np.zeros((0, *self.single_observation_space.shape), np.float32)
        return np.stack(
            [self.interfaces[i].observe(env_obs[i], views[i]) for i in indices]
        ).reshape(len(indices), -1)


def build_vector_env(config: EgoEnvConfig, num_envs: int, seed: int = 0) -> EgoVectorEnv:
    """``num_envs`` scenes of the training env of ``config`` (not yet reset): the vector
    counterpart of :func:`~policies.rl.envs.build_env`. Scene ``b``'s adversary draws its
    noise from ``seed + b`` (until ``reset(seed=s)`` reseeds it with ``s + b``)."""
    return EgoVectorEnv(
        num_envs,
        config=config.env,
        scenarios=training_scenes(config),
        policy=make_traffic(config.traffic, seed=seed),
        **interface_options(config),
    )


def ego_vector_entry_point(
    num_envs: int,
    config: EnvConfig | None = None,
    scenarios: ScenarioSource | Sequence[Scenario] | Scenario | None = None,
    policy: ScenePolicy | None = None,
    render_mode: str | None = None,
    **interface: Any,
) -> EgoVectorEnv:
    """``RiskFlowEgo-v0``'s vector entry point: ``gymnasium.make_vec("RiskFlowEgo-v0",
    num_envs=N, vectorization_mode="vector_entry_point", **kwargs)`` is N scenes of
    ``gymnasium.make("RiskFlowEgo-v0", **kwargs)`` as one :class:`EgoVectorEnv`, with the
    single env's spaces (the env's observation; its (accel [m/s^2], yaw rate [rad/s])
    actions, ``normalize_actions=False``) unless ``**interface`` (:class:`EgoVectorEnv`'s)
    asks for another; ``render_mode`` must be None (the vector env does not render)."""
    if render_mode is not None:
        raise ValueError(
            f"render_mode must be None for the vector env, got {render_mode!r}: render one "
            "scene with gymnasium.make('RiskFlowEgo-v0', render_mode=...)"
        )
    interface.setdefault("normalize_actions", False)
    return EgoVectorEnv(num_envs, config, scenarios, policy, **interface)
