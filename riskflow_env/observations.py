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

import functools

import numpy as np

from riskflow_env._array import Array, namespace
from riskflow_env.config import DynamicsConfig, ObservationConfig
from riskflow_env.dynamics import YAW
from riskflow_env.geometry import from_frame
from riskflow_env.maps import DrivableMap
from riskflow_env.maps.sampling import constant_like
from riskflow_env.risk import MAX_INTERACTION_DISTANCE, NUM_PAIR_FEATURES
from riskflow_env.state import SceneState

OWN_FEATURES = ("speed", "accel", "yaw_rate", "length", "width", "sdf")
NEIGHBOR_FEATURES = 3  # length, width, presence, after the pair features


def observation_size(config: ObservationConfig) -> int:
    """Length of one agent's observation vector."""
    neighbor = config.num_neighbors * (NUM_PAIR_FEATURES + NEIGHBOR_FEATURES)
    return len(OWN_FEATURES) + neighbor + config.ray_directions * len(config.ray_distances)


def observation_bounds(
    config: ObservationConfig, dynamics: DynamicsConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 of every entry where a physical bound holds (the dynamics'
    action bounds for the last action, 0 for speeds, sizes and the normalised distance,
    the 50 m interaction range for a neighbour's dx and dy, [-1, 1] for cosines and sines,
    [0, 1] for the TTC risk weight and the presence flag); +-inf elsewhere (SDF values,
    relative velocities)."""
    inf = np.inf
    own = [
        (0.0, inf),
        (dynamics.accel_min, dynamics.accel_max),
        (-dynamics.yaw_rate_max, dynamics.yaw_rate_max),
        (0.0, inf),
        (0.0, inf),
        (-inf, inf),
    ]
    reach = MAX_INTERACTION_DISTANCE
    pair = [
        (-reach, reach),
        (-reach, reach),
        (-1.0, 1.0),
        (-1.0, 1.0),
        (-inf, inf),
        (-inf, inf),
        (0.0, inf),
        (0.0, 1.0),
    ]
    neighbor = pair + [(0.0, inf), (0.0, inf), (0.0, 1.0)]
    rays = [(-inf, inf)] * (config.ray_directions * len(config.ray_distances))
    bounds = np.array(own + neighbor * config.num_neighbors + rays, dtype=np.float32)
    return bounds[:, 0].copy(), bounds[:, 1].copy()


def ray_offsets(config: ObservationConfig) -> np.ndarray:
    """(K * D, 2) SDF sample offsets in the agent's frame [m]."""
    angles = 2.0 * np.pi * np.arange(config.ray_directions) / max(config.ray_directions, 1)
    distances = np.asarray(config.ray_distances, dtype=float)
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (K, 2)
    return (unit[:, None, :] * distances[None, :, None]).reshape(-1, 2)


@functools.lru_cache(maxsize=16)
def _sample_offsets(config: ObservationConfig) -> np.ndarray:
    """(2, 1 + K * D) read-only SDF sample offsets (x row, y row) [m]: centre, then rays."""
    offsets = np.concatenate([np.zeros((1, 2)), ray_offsets(config)]).T.copy()
    offsets.setflags(write=False)
    return offsets


def sample_points(current: Array, config: ObservationConfig) -> Array:
    """World points of each agent's map SDF samples: its centre, then the rays.

    Args:
        current: (..., A, 4) agent states (x [m], y [m], v [m/s], psi [rad]).
        config: ray layout.

    Returns:
        (..., A, 1 + K * D, 2) [m].
    """
    xp = namespace(current)
    x, y, yaw = current[..., 0, None], current[..., 1, None], current[..., YAW, None]
    cos, sin = xp.cos(yaw), xp.sin(yaw)
    offsets = constant_like(_sample_offsets(config), current)
    forward, left = offsets[0], offsets[1]  # (P,) each, centre first
    dx, dy = from_frame(forward, left, cos, sin)
    return xp.stack([x + dx, y + dy], axis=-1)


def observe(
    state: SceneState,
    pair_features: Array,
    pair_mask: Array,
    drivable_map: DrivableMap,
    config: ObservationConfig,
    sdf: Array | None = None,
) -> Array:
    """Observations of all slots at once.

    Works on one scene (a :class:`SceneState`, leading dims ``(A,)``) and on a batch of
    scenes sharing one map (any object with the same ``current``, ``last_action``,
    ``length``, ``width`` and ``present`` arrays, leading dims ``(..., A)``), with numpy
    arrays or torch tensors.

    Args:
        state: the scene state: ``current`` (..., A, 4), ``last_action`` (..., A, 2),
            ``length``, ``width`` (..., A) [m], ``present`` (..., A) bool.
        pair_features: (..., A, A, 8) from :func:`riskflow_env.risk.pairwise_features`.
        pair_mask: (..., A, A) bool, which pairs are observed (see ``pairwise_features``).
        drivable_map: the scene's map.
        config: observation layout.
        sdf: (..., A, 1 + K * D) the map SDF [m] at :func:`sample_points`, when the
            caller has looked it up already (one lookup for all points of a step).

    Returns:
        (..., A, observation_size(config)) float32; rows of empty slots are zeros.
    """
    current = state.current
    xp = namespace(current)
    num_agents = current.shape[-2]
    if sdf is None:
        sdf = drivable_map.sdf_at(sample_points(current, config))  # (..., A, 1 + K*D)

    length, width = state.length, state.width
    own = xp.stack(
        [
            current[..., 2],
            state.last_action[..., 0],
            state.last_action[..., 1],
            length,
            width,
            sdf[..., 0],
        ],
        axis=-1,
    )

    count = config.num_neighbors
    distance = xp.where(
        pair_mask, xp.hypot(pair_features[..., 0], pair_features[..., 1]), float("inf")
    )
    order = xp.argsort(distance, axis=-1, stable=True)[..., :count]  # (..., A, min(N, A))
    seen = xp.take_along_axis(pair_mask, order, axis=-1)
    neighbor_length = xp.take_along_axis(length[..., None, :], order, axis=-1)
    neighbor_width = xp.take_along_axis(width[..., None, :], order, axis=-1)
    neighbor = (
        xp.concat(
            [
                xp.take_along_axis(pair_features, order[..., None], axis=-2),
                xp.stack([neighbor_length, neighbor_width, xp.ones_like(neighbor_length)], -1),
            ],
            axis=-1,
        )
        * seen[..., None]
    )
    lead = tuple(neighbor.shape[:-2])
    if order.shape[-1] < count:  # fewer slots than observed neighbours: pad with absent ones
        pad = xp.zeros(lead + (count - order.shape[-1], neighbor.shape[-1]), dtype=neighbor.dtype)
        neighbor = xp.concat([neighbor, pad], axis=-2)

    observation = xp.concat(
        [own, xp.reshape(neighbor, lead[:-1] + (num_agents, -1)), sdf[..., 1:]], axis=-1
    )
    return xp.astype(xp.where(state.present[..., None], observation, 0.0), xp.float32)
