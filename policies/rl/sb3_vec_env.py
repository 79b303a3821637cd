"""Stable-Baselines3 ``VecEnv`` over :class:`~policies.rl.vector_env.EgoVectorEnv`.

SB3's vector API (stable_baselines3/common/vec_env/base_vec_env.py) differs from
Gymnasium's: ``reset()`` takes no arguments (seeds come from ``VecEnv.seed(s)``, which
keeps ``s + i`` for env ``i`` until the next reset), ``step_wait`` returns
``(obs, rewards, dones, infos)`` with one info dict per env, and a finished env is reset
in the same step, its last observation in ``info["terminal_observation"]`` and
``info["TimeLimit.truncated"]`` telling a time limit from a termination (as
``DummyVecEnv`` does). :class:`EgoVectorEnv` already resets finished scenes in the same
step (``AutoresetMode.SAME_STEP``), so the adapter only changes the layout; the scenes
step as one batch.

    from policies.rl.sb3_vec_env import sb3_ego_vec_env
    venv = sb3_ego_vec_env(EgoVectorEnv(8, policy=RiskFlowAdversary(k=5)))
    PPO("MlpPolicy", venv, seed=0).learn(10_000)

Needs the ``rl`` extra (stable-baselines3).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from policies.rl.vector_env import EgoVectorEnv
from policies.rl.vector_infos import scene_info


class SB3EgoVecEnv(VecEnv):
    """An :class:`EgoVectorEnv` as an SB3 ``VecEnv`` (module docstring).

    Args:
        env: the vector env (its scenes are SB3's envs).
    """

    def __init__(self, env: EgoVectorEnv) -> None:
        if not isinstance(env, EgoVectorEnv):
            raise TypeError(f"env must be an EgoVectorEnv, got {type(env).__name__}")
        if env.autoreset_mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                "env must reset finished scenes in the same step (SB3's convention): build it "
                f"with autoreset_mode='SameStep', got {env.autoreset_mode.value!r}"
            )
        self.env = env
        self._actions: np.ndarray | None = None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)

    def reset(self) -> np.ndarray:
        """Reset every scene, with the seeds of the last ``seed(...)`` if any."""
        seeds = None if all(seed is None for seed in self._seeds) else list(self._seeds)
        options = self._options[0] or None
        observations, infos = self.env.reset(seed=seeds, options=options)
        self.reset_infos = [scene_info(infos, index) for index in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async(actions)")
        observations, rewards, terminated, truncated, infos = self.env.step(self._actions)
        self._actions = None
        dones = terminated | truncated
        scene_infos = []
        for index in range(self.num_envs):
            if dones[index]:
                info = scene_info(infos["final_info"], index)
                info["terminal_observation"] = infos["final_obs"][index]
                self.reset_infos[index] = scene_info(infos, index)
            else:
                info = scene_info(infos, index)
            info["TimeLimit.truncated"] = bool(truncated[index] and not terminated[index])
            scene_infos.append(info)
        return observations, rewards.astype(np.float32), dones, scene_infos

    def close(self) -> None:
        self.env.close()

    def _indices(self, indices: Any) -> list[int]:
        return list(self._get_indices(indices))

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """The vector env's attribute, once per requested env (they share it)."""
        value = getattr(self.env, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set an attribute of the vector env (shared by every scene: all indices only)."""
        if len(self._indices(indices)) != self.num_envs:
            raise ValueError("set_attr: the scenes share one vector env; set it for all")
        setattr(self.env, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of the vector env once (e.g. ``set_adversary_stage``, which sets
        every scene's adversary); its result repeated per requested env."""
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False for _ in self._indices(indices)]


def sb3_ego_vec_env(env: EgoVectorEnv, monitor: bool = True) -> VecEnv:
    """``env`` as an SB3 ``VecEnv``; with ``monitor``, in ``VecMonitor`` (episode returns
    and lengths in ``info["episode"]``, as ``Monitor`` gives SB3's logger)."""
    vec_env = SB3EgoVecEnv(env)
    return VecMonitor(vec_env) if monitor else vec_env


__all__: Sequence[str] = ["SB3EgoVecEnv", "sb3_ego_vec_env"]
