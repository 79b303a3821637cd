"""RiskFlow-Env: safety-critical multi-agent traffic simulation.

``parallel_env(...)`` builds the PettingZoo ``ParallelEnv`` (``riskflow_v0``); ``env(...)``
the AEC view of the same env. See :mod:`riskflow_env.env` for agents, spaces and options.
``gymnasium.make("RiskFlowEgo-v0")`` is the ego's single-agent Gymnasium view
(:class:`riskflow_env.wrappers.EgoEnv`); ``gymnasium.make_vec("RiskFlowEgo-v0",
num_envs=N)`` is N of them stepped as one batch (``policies.rl.EgoVectorEnv``).
"""

from __future__ import annotations

import dataclasses
from importlib.metadata import PackageNotFoundError, version

import gymnasium
from pettingzoo.utils.conversions import parallel_to_aec_wrapper
from pettingzoo.utils.wrappers import OrderEnforcingWrapper

from riskflow_env.config import (
    DynamicsConfig,
    EnvConfig,
    ObservationConfig,
    RewardConfig,
    is_integer,
)
from riskflow_env.env import RiskFlowParallelEnv

try:
    __version__ = version("riskflow-env")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"


if "RiskFlowEgo-v0" not in gymnasium.registry:
    # The vector entry point lives in the sibling package ``policies`` (the batched
    # adversary is a policy); gymnasium imports it only when make_vec asks for it.
    gymnasium.register(
        id="RiskFlowEgo-v0",
        entry_point="riskflow_env.wrappers.ego_env:EgoEnv",
        vector_entry_point="policies.rl.vector_env:ego_vector_entry_point",
    )


def parallel_env(*, max_cycles: int | None = None, **kwargs) -> RiskFlowParallelEnv:
    """The ``riskflow_v0`` PettingZoo ``ParallelEnv``; keyword arguments as
    :class:`RiskFlowParallelEnv` (``config``, ``scenarios``, ``render_mode``).

    ``max_cycles`` (PettingZoo's name for the episode length) sets the config's
    ``episode_steps``: every agent is truncated after that many steps."""
    if max_cycles is not None:
        config = kwargs.get("config") or EnvConfig()
        if not isinstance(config, EnvConfig):
            raise TypeError(f"config must be an EnvConfig, got {type(config).__name__}")
        if not is_integer(max_cycles) or max_cycles < 1:
            raise ValueError(f"max_cycles must be an int >= 1 (steps), got {max_cycles!r}")
        kwargs["config"] = dataclasses.replace(config, episode_steps=max_cycles)
    return RiskFlowParallelEnv(**kwargs)


class AECView(parallel_to_aec_wrapper):
    """:func:`env`'s AEC view: PettingZoo's conversion of the parallel env, which checks
    each action as it is given (an error naming the agent), not when the last agent of
    the cycle steps the parallel env."""

    def step(self, action) -> None:
        agent = self.agent_selection
        if not (self.terminations[agent] or self.truncations[agent]):
            self.env.action_input.check(agent, action)
        super().step(action)


def env(*, max_cycles: int | None = None, **kwargs) -> OrderEnforcingWrapper:
    """The AEC (turn-by-turn) view of :func:`parallel_env`, for AEC-only libraries
    (:class:`AECView`, inside PettingZoo's check that ``reset`` comes first)."""
    return OrderEnforcingWrapper(AECView(parallel_env(max_cycles=max_cycles, **kwargs)))


__all__ = [
    "AECView",
    "DynamicsConfig",
    "EnvConfig",
    "ObservationConfig",
    "RewardConfig",
    "RiskFlowParallelEnv",
    "__version__",
    "env",
    "parallel_env",
]
