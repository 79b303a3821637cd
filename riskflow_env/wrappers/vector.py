"""Stable-Baselines3 vector env over a parallel env, through SuperSuit, with a working seed.

SuperSuit's chain ``pettingzoo_env_to_vec_env_v1`` + ``concat_vec_envs_v1(...,
base_class="stable_baselines3")`` turns every agent of every copy of a ``ParallelEnv`` into
one row of an SB3 ``VecEnv`` (parameter sharing: one policy acts for all rows). SB3 >= 2
calls ``VecEnv.seed`` (``PPO(..., seed=0)``); SuperSuit <= 3.11's ``SB3VecEnvWrapper``
passes it to its ``ConcatVecEnv``, which has none (``AttributeError: 'ConcatVecEnv'
object has no attribute 'seed'``), and its ``reset(seed=...)`` drops the seed.
:func:`sb3_vec_env` is that chain with both fixed: the seed is kept for the next reset,
as SB3's own ``VecEnv.seed`` does ("those seeds will only be passed to the environment at
the next reset", stable_baselines3/common/vec_env/base_vec_env.py), and copy ``i`` of the
env is reset with ``seed + i`` (SuperSuit's ``ConcatVecEnv.reset``).

SuperSuit's vector env wants an observation for every possible agent at every step: wrap
``riskflow_v0`` in :class:`~riskflow_env.wrappers.FixedRosterEnv` first.
"""

from __future__ import annotations

from typing import Any

from riskflow_env.config import is_integer


def sb3_vec_env(env: Any, num_envs: int = 1, num_cpus: int = 0) -> Any:
    """An SB3 ``VecEnv`` of ``num_envs`` copies of ``env`` x its ``possible_agents`` rows.

    Args:
        env: a PettingZoo ``ParallelEnv`` whose agents are all live until the episode ends
            together (:class:`~riskflow_env.wrappers.FixedRosterEnv`), with identical spaces.
        num_envs: copies of ``env`` (each a deep copy, as SuperSuit makes them).
        num_cpus: processes to step the copies in (0: in this process).

    Needs the ``rl`` extra (supersuit, stable-baselines3).
    """
    from pettingzoo import ParallelEnv

    if not isinstance(env, ParallelEnv):
        raise TypeError(f"env must be a PettingZoo ParallelEnv, got {type(env).__name__}")
    for name, value, minimum in (("num_envs", num_envs, 1), ("num_cpus", num_cpus, 0)):
        if not is_integer(value) or value < minimum:
            raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    try:
        import supersuit
        from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper
    except ImportError as error:
        raise ImportError(
            "sb3_vec_env needs supersuit and stable-baselines3: pip install 'riskflow-env[rl]'"
        ) from error

    class SeededSB3VecEnv(SB3VecEnvWrapper):
        """SuperSuit's SB3 wrapper with ``seed`` and a seeded ``reset``."""

        _next_seed: int | None = None

        def seed(self, seed: int | None = None) -> list[int | None]:
            self._next_seed = seed  # used by the next reset
            return [seed] * self.num_envs

        def reset(self, seed: int | None = None, options: dict | None = None):
            seed, self._next_seed = (self._next_seed if seed is None else seed), None
            observations, self.reset_infos = self.venv.reset(seed=seed, options=options)
            return observations

    vec_env = supersuit.pettingzoo_env_to_vec_env_v1(env)
    concat = supersuit.concat_vec_envs_v1(vec_env, num_envs, num_cpus, base_class="gymnasium")
    return SeededSB3VecEnv(concat)
