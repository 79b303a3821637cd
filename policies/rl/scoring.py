"""A maneuver-scoring policy for Stable-Baselines3 PPO: one small network scores every maneuver.

With maneuver actions and maneuver features (:mod:`policies.rl.features`) the observation
ends in two blocks of ``M`` values, the predicted clearance and road margin of each
maneuver, and the action picks one of the ``M`` maneuvers. SB3's ``MlpPolicy`` maps the
whole vector to ``M`` logits through one MLP, so it must learn the same "a free, on-road
maneuver that keeps moving is good" rule ``M`` times over. :class:`ManeuverScoringPolicy`
instead gives every maneuver the same scorer, its weights shared over the maneuvers (as
DRRN scores each action from its own features: He et al., *Deep Reinforcement Learning
with a Natural Language Action Space*, ACL 2016):

    logit_m = f(gap_m, edge_m, descriptor_m, context(env observation))

with ``descriptor_m`` the maneuver's acceleration, its first and last yaw rate (a lane
change or a turn) and ``context`` an MLP embedding of the env's own observation (the ego's
speed, its neighbours). The critic reads the context and the logits. The policy is
selected by ``examples/train_ego_ppo.py --policy scoring`` and loads like any SB3 policy.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from policies.rl.features import maneuvers

POLICIES = ("mlp", "scoring")
LAST_LAYER_GAIN = 0.01  # small first logits: the untrained policy is near uniform


def sb3_policy(options: Any) -> tuple[str | type[ActorCriticPolicy], dict[str, Any]]:
    """SB3's policy and ``policy_kwargs`` for training options with ``policy``,
    ``maneuver_actions``, ``maneuver_features``, ``maneuver_set`` and ``log_std_init``
    (``examples/train_ego_ppo.py``); a ``ValueError`` names the option that does not fit."""
    if options.policy not in POLICIES:
        raise ValueError(f"--policy must be one of {POLICIES}, got {options.policy!r}")
    if options.policy == "scoring":
        if not (options.maneuver_actions and options.maneuver_features):
            raise ValueError("--policy scoring needs --maneuver-actions and --maneuver-features")
        kwargs = {"features_extractor_kwargs": {"maneuver_set": options.maneuver_set}}
        return ManeuverScoringPolicy, kwargs
    if options.maneuver_actions:
        return "MlpPolicy", {}
    return "MlpPolicy", {"log_std_init": options.log_std_init}


def descriptors(maneuver_set: str) -> np.ndarray:
    """(M, 3) per maneuver: acceleration / 8 m/s^2, first and last yaw rate / 0.3 rad/s."""
    chosen = maneuvers(maneuver_set=maneuver_set)
    return np.stack(
        [chosen[:, 0, 0] / 8.0, chosen[:, 0, 1] / 0.3, chosen[:, -1, 1] / 0.3], axis=-1
    ).astype(np.float32)


class ManeuverScorer(BaseFeaturesExtractor):
    """Features ``[logits (M), context (C)]`` of an observation ``[env (D), gap (M), edge (M)]``.

    Args:
        observation_space: the policy's observation space (size ``D + 2 M``).
        maneuver_set: which maneuvers (:func:`policies.rl.features.maneuvers`).
        context: size ``C`` of the embedding of the env's observation.
        hidden: width of the scorer's hidden layers.
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        maneuver_set: str = "mpc",
        context: int = 32,
        hidden: int = 64,
    ) -> None:
        described = torch.as_tensor(descriptors(maneuver_set))
        count = len(described)
        env_size = int(observation_space.shape[0]) - 2 * count
        if env_size < 1:
            raise ValueError(
                f"the observation ({observation_space.shape[0]} values) has no room for the "
                f"features of {count} maneuvers: train with --maneuver-features"
            )
        super().__init__(observation_space, features_dim=count + context)
        self.count, self.env_size = count, env_size
        self.register_buffer("described", described)
        self.context = nn.Sequential(nn.Linear(env_size, context), nn.Tanh())
        self.scorer = nn.Sequential(
            nn.Linear(2 + described.shape[1] + context, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, 1),
        )

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        env, gap, edge = torch.split(observations, [self.env_size, self.count, self.count], -1)
        context = self.context(env)  # (B, C)
        batch = observations.shape[0]
        per_maneuver = torch.cat(
            [
                gap[..., None],
                edge[..., None],
                self.described.expand(batch, -1, -1),
                context[:, None, :].expand(-1, self.count, -1),
            ],
            dim=-1,
        )  # (B, M, 2 + 3 + C)
        return torch.cat([self.scorer(per_maneuver)[..., 0], context], dim=-1)


class _Logits(nn.Module):
    """The first ``count`` features: the scorer's logits are the action distribution's."""

    def __init__(self, count: int) -> None:
        super().__init__()
        self.count = count

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return latent[..., : self.count]


class ManeuverScoringPolicy(ActorCriticPolicy):
    """SB3 actor-critic whose logits are :class:`ManeuverScorer`'s (module docstring).

    ``policy_kwargs``: ``features_extractor_kwargs={"maneuver_set": ...}``; the actor adds
    no layer (``net_arch["pi"] == []``), the critic two of 64.
    """

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("features_extractor_class", ManeuverScorer)
        kwargs.setdefault("net_arch", {"pi": [], "vf": [64, 64]})
        super().__init__(*args, **kwargs)

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)
        if self.mlp_extractor.latent_dim_pi != self.features_extractor.features_dim:
            raise ValueError('ManeuverScoringPolicy needs net_arch["pi"] == [] (no actor layer)')
        self.action_net = _Logits(self.features_extractor.count)
        last = self.features_extractor.scorer[-1]
        nn.init.orthogonal_(last.weight, gain=LAST_LAYER_GAIN)
        nn.init.zeros_(last.bias)
        self.optimizer = self.optimizer_class(
            self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )
