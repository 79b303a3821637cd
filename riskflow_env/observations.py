"""Per-agent observations: one flat float32 vector with the same layout for every agent.

Layout (``observation_size(config)`` entries):

==========================  =================================================================
block                       contents
==========================  =================================================================
own (6)                     speed [m/s], last accel [m/s^2], last yaw rate [rad/s],
                            length [m], width [m], SDF at the centre [m]
neighbours (N x 11)         the N nearest other vehicles within 50 m, nearest first, in the
                            agent's frame: the 8 pair features of :mod:`riskflow_env.risk`
                            (dx, dy, cos/sin relative heading, dvx, dvy, normalised
                            distance, TTC risk weight), their length and width [m], and a
                            1/0 presence flag; absent neighbours are all zeros
map rays (K x D)            the map SDF [m] at distances D along K directions spread
                            evenly around the agent's heading (negative = on the road)
==========================  =================================================================
"""

from __future__ import annotations

import numpy as np

from riskflow_env.config import ObservationConfig
from riskflow_env.dynamics import YAW
from riskflow_env.maps import DrivableMap
from riskflow_env.risk import NUM_PAIR_FEATURES
from riskflow_env.state import SceneState

OWN_FEATURES = ("speed", "accel", "yaw_rate", "length", "width", "sdf")
NEIGHBOR_FEATURES = 3  # length, width, presence, after the pair features


def observation_size(config: ObservationConfig) -> int:
    """Length of one agent's observation vector."""
    neighbor = config.num_neighbors * (NUM_PAIR_FEATURES + NEIGHBOR_FEATURES)
    return len(OWN_FEATURES) + neighbor + config.ray_directions * len(config.ray_distances)


def ray_offsets(config: ObservationConfig) -> np.ndarray:
    """(K * D, 2) SDF sample offsets in the agent's frame [m]."""
    angles = 2.0 * np.pi * np.arange(config.ray_directions) / max(config.ray_directions, 1)
    distances = np.asarray(config.ray_distances, dtype=float)
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (K, 2)
    return (unit[:, None, :] * distances[None, :, None]).reshape(-1, 2)


def observe(
    state: SceneState,
    pair_features: np.ndarray,
    pair_mask: np.ndarray,
    drivable_map: DrivableMap,
    config: ObservationConfig,
) -> np.ndarray:
    """Observations of all slots at once.

    Args:
        state: the scene state.
        pair_features: (A, A, 8) from :func:`riskflow_env.risk.pairwise_features`.
        pair_mask: (A, A) bool, which pairs are observed (see ``pairwise_features``).
        drivable_map: the scene's map.
        config: observation layout.

    Returns:
        (A, observation_size(config)) float32; rows of empty slots are zeros.
    """
    current = state.current
    num_agents = state.num_agents
    xy, yaw = current[:, :2], current[:, YAW]
    cos, sin = np.cos(yaw), np.sin(yaw)
    rotation = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)  # (A, 2, 2)

    offsets = ray_offsets(config)
    points = np.concatenate([np.zeros((1, 2)), offsets])  # centre first
    world = xy[:, None, :] + np.einsum("aij,kj->aki", rotation, points)
    sdf = drivable_map.sdf_at(world)  # (A, 1 + K*D)

    own = np.stack(
        [
            current[:, 2],
            state.last_action[:, 0],
            state.last_action[:, 1],
            state.length,
            state.width,
            sdf[:, 0],
        ],
        axis=-1,
    )

    count = config.num_neighbors
    distance = np.where(pair_mask, np.hypot(pair_features[..., 0], pair_features[..., 1]), np.inf)
    order = np.argsort(distance, axis=-1, kind="stable")[:, :count]  # (A, min(N, A))
    seen = np.take_along_axis(pair_mask, order, axis=-1)
    neighbor = (
        np.concatenate(
            [
                np.take_along_axis(pair_features, order[..., None], axis=1),
                state.length[order][..., None],
                state.width[order][..., None],
                np.ones(order.shape + (1,)),
            ],
            axis=-1,
        )
        * seen[..., None]
    )
    if order.shape[1] < count:  # fewer slots than observed neighbours: pad with absent ones
        pad = np.zeros((num_agents, count - order.shape[1], neighbor.shape[-1]))
        neighbor = np.concatenate([neighbor, pad], axis=1)

    observation = np.concatenate([own, neighbor.reshape(num_agents, -1), sdf[:, 1:]], axis=-1)
    return np.where(state.present[:, None], observation, 0.0).astype(np.float32)
