"""Per-step features of WOSAC-style realism (Montali et al. 2023, 2024 challenge).

Each feature is an (A, T) array with its own validity, computed the same way for the
simulated tracks and for the logged reference (:func:`wosac_features`). They follow
the Waymo Open Dataset's ``sim_agents_metrics`` code, in 2-D:

* kinematics from finite differences of positions and headings (the states' ``v`` is
  not used): ``linear_speed_t = ||xy_{t+1} - xy_{t-1}|| / (2 dt)`` [m/s],
  ``linear_acceleration_t`` = central difference of the speed [m/s^2],
  ``angular_speed_t = wrap(psi_{t+1} - psi_{t-1}) / (2 dt)`` [rad/s],
  ``angular_acceleration_t`` = wrapped central difference of the angular speed
  [rad/s^2]; valid where the states used are (one / two steps either side);
* ``distance_to_nearest_object`` [m]: the signed distance between boxes, the Euclidean
  gap when apart and minus the penetration depth when overlapping, to the nearest other
  valid vehicle (``inf`` when alone);
* ``collision_indication``: that distance is ``<= 0``. WOSAC uses ``< 0``; ``<= 0``
  matches the env's collision test (touching counts);
* ``time_to_collision`` [s]: WOSAC's definition, not :mod:`riskflow_env.risk`'s: along
  the heading, to the nearest vehicle *ahead* that the agent follows (its box ahead of
  the agent's front, laterally overlapping the agent's straight trail, heading within
  75 deg, or within 10 deg when the lateral overlap is under 0.5 m), at constant
  speeds: ``gap / (v - v_ahead)`` when closing, clipped to ``MAX_TTC``; ``MAX_TTC``
  when following nothing or opening. Speeds are the states' ``v``; heading differences
  are wrapped to [-pi, pi] (the WOSAC code takes the raw difference);
* ``distance_to_road_edge`` [m]: the largest map SDF over the 9 footprint points
  (positive off the road; WOSAC uses the 4 corners and road-edge polylines);
* ``offroad_indication``: that distance is ``> 0``, the env's off-road event.
"""

from __future__ import annotations

import math

import numpy as np

from riskflow_env.dynamics import SPEED, YAW, wrap_angle
from riskflow_env.geometry import box_corners, separation, to_frame
from riskflow_env.kernel_loading import optional_kernels
from riskflow_env.maps import DrivableMap
from riskflow_env.metrics.safety import footprint_sdf

MAX_TTC = 5.0  # [s] TTC clip and value when following nothing (WOSAC)
MAX_FOLLOW_HEADING = math.radians(75.0)  # [rad] heading difference to count as following
MAX_FOLLOW_HEADING_SMALL_OVERLAP = math.radians(10.0)  # [rad] same, small lateral overlap
SMALL_OVERLAP = 0.5  # [m] lateral overlap below which the stricter heading bound applies

WOSAC_FEATURES = (
    "linear_speed",
    "linear_acceleration",
    "angular_speed",
    "angular_acceleration",
    "distance_to_nearest_object",
    "collision_indication",
    "time_to_collision",
    "distance_to_road_edge",
    "offroad_indication",
)


def _central(values: np.ndarray) -> np.ndarray:
    """(A, T) -> (A, T) central difference ``(f_{t+1} - f_{t-1}) / 2``, NaN at both ends."""
    out = np.full(values.shape, np.nan)
    out[:, 1:-1] = 0.5 * (values[:, 2:] - values[:, :-2])
    return out


def _central_valid(valid: np.ndarray) -> np.ndarray:
    """(A, T) bool: both neighbours valid (False at both ends)."""
    out = np.zeros(valid.shape, dtype=bool)
    out[:, 1:-1] = valid[:, 2:] & valid[:, :-2]
    return out


def kinematic_features(
    states: np.ndarray, valid: np.ndarray, dt: float
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """WOSAC's four kinematic features, ``name -> (values (A, T), valid (A, T))``."""
    with np.errstate(invalid="ignore"):
        step = np.stack([_central(states[..., 0]), _central(states[..., 1])], axis=-1)
        speed = np.linalg.norm(step, axis=-1) / dt
        accel = _central(speed) / dt
        # Wrap twice the half-difference, then halve: the 2-step heading change is taken
        # as the acute one (WOSAC's trajectory_features).
        yaw_step = wrap_angle(2.0 * _central(states[..., YAW])) / 2.0
        yaw_accel_step = wrap_angle(2.0 * _central(yaw_step)) / 2.0
    speed_ok = _central_valid(valid)
    accel_ok = _central_valid(speed_ok)
    return {
        "linear_speed": (speed, speed_ok),
        "linear_acceleration": (accel, accel_ok),
        "angular_speed": (yaw_step / dt, speed_ok),
        "angular_acceleration": (yaw_accel_step / dt**2, accel_ok),
    }


def _pair_frame(states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per step t, pair (i, j): j's centre in i's frame and the heading difference.

    Returns (T, A, A) arrays: forward and left offsets [m], cos and sin of
    ``psi_j - psi_i``.
    """
    x, y, yaw = states[..., 0].T, states[..., 1].T, states[..., YAW].T  # (T, A)
    dx, dy = x[:, None, :] - x[:, :, None], y[:, None, :] - y[:, :, None]
    cos_i, sin_i = np.cos(yaw)[:, :, None], np.sin(yaw)[:, :, None]
    dyaw = yaw[:, None, :] - yaw[:, :, None]
    return *to_frame(dx, dy, cos_i, sin_i), np.cos(dyaw), np.sin(dyaw)


def box_signed_distance(states: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Signed distance between the boxes of every pair at every step.

    Args:
        states: (A, T, 4) states.
        length: (A,) lengths [m].
        width: (A,) widths [m].

    Returns:
        (T, A, A) [m]: the Euclidean distance between disjoint boxes, minus the
        penetration depth (SAT separation, exact for rectangles) for overlapping ones.
        The diagonal is meaningless (a box overlaps itself).
    """
    xy, yaw = states[..., :2].transpose(1, 0, 2), states[..., YAW].T  # (T, A, 2), (T, A)
    sep = separation(
        xy[:, :, None], yaw[:, :, None], length[:, None], width[:, None],
        xy[:, None, :], yaw[:, None, :], length[None, :], width[None, :],
    )  # fmt: skip
    # Two disjoint convex polygons are closest at a vertex of one of them: the distance
    # is the smallest corner-to-box distance, corners of j to box i and of i to box j.
    corners = box_corners(xy, yaw, length, width)  # (T, A, 4, 2)
    rel = corners[:, None, :, :, :] - xy[:, :, None, None, :]  # (T, i, j, 4, 2)
    cos_i, sin_i = np.cos(yaw)[:, :, None, None], np.sin(yaw)[:, :, None, None]
    forward, left = to_frame(rel[..., 0], rel[..., 1], cos_i, sin_i)
    out_x = np.maximum(np.abs(forward) - 0.5 * length[None, :, None, None], 0.0)
    out_y = np.maximum(np.abs(left) - 0.5 * width[None, :, None, None], 0.0)
    to_box_i = np.hypot(out_x, out_y).min(axis=-1)  # (T, i, j): corners of j to box i
    distance = np.minimum(to_box_i, to_box_i.transpose(0, 2, 1))
    return np.where(sep > 0, distance, sep)


def interaction_features(
    states: np.ndarray, valid: np.ndarray, length: np.ndarray, width: np.ndarray
) -> dict[str, np.ndarray]:
    """Distance to the nearest object, collision flag and TTC, each (A, T)."""
    num_agents = states.shape[0]
    pair_ok = valid.T[:, :, None] & valid.T[:, None, :] & ~np.eye(num_agents, dtype=bool)
    kernels = optional_kernels("riskflow_env.metrics.wosac_kernels", "the compiled WOSAC distances")
    if kernels is not None:  # the same distances, each pair once and the far ones skipped
        nearest = np.empty(valid.shape)
        kernels.nearest_objects(
            np.ascontiguousarray(states, dtype=np.float64), np.ascontiguousarray(valid),
            np.asarray(length, dtype=np.float64), np.asarray(width, dtype=np.float64), nearest,
        )  # fmt: skip
    else:
        distance = np.where(pair_ok, box_signed_distance(states, length, width), np.inf)
        nearest = distance.min(axis=2).T  # (A, T)

    forward, left, cos_d, sin_d = _pair_frame(states)
    abs_c, abs_s = np.abs(cos_d), np.abs(sin_d)
    half_len, half_wid = 0.5 * length, 0.5 * width
    other_long = half_len[None, None, :] * abs_c + half_wid[None, None, :] * abs_s
    other_lat = half_len[None, None, :] * abs_s + half_wid[None, None, :] * abs_c
    gap = forward - half_len[None, :, None] - other_long  # ahead of i's front
    lat_overlap = np.abs(left) - half_wid[None, :, None] - other_lat  # < 0: in i's trail
    heading_diff = np.abs(np.arctan2(sin_d, cos_d))
    following = (
        pair_ok
        & (gap > 0)
        & (heading_diff <= MAX_FOLLOW_HEADING)
        & (lat_overlap < 0)
        & ((lat_overlap < -SMALL_OVERLAP) | (heading_diff <= MAX_FOLLOW_HEADING_SMALL_OVERLAP))
    )
    gap = np.where(following, gap, np.inf)
    ahead = np.argmin(gap, axis=2)  # (T, A)
    gap_ahead = np.take_along_axis(gap, ahead[..., None], axis=2)[..., 0]
    speed = states[..., SPEED].T  # (T, A)
    closing = speed - np.take_along_axis(speed, ahead, axis=1)
    has_ahead = np.isfinite(gap_ahead)
    closing_ok = has_ahead & (closing > 0)
    ttc = np.where(closing_ok, gap_ahead / np.where(closing_ok, closing, 1.0), MAX_TTC)
    return {
        "distance_to_nearest_object": nearest,
        "collision_indication": nearest <= 0.0,
        "time_to_collision": np.minimum(ttc, MAX_TTC).T,
    }


def wosac_features(
    states: np.ndarray,
    valid: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    dt: float,
    drivable_map: DrivableMap,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """All ``WOSAC_FEATURES`` of one set of tracks.

    Args:
        states: (A, T, 4) (x [m], y [m], v [m/s], psi [rad]).
        valid: (A, T) bool.
        length: (A,) lengths [m].
        width: (A,) widths [m].
        dt: time step [s].
        drivable_map: the scene's map.

    Returns:
        name -> (values (A, T), valid (A, T)); the collision and off-road indications
        are bool. Interactions consider every valid agent.
    """
    features = kinematic_features(states, valid, dt)
    interactions = interaction_features(states, valid, length, width)
    features.update({name: (values, valid) for name, values in interactions.items()})
    road = footprint_sdf(drivable_map, states, length, width).max(axis=-1)
    features["distance_to_road_edge"] = (road, valid)
    features["offroad_indication"] = (road > 0.0, valid)
    return {name: features[name] for name in WOSAC_FEATURES}
